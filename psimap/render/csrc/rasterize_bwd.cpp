// Backward rasterization: per pixel, back to front from the last blended surfel, reconstructing
// the transmittance T_i = T_{i+1} / (1 - alpha_i) from the saved final one. Gradients are summed
// per (tile, surfel) bin entry, each tile by whichever thread takes it (no atomics), then reduced
// per surfel in tile order: the sum is the same bits for any thread count and schedule, so
// training stays reproducible on every core.
#include <algorithm>
#include <cstring>
#include <memory>

#include <omp.h>

#include "threads.h"

#include "rasterize.h"

namespace psimap {

namespace {
// Per-surfel gradient slots besides the features.
constexpr int kGT = 0, kGCenter = 9, kGDepthKey = 11, kGNormal = 12, kGOpacity = 15, kGColor = 16;
constexpr int kGSlots = 19;
}  // namespace

void rasterize_backward(const SurfelInputs& in, const TileBins& bins, const RasterConfig& cfg,
                        const ForwardBuffers& saved, const BackwardGrads& g) {
    const int W = cfg.width, H = cfg.height, C = in.channels, K = cfg.topk;
    const int64_t N = in.n;
    const int tiles = bins.tiles_x * bins.tiles_y;
    const float near = cfg.near, far = cfg.far;
    const float* bg = cfg.background;
    const int64_t pairs = bins.offsets[tiles];
    // One gradient row per bin entry (tile, surfel): written by the tile's thread only.
    // (uninitialised: every tile zeroes its own rows)
    std::unique_ptr<float[]> entry_geo(new float[static_cast<size_t>(pairs) * kGSlots]);
    std::unique_ptr<float[]> entry_feat(new float[static_cast<size_t>(pairs) * C + 1]);

#pragma omp parallel num_threads(kernel_threads())
    {
        std::vector<SurfelParams> params;
        std::vector<Footprint> footprints;
        std::vector<Footprint>* fp = cfg.exact_footprint ? &footprints : nullptr;
        std::vector<int32_t> block_pos;
        int32_t block_start[kBlocks * kBlocks + 1];
#pragma omp for schedule(dynamic, 1)
        for (int t = 0; t < tiles; ++t) {
            const int n = bins.offsets[t + 1] - bins.offsets[t];
            if (n == 0) continue;
            gather_tile(in, bins, t, params, fp);
            const int32_t* ids = bins.ids + bins.offsets[t];
            float* tile_geo = entry_geo.get() + static_cast<size_t>(bins.offsets[t]) * kGSlots;
            float* tile_feat = entry_feat.get() + static_cast<size_t>(bins.offsets[t]) * C;
            std::fill(tile_geo, tile_geo + static_cast<size_t>(n) * kGSlots, 0.0f);
            std::fill(tile_feat, tile_feat + static_cast<size_t>(n) * C, 0.0f);
            const int tx = t % bins.tiles_x, ty = t / bins.tiles_x;
            block_lists(params, tx * kTile, ty * kTile, block_pos, block_start, fp);
            const int px1 = std::min(W, (tx + 1) * kTile), py1 = std::min(H, (ty + 1) * kTile);
            for (int py = ty * kTile; py < py1; ++py) {
                for (int px = tx * kTile; px < px1; ++px) {
                    const int64_t pix = static_cast<int64_t>(py) * W + px;
                    const int last = saved.n_last[pix];
                    if (last == 0) continue;
                    const float x = static_cast<float>(px), y = static_cast<float>(py);
                    const float T_final = saved.t_final[pix];
                    const float alpha_out = 1.0f - T_final;
                    const double A = saved.dist_sums[3 * pix], D = saved.dist_sums[3 * pix + 1],
                                 D2 = saved.dist_sums[3 * pix + 2];
                    const float* g_rgb = g.rgb + 3 * pix;
                    const float* g_nrm = g.normal + 3 * pix;
                    const float* g_f = g.feature + pix * C;
                    const float g_dist = g.distortion[pix];
                    const float g_med = g.median[pix];
                    const int med_pos = saved.median_pos[pix];
                    // alpha_out = 1 - T_final; rgb = ... + T_final bg; depth = num / alpha_out.
                    float g_Tf = -g.alpha[pix] + g_rgb[0] * bg[0] + g_rgb[1] * bg[1] + g_rgb[2] * bg[2];
                    float g_num = 0.0f;
                    if (alpha_out > kAlphaOutMin) {
                        g_num = g.depth[pix] / alpha_out;
                        g_Tf += g.depth[pix] * saved.depth[pix] / alpha_out;
                    }
                    const int32_t* sel = K > 0 ? saved.topk_pos + pix * K : nullptr;
                    int sel_k = K - 1;
                    if (K > 0)
                        while (sel_k >= 0 && sel[sel_k] < 0) --sel_k;
                    float T = T_final;
                    float S = g_Tf * T_final;  // sum_{k > i} dL/dw_k w_k + dL/dT_final T_final
                    const int b = block_of(px, py, tx * kTile, ty * kTile);
                    for (int k = block_start[b + 1] - 1; k >= block_start[b]; --k) {
                        const int j = block_pos[k];
                        if (j >= last) continue;
                        const SurfelParams& s = params[j];
                        SurfelHit h;
                        eval_surfel(s, x, y, near, h);
                        const float oG = s.opacity * h.G;
                        const float alpha = std::min(kAlphaMax, oG);
                        if (!(alpha >= kAlphaMin)) continue;
                        const float one_minus = 1.0f - alpha;
                        T = T / one_minus;
                        const float w = alpha * T;
                        bool selected = K == 0;
                        if (K > 0 && sel_k >= 0 && sel[sel_k] == j) {
                            selected = true;
                            --sel_k;
                        }
                        // dDist/dw_i = sum_j w_j (m_i - m_j)^2, dDist/dm_i = 2 w_i (m_i A - D).
                        const double m = ndc_depth_d(h.d, near, far);
                        float g_w = g_rgb[0] * s.color[0] + g_rgb[1] * s.color[1] +
                                    g_rgb[2] * s.color[2] + g_num * h.d +
                                    g_nrm[0] * s.normal[0] + g_nrm[1] * s.normal[1] +
                                    g_nrm[2] * s.normal[2] +
                                    static_cast<float>(g_dist * (m * m * A - 2.0 * m * D + D2));
                        float* tg = tile_geo + static_cast<size_t>(j) * kGSlots;
                        if (selected && C > 0) {
                            const float* f = in.feature + static_cast<int64_t>(ids[j]) * C;
                            float* tf = tile_feat + static_cast<size_t>(j) * C;
                            float dot = 0.0f;
                            for (int c = 0; c < C; ++c) {
                                dot += g_f[c] * f[c];
                                tf[c] += w * g_f[c];
                            }
                            g_w += dot;
                        }
                        const double dm_dd = static_cast<double>(far) * near / ((static_cast<double>(far) - near) * h.d * h.d);
                        float g_d = g_num * w +
                                    static_cast<float>(g_dist * 2.0 * w * (m * A - D) * dm_dd);
                        if (j == med_pos) g_d += g_med;
                        const float g_alpha = T * g_w - S / one_minus;
                        S += g_w * w;
                        for (int c = 0; c < 3; ++c) {
                            tg[kGColor + c] += w * g_rgb[c];
                            tg[kGNormal + c] += w * g_nrm[c];
                        }
                        float g_G = 0.0f;
                        if (oG <= kAlphaMax) {
                            tg[kGOpacity] += g_alpha * h.G;
                            g_G = g_alpha * s.opacity;
                        }
                        eval_surfel_backward(s, x, y, h, g_G, g_d, tg + kGT, tg + kGCenter,
                                             tg + kGDepthKey);
                    }
                }
            }
        }
    }

    // Reduce per surfel in tile order. Each thread owns a contiguous range of surfel ids and walks
    // every entry (ids only: 4 bytes each), adding the rows of its own surfels.
    std::unique_ptr<float[]> acc_geo(new float[static_cast<size_t>(N) * kGSlots + 1]);
#pragma omp parallel num_threads(kernel_threads())
    {
        const int th = omp_get_thread_num(), nth = omp_get_num_threads();
        const int64_t lo = N * th / nth, hi = N * (th + 1) / nth;
        std::fill(acc_geo.get() + lo * kGSlots, acc_geo.get() + hi * kGSlots, 0.0f);
        if (C > 0) std::fill(g.feat + lo * C, g.feat + hi * C, 0.0f);
        for (int64_t e = 0; e < pairs; ++e) {
            const int64_t i = bins.ids[e];
            if (i < lo || i >= hi) continue;
            float* dst = acc_geo.get() + i * kGSlots;
            const float* src = entry_geo.get() + e * kGSlots;
            for (int k = 0; k < kGSlots; ++k) dst[k] += src[k];
            float* dstf = g.feat + i * C;
            const float* srcf = entry_feat.get() + e * C;
            for (int c = 0; c < C; ++c) dstf[c] += srcf[c];
        }
        for (int64_t i = lo; i < hi; ++i) {
            const float* acc = acc_geo.get() + i * kGSlots;
            for (int k = 0; k < 9; ++k) g.T[9 * i + k] = acc[kGT + k];
            g.center[2 * i] = acc[kGCenter];
            g.center[2 * i + 1] = acc[kGCenter + 1];
            g.depth_key[i] = acc[kGDepthKey];
            for (int k = 0; k < 3; ++k) {
                g.normal_c[3 * i + k] = acc[kGNormal + k];
                g.color[3 * i + k] = acc[kGColor + k];
            }
            g.opacity[i] = acc[kGOpacity];
        }
    }
}

}  // namespace psimap
