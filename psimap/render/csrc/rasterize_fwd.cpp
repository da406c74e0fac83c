// Forward rasterization: OpenMP over 16x16 tiles (dynamic schedule), per pixel front-to-back
// alpha blending of the tile's surfels (SPEC.md stage 3), Top-K feature selection.
#include <algorithm>
#include <cstring>

#include <omp.h>

#include "threads.h"

#include "rasterize.h"

namespace psimap {

int64_t rasterize_forward(const SurfelInputs& in, const TileBins& bins, const RasterConfig& cfg,
                          const ForwardBuffers& out) {
    const int W = cfg.width, H = cfg.height, C = in.channels, K = cfg.topk;
    const int tiles = bins.tiles_x * bins.tiles_y;
    const float near = cfg.near, far = cfg.far;
    int64_t evaluated = 0;
#pragma omp parallel reduction(+ : evaluated) num_threads(kernel_threads())
    {
        std::vector<SurfelParams> params;
        std::vector<Footprint> footprints;
        std::vector<Footprint>* fp = cfg.exact_footprint ? &footprints : nullptr;
        std::vector<int32_t> block_pos;
        int32_t block_start[kBlocks * kBlocks + 1];
        std::vector<float> feat_acc(C);
#pragma omp for schedule(dynamic, 1)
        for (int t = 0; t < tiles; ++t) {
            gather_tile(in, bins, t, params, fp);
            const int32_t* ids = bins.ids + bins.offsets[t];
            const int tx = t % bins.tiles_x, ty = t / bins.tiles_x;
            block_lists(params, tx * kTile, ty * kTile, block_pos, block_start, fp);
            const int px1 = std::min(W, (tx + 1) * kTile), py1 = std::min(H, (ty + 1) * kTile);
            for (int py = ty * kTile; py < py1; ++py) {
                for (int px = tx * kTile; px < px1; ++px) {
                    const int64_t pix = static_cast<int64_t>(py) * W + px;
                    const float x = static_cast<float>(px), y = static_cast<float>(py);
                    float T_acc = 1.0f;
                    float rgb[3] = {0.0f, 0.0f, 0.0f}, nrm[3] = {0.0f, 0.0f, 0.0f};
                    float depth_num = 0.0f, median = 0.0f;
                    double dist = 0.0, A = 0.0, D = 0.0, D2 = 0.0;
                    int median_pos = -1, last = 0;
                    float top_w[kMaxTopK];
                    int top_pos[kMaxTopK];
                    int top_count = 0, top_evict = 0;
                    if (K == 0) std::fill(feat_acc.begin(), feat_acc.end(), 0.0f);
                    const int b = block_of(px, py, tx * kTile, ty * kTile);
                    for (int k = block_start[b]; k < block_start[b + 1]; ++k) {
                        const int j = block_pos[k];
                        const SurfelParams& s = params[j];
                        // (pixel, surfel) evaluations: those inside the surfel's box.
                        evaluated += (x >= s.x0) & (x < s.x1) & (y >= s.y0) & (y < s.y1);
                        SurfelHit h;
                        eval_surfel(s, x, y, near, h);
                        const float alpha = std::min(kAlphaMax, s.opacity * h.G);
                        if (!(alpha >= kAlphaMin)) continue;
                        const float T_next = T_acc * (1.0f - alpha);
                        if (T_next < kTransmitMin) break;  // this surfel is not blended
                        const float w = alpha * T_acc;
                        for (int c = 0; c < 3; ++c) {
                            rgb[c] += w * s.color[c];
                            nrm[c] += w * s.normal[c];
                        }
                        depth_num += w * h.d;
                        if (T_acc > 0.5f) {
                            median = h.d;
                            median_pos = j;
                        }
                        const double m = ndc_depth_d(h.d, near, far);
                        dist += w * (m * m * A + D2 - 2.0 * m * D);
                        A += w;
                        D += w * m;
                        D2 += w * m * m;
                        if (K > 0) {
                            topk_insert(top_w, top_pos, top_count, top_evict, K, w, j);
                        } else if (C > 0) {
                            const float* f = in.feature + static_cast<int64_t>(ids[j]) * C;
                            for (int c = 0; c < C; ++c) feat_acc[c] += w * f[c];
                        }
                        T_acc = T_next;
                        last = j + 1;
                    }
                    const float alpha_out = 1.0f - T_acc;
                    for (int c = 0; c < 3; ++c) {
                        out.rgb[3 * pix + c] = rgb[c] + T_acc * cfg.background[c];
                        out.normal[3 * pix + c] = nrm[c];
                    }
                    out.alpha[pix] = alpha_out;
                    out.depth[pix] = alpha_out > kAlphaOutMin ? depth_num / alpha_out : 0.0f;
                    out.median[pix] = median;
                    out.distortion[pix] = static_cast<float>(dist);
                    out.t_final[pix] = T_acc;
                    out.n_last[pix] = last;
                    out.median_pos[pix] = median_pos;
                    out.dist_sums[3 * pix] = A;
                    out.dist_sums[3 * pix + 1] = D;
                    out.dist_sums[3 * pix + 2] = D2;
                    float* fo = out.feature + pix * C;
                    if (K > 0) {
                        // Sum the selected surfels front to back (the order blending visits them):
                        // insertion sort of the (position, weight) pairs by position.
                        for (int a = 1; a < top_count; ++a) {
                            const int pa = top_pos[a];
                            const float wa = top_w[a];
                            int b = a;
                            for (; b > 0 && top_pos[b - 1] > pa; --b) {
                                top_pos[b] = top_pos[b - 1];
                                top_w[b] = top_w[b - 1];
                            }
                            top_pos[b] = pa;
                            top_w[b] = wa;
                        }
                        // Summed in the thread's buffer (the compiler cannot prove `fo` apart
                        // from the features), stored once.
                        float* acc = feat_acc.data();
                        std::fill(acc, acc + C, 0.0f);
                        int32_t* saved = out.topk_pos + pix * K;
                        if (out.topk_w != nullptr) {
                            float* ws = out.topk_w + pix * K;
                            for (int k = 0; k < K; ++k) ws[k] = k < top_count ? top_w[k] : 0.0f;
                        }
                        for (int k = 0; k < top_count; ++k) {
                            saved[k] = top_pos[k];
                            const float* f = in.feature + static_cast<int64_t>(ids[top_pos[k]]) * C;
                            const float wk = top_w[k];
                            for (int c = 0; c < C; ++c) acc[c] += wk * f[c];
                        }
                        for (int k = top_count; k < K; ++k) saved[k] = -1;
                        std::copy(acc, acc + C, fo);
                    } else {
                        for (int c = 0; c < C; ++c) fo[c] = feat_acc[c];
                    }
                }
            }
        }
    }
    return evaluated;
}

}  // namespace psimap
