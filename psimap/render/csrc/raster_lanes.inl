// The per-pixel loops of the rasterizer (SPEC.md stage 3) on lanes of pixels: each lane is one
// pixel of a 4x4 block and every lane walks the block's surfel list together, so one surfel's
// evaluation, exponentials and blending cost one vector instruction for kLanes pixels. Each lane
// makes the float decisions and sums of the per-pixel definition in the same order, so the forward
// gives the same bits for any lane count. Included by raster_isa_*.cpp inside
// namespace psimap::PSIMAP_ISA_NS, compiled once per instruction set (simd_lanes.h); uses no
// inline function of a shared header (a copy compiled for AVX-512 could be linked for every ISA).
#include <stdint.h>
#include <string.h>

#if defined(__SSE2__)
#include <immintrin.h>
#endif

#include "rasterize.h"

namespace psimap {
namespace PSIMAP_ISA_NS {

#include "simd_lanes.h"

namespace {

// Lane l of group g is pixel q = g kLanes + l of the 4x4 block: (q % 4, q / 4).
struct LanePixels {
    vf x, y;
    vi inside;                 // the pixel is in the image
    int64_t pix[kLanes];       // row-major pixel index (unused lanes: -1)
};

PSIMAP_LANE_FN LanePixels lane_pixels(int bx0, int by0, int group, int width, int height) {
    LanePixels p;
    for (int l = 0; l < kLanes; ++l) {
        const int q = group * kLanes + l;
        const int px = bx0 + (q & 3), py = by0 + (q >> 2);
        p.x[l] = static_cast<float>(px);
        p.y[l] = static_cast<float>(py);
        const bool in = px < width && py < height;
        p.inside[l] = in ? -1 : 0;
        p.pix[l] = in ? static_cast<int64_t>(py) * width + px : -1;
    }
    return p;
}

// One surfel at every lane's pixel (SPEC.md stage 3): the kernel value G = max(G3, G2) of the
// ray-splat intersection (u, v) and of the low-pass fallback, and the hit depth d. `none` is set
// when no lane can reach alpha >= 1/255.
struct LaneHit {
    vf G, d, u, v;
    vi use3, use2;   // branch of each lane (neither: G = 0)
    bool none;
};

PSIMAP_LANE_FN LaneHit eval_lanes(const SurfelParams& s, vf x, vf y, vi lanes, float near) {
    LaneHit h;
    h.none = true;
    const float* T = s.T;
    const vf hx0 = x * T[6] - T[0], hx1 = x * T[7] - T[1], hx2 = x * T[8] - T[2];
    const vf hy0 = y * T[6] - T[3], hy1 = y * T[7] - T[4], hy2 = y * T[8] - T[5];
    const vf p0 = hx1 * hy2 - hx2 * hy1;
    const vf p1 = hx2 * hy0 - hx0 * hy2;
    const vf p2 = hx0 * hy1 - hx1 * hy0;
    const vf hx_sq = hx0 * hx0 + hx1 * hx1 + hx2 * hx2;
    const vf hy_sq = hy0 * hy0 + hy1 * hy1 + hy2 * hy2;
    const vf den = p2 * p2;
    const float lim = s.half_rho_cut < kChi2 / 2.0f ? 2.0f * s.half_rho_cut : kChi2;  // fminf
    // |p2| > eps |hx| |hy|, squared (as the reference does), else the surfel is edge-on. Then a
    // division-free rejection (most evaluations miss the splat): rho3 = |p01|^2 / p2^2 beyond
    // min(chi^2, 2 cut) by a 1e-4 margin (>> rounding) fails the divided test too: either
    // rho3 > chi^2, or G3 < 1/(255 o) < G2 whenever the low-pass is tried.
    const vi pass3 = lanes & (den > kEdgeOnEps2 * hx_sq * hy_sq) & (p0 * p0 + p1 * p1 <= lim * den * 1.0001f);
    const vf dx = x - s.cx, dy = y - s.cy;
    const vf rho2 = dx * dx + dy * dy;
    const vi valid2 = lanes & (rho2 <= kLowPass2);
    vi valid3 = vi{};
    vf rho3 = vf{}, u = vf{}, v = vf{}, z3 = vf{};
    if (any(pass3)) {
        u = p0 / p2;
        v = p1 / p2;
        rho3 = u * u + v * v;
        z3 = T[6] * u + T[7] * v + T[8];
        valid3 = pass3 & (rho3 <= kChi2) & (z3 > near);
    }
    // Lanes where alpha can reach 1/255; elsewhere G = 0 without the exponentials (the same
    // decisions as the exact test: half_rho_cut). Ties G3 = G2 go to the 3D branch.
    const vi tried = (valid3 & (0.5f * rho3 <= s.half_rho_cut)) | (valid2 & (rho2 <= s.half_rho_cut));
    if (!any(tried)) return h;
    h.none = false;
    const vi try3 = valid3 & tried, try2 = valid2 & tried;
    const vf G3 = any(try3) ? select(try3, exp_nonpositive(select(try3, -rho3 / 2.0f, vf{})), vf{}) : vf{};
    const vf G2 = any(try2) ? select(try2, exp_nonpositive(select(try2, -rho2, vf{})), vf{}) : vf{};
    h.use3 = try3 & (G3 >= G2);
    h.use2 = try2 & ~h.use3;
    h.G = select(h.use3, G3, select(h.use2, G2, vf{}));
    h.d = select(h.use3, z3, splat(s.depth_key));
    h.u = u;
    h.v = v;
    return h;
}

// Top-K of each lane: the K largest weights so far (ties: the earlier position stays), slot-major
// [K] vectors sorted by weight, largest first (equal weights in position order). A new surfel
// enters when its weight beats the last slot's (threshold; -1 while the list is not full), which
// it evicts: the smallest weight, the latest position among equal ones.
struct LaneTopK {
    vf w[kMaxTopK];
    vi pos[kMaxTopK];
};

PSIMAP_LANE_FN void topk_lanes_insert(LaneTopK& top, int K, vi take, vf w, int pos) {
    // Slots k with w > w[k] shift down by one; the first of them takes the new surfel. The
    // weights are sorted, so w > w[k] holds from some slot on (ties stay in front of it).
    for (int k = K - 1; k >= 0; --k) {
        const vi moves = take & (w > top.w[k]);
        if (k > 0) {
            const vi from_above = w > top.w[k - 1];
            top.w[k] = select(moves, select(from_above, top.w[k - 1], w), top.w[k]);
            top.pos[k] = select(moves, select(from_above, top.pos[k - 1], splat_i(pos)), top.pos[k]);
        } else {
            top.w[0] = select(moves, w, top.w[0]);
            top.pos[0] = select(moves, splat_i(pos), top.pos[0]);
        }
    }
}

// Sorts every lane's slots by position (bitonic network over the slots, padded to a power of
// two; empty slots hold position INT32_MAX and sort last): a compare-exchange costs a few vector
// instructions for all lanes, where sorting each pixel's list alone branches at every step.
PSIMAP_LANE_FN void topk_lanes_sort(LaneTopK& top, int K) {
    int padded = 1;
    while (padded < K) padded *= 2;
    for (int k = K; k < padded; ++k) {
        top.pos[k] = splat_i(INT32_MAX);
        top.w[k] = splat(-1.0f);
    }
    for (int size = 2; size <= padded; size *= 2)
        for (int stride = size / 2; stride > 0; stride /= 2)
            for (int i = 0; i < padded; ++i) {
                const int j = i ^ stride;
                if (j < i) continue;
                // ascending pairs where bit `size` of i is clear, descending where it is set
                const vi swap = (i & size) == 0 ? (top.pos[i] > top.pos[j]) : (top.pos[i] < top.pos[j]);
                const vi pi = top.pos[i];
                const vf wi = top.w[i];
                top.pos[i] = select(swap, top.pos[j], pi);
                top.w[i] = select(swap, top.w[j], wi);
                top.pos[j] = select(swap, pi, top.pos[j]);
                top.w[j] = select(swap, wi, top.w[j]);
            }
}

// Forward of one tile: every 4x4 block, kLanes pixels at a time.
int64_t forward_tile(const SurfelInputs& in, const RasterConfig& cfg, const ForwardBuffers& out,
                     const TileWork& work) {
    const int C = in.channels, K = cfg.topk;
    const float near = cfg.near;
    const double far_d = cfg.far, near_d = cfg.near;
    const SurfelParams* __restrict params = work.params;
    float* __restrict facc = work.scratch;  // [C] lane vectors: full blending of features
    LaneTopK top;
    int64_t evaluated = 0;
    for (int b = 0; b < kBlocks * kBlocks; ++b) {
        const int bx0 = work.x0 + (b % kBlocks) * kBlockPx, by0 = work.y0 + (b / kBlocks) * kBlockPx;
        const int32_t* __restrict list = work.block_pos + work.block_start[b];
        const int n_list = work.block_start[b + 1] - work.block_start[b];
        for (int group = 0; group < kBlockPx * kBlockPx / kLanes; ++group) {
            const LanePixels px = lane_pixels(bx0, by0, group, cfg.width, cfg.height);
            if (!any(px.inside)) continue;
            vi active = px.inside;
            vf T_acc = splat(1.0f);
            vf rgb0 = vf{}, rgb1 = vf{}, rgb2 = vf{}, nrm0 = vf{}, nrm1 = vf{}, nrm2 = vf{};
            vf depth_num = vf{}, median = vf{};
            vi median_pos = splat_i(-1), last = vi{};
            vd dist[2] = {vd{}, vd{}}, A[2] = {vd{}, vd{}}, D[2] = {vd{}, vd{}}, D2[2] = {vd{}, vd{}};
            if (K == 0)
                for (int64_t k = 0; k < static_cast<int64_t>(C) * kLanes; ++k) facc[k] = 0.0f;
            if (K > 0) {
                for (int k = 0; k < K; ++k) {
                    top.pos[k] = splat_i(INT32_MAX);  // empty: sorts last by position
                    top.w[k] = splat(-1.0f);          // below any weight (w > 0)
                }
            }
            for (int k = 0; k < n_list; ++k) {
                const int j = list[k];
                const SurfelParams& s = params[j];
                // (pixel, surfel) evaluations: the pixels inside the surfel's box, until they stop.
                const vi in_box = active & (px.x >= s.x0) & (px.x < s.x1) & (px.y >= s.y0) & (px.y < s.y1);
                const unsigned box_bits = lane_bits(in_box);
                if (box_bits == 0) continue;
                evaluated += __builtin_popcount(box_bits);
                if (s.half_rho_cut < 0.0f) continue;
                const LaneHit h = eval_lanes(s, px.x, px.y, in_box, near);
                if (h.none) continue;
                const vf oG = s.opacity * h.G;
                const vf alpha = min_of(splat(kAlphaMax), oG);
                vi blend = in_box & (alpha >= kAlphaMin);
                if (!any(blend)) continue;
                const vf T_next = T_acc * (1.0f - alpha);
                const vi stop = blend & (T_next < kTransmitMin);  // these pixels end before this surfel
                blend &= ~stop;
                active &= ~stop;
                if (any(blend)) {
                    const vf w = alpha * T_acc;
                    rgb0 = select(blend, rgb0 + w * s.color[0], rgb0);
                    nrm0 = select(blend, nrm0 + w * s.normal[0], nrm0);
                    rgb1 = select(blend, rgb1 + w * s.color[1], rgb1);
                    nrm1 = select(blend, nrm1 + w * s.normal[1], nrm1);
                    rgb2 = select(blend, rgb2 + w * s.color[2], rgb2);
                    nrm2 = select(blend, nrm2 + w * s.normal[2], nrm2);
                    depth_num = select(blend, depth_num + w * h.d, depth_num);
                    const vi med = blend & (T_acc > 0.5f);
                    median = select(med, h.d, median);
                    median_pos = select(med, splat_i(j), median_pos);
                    // Distortion (2DGS, one pass) in double on both halves of the lanes, m = NDC depth.
                    const vd d_half[2] = {lo_d(h.d), hi_d(h.d)}, w_half[2] = {lo_d(w), hi_d(w)};
                    const vl m_half[2] = {lo_mask(blend), hi_mask(blend)};
                    for (int hf = 0; hf < 2; ++hf) {
                        const vd dd = d_half[hf], ww = w_half[hf];
                        const vd m = far_d * (dd - near_d) / ((far_d - near_d) * dd);
                        const vl on = m_half[hf];
                        dist[hf] = select(on, dist[hf] + ww * (m * m * A[hf] + D2[hf] - 2.0 * m * D[hf]), dist[hf]);
                        A[hf] = select(on, A[hf] + ww, A[hf]);
                        D[hf] = select(on, D[hf] + ww * m, D[hf]);
                        D2[hf] = select(on, D2[hf] + ww * m * m, D2[hf]);
                    }
                    if (K > 0) {
                        const vi take = blend & (w > top.w[K - 1]);
                        if (any(take)) topk_lanes_insert(top, K, take, w, j);
                    } else if (C > 0) {
                        const float* __restrict f = in.feature + static_cast<int64_t>(work.ids[j]) * C;
                        for (int c = 0; c < C; ++c) {
                            vf a;
                            memcpy(&a, facc + c * kLanes, sizeof a);
                            a = select(blend, a + w * f[c], a);
                            memcpy(facc + c * kLanes, &a, sizeof a);
                        }
                    }
                    T_acc = select(blend, T_next, T_acc);
                    last = select(blend, splat_i(j + 1), last);
                }
                if (!any(active)) break;
            }
            vi top_count = vi{};
            if (K > 0) {
                for (int k = 0; k < K; ++k) top_count -= top.w[k] >= 0.0f;  // filled slots
                topk_lanes_sort(top, K);
            }
            // Per pixel outputs.
            const vf alpha_out = 1.0f - T_acc;
            const vf depth = select(alpha_out > kAlphaOutMin, depth_num / alpha_out, vf{});
            double dist_l[kLanes], A_l[kLanes], D_l[kLanes], D2_l[kLanes];
            memcpy(dist_l, &dist[0], sizeof(vd));
            memcpy(dist_l + kHalf, &dist[1], sizeof(vd));
            memcpy(A_l, &A[0], sizeof(vd));
            memcpy(A_l + kHalf, &A[1], sizeof(vd));
            memcpy(D_l, &D[0], sizeof(vd));
            memcpy(D_l + kHalf, &D[1], sizeof(vd));
            memcpy(D2_l, &D2[0], sizeof(vd));
            memcpy(D2_l + kHalf, &D2[1], sizeof(vd));
            for (int l = 0; l < kLanes; ++l) {
                const int64_t pix = px.pix[l];
                if (pix < 0) continue;
                out.rgb[3 * pix] = rgb0[l] + T_acc[l] * cfg.background[0];
                out.rgb[3 * pix + 1] = rgb1[l] + T_acc[l] * cfg.background[1];
                out.rgb[3 * pix + 2] = rgb2[l] + T_acc[l] * cfg.background[2];
                out.normal[3 * pix] = nrm0[l];
                out.normal[3 * pix + 1] = nrm1[l];
                out.normal[3 * pix + 2] = nrm2[l];
                out.alpha[pix] = alpha_out[l];
                out.depth[pix] = depth[l];
                out.median[pix] = median[l];
                out.distortion[pix] = static_cast<float>(dist_l[l]);
                out.t_final[pix] = T_acc[l];
                out.n_last[pix] = last[l];
                out.median_pos[pix] = median_pos[l];
                out.dist_sums[3 * pix] = A_l[l];
                out.dist_sums[3 * pix + 1] = D_l[l];
                out.dist_sums[3 * pix + 2] = D2_l[l];
                float* __restrict fo = out.feature + pix * C;
                if (K == 0) {
                    for (int c = 0; c < C; ++c) fo[c] = facc[c * kLanes + l];
                    continue;
                }
                // Top-K: sum the selected surfels front to back (the order blending visits them;
                // the slots were sorted by position below).
                const int n_top = top_count[l];
                int32_t* saved = out.topk_pos + pix * K;
                for (int a = 0; a < K; ++a) saved[a] = a < n_top ? top.pos[a][l] : -1;
                if (out.topk_w != nullptr) {
                    float* ws = out.topk_w + pix * K;
                    for (int a = 0; a < K; ++a) ws[a] = a < n_top ? top.w[a][l] : 0.0f;
                }
                // Channels kLanes at a time in a register (the pixel's rows are read once per
                // chunk: a tile's few surfels stay in L1), each summed over a = 0 .. n_top - 1.
                const float* rows[kMaxTopK];
                for (int a = 0; a < n_top; ++a) rows[a] = in.feature + static_cast<int64_t>(work.ids[top.pos[a][l]]) * C;
                int c0 = 0;
                for (; c0 + kLanes <= C; c0 += kLanes) {
                    vf acc = vf{};
                    for (int a = 0; a < n_top; ++a) {
                        vf f;
                        memcpy(&f, rows[a] + c0, sizeof f);
                        acc += top.w[a][l] * f;
                    }
                    memcpy(fo + c0, &acc, sizeof acc);
                }
                for (int c = c0; c < C; ++c) {
                    float acc = 0.0f;
                    for (int a = 0; a < n_top; ++a) acc += top.w[a][l] * rows[a][c];
                    fo[c] = acc;
                }
            }
        }
    }
    return evaluated;
}

}  // namespace

// Backward of one tile: every 4x4 block, kLanes pixels at a time, each lane back to front from its
// last blended surfel (the transmittance rebuilt as T_i = T_{i+1} / (1 - alpha_i) from the same
// alphas the forward computed). Each lane's gradient terms go to per-lane partial sums per surfel
// of the tile (work.lane_acc), summed across lanes once per tile into work.grad_rows: a fixed
// order, so the result does not depend on the threads (it does on the lane count: ulps).
void backward_tile(const SurfelInputs& in, const RasterConfig& cfg, const ForwardBuffers& saved,
                   const BackwardGrads& g, const TileWork& work) {
    const int C = in.channels, K = cfg.topk;
    const float near = cfg.near;
    const double far_d = cfg.far, near_d = cfg.near;
    const float* bg = cfg.background;
    const SurfelParams* __restrict params = work.params;
    float* __restrict gF = work.scratch;  // [C] lane vectors: dL/dfeature of each lane's pixel
    vf* __restrict lane_acc = reinterpret_cast<vf*>(work.lane_acc);  // [n][kGradSlots]
    for (int j = 0; j < work.n; ++j) work.touched[j] = 0;
    for (int b = 0; b < kBlocks * kBlocks; ++b) {
        const int bx0 = work.x0 + (b % kBlocks) * kBlockPx, by0 = work.y0 + (b / kBlocks) * kBlockPx;
        const int32_t* __restrict list = work.block_pos + work.block_start[b];
        const int n_list = work.block_start[b + 1] - work.block_start[b];
        for (int group = 0; group < kBlockPx * kBlockPx / kLanes; ++group) {
            const LanePixels px = lane_pixels(bx0, by0, group, cfg.width, cfg.height);
            // Per-lane state of the pixel (lanes outside the image, or where nothing blended, idle).
            float T_fin[kLanes], g_Tf[kLanes], g_num[kLanes], g_r[3][kLanes], g_n[3][kLanes], g_di[kLanes],
                g_me[kLanes];
            double A_l[kLanes], D_l[kLanes], D2_l[kLanes];
            int32_t last_l[kLanes], med_l[kLanes], sel_k[kLanes], next_l[kLanes];
            int max_last = 0;
            for (int l = 0; l < kLanes; ++l) {
                const int64_t pix = px.pix[l];
                last_l[l] = pix < 0 ? 0 : saved.n_last[pix];
                max_last = last_l[l] > max_last ? last_l[l] : max_last;
                if (last_l[l] == 0) {
                    T_fin[l] = g_Tf[l] = g_num[l] = g_di[l] = g_me[l] = 0.0f;
                    for (int c = 0; c < 3; ++c) g_r[c][l] = g_n[c][l] = 0.0f;
                    A_l[l] = D_l[l] = D2_l[l] = 0.0;
                    med_l[l] = next_l[l] = -1;
                    sel_k[l] = -1;
                    for (int c = 0; c < C; ++c) gF[c * kLanes + l] = 0.0f;
                    continue;
                }
                T_fin[l] = saved.t_final[pix];
                const float alpha_out = 1.0f - T_fin[l];
                A_l[l] = saved.dist_sums[3 * pix];
                D_l[l] = saved.dist_sums[3 * pix + 1];
                D2_l[l] = saved.dist_sums[3 * pix + 2];
                for (int c = 0; c < 3; ++c) {
                    g_r[c][l] = g.rgb[3 * pix + c];
                    g_n[c][l] = g.normal[3 * pix + c];
                }
                g_di[l] = g.distortion[pix];
                g_me[l] = g.median[pix];
                med_l[l] = saved.median_pos[pix];
                // alpha_out = 1 - T_final; rgb = ... + T_final bg; depth = num / alpha_out.
                g_Tf[l] = -g.alpha[pix] + g_r[0][l] * bg[0] + g_r[1][l] * bg[1] + g_r[2][l] * bg[2];
                g_num[l] = 0.0f;
                if (alpha_out > kAlphaOutMin) {
                    g_num[l] = g.depth[pix] / alpha_out;
                    g_Tf[l] += g.depth[pix] * saved.depth[pix] / alpha_out;
                }
                for (int c = 0; c < C; ++c) gF[c * kLanes + l] = g.feature[pix * C + c];
                // Top-K: the lane's selected positions, walked from the back.
                int k = K - 1;
                if (K > 0)
                    while (k >= 0 && saved.topk_pos[pix * K + k] < 0) --k;
                sel_k[l] = k;
                next_l[l] = K > 0 && k >= 0 ? saved.topk_pos[pix * K + k] : -1;
            }
            if (max_last == 0) continue;
            vf T, S, gr[3], gn[3], g_dist, g_med, gnum;
            vi last, med_pos, next_sel;
            memcpy(&T, T_fin, sizeof T);
            memcpy(&S, g_Tf, sizeof S);
            S = S * T;  // sum_{k > i} dL/dw_k w_k + dL/dT_final T_final
            for (int c = 0; c < 3; ++c) {
                memcpy(&gr[c], g_r[c], sizeof(vf));
                memcpy(&gn[c], g_n[c], sizeof(vf));
            }
            memcpy(&g_dist, g_di, sizeof g_dist);
            memcpy(&g_med, g_me, sizeof g_med);
            memcpy(&gnum, g_num, sizeof gnum);
            memcpy(&last, last_l, sizeof last);
            memcpy(&med_pos, med_l, sizeof med_pos);
            memcpy(&next_sel, next_l, sizeof next_sel);
            vd A[2], D[2], D2[2];
            memcpy(&A[0], A_l, sizeof(vd));
            memcpy(&A[1], A_l + kHalf, sizeof(vd));
            memcpy(&D[0], D_l, sizeof(vd));
            memcpy(&D[1], D_l + kHalf, sizeof(vd));
            memcpy(&D2[0], D2_l, sizeof(vd));
            memcpy(&D2[1], D2_l + kHalf, sizeof(vd));
            const vd g_dist_d[2] = {lo_d(g_dist), hi_d(g_dist)};
            int k = n_list - 1;
            while (k >= 0 && list[k] >= max_last) --k;
            for (; k >= 0; --k) {
                const int j = list[k];
                const SurfelParams& s = params[j];
                const vi in_box = (splat_i(j) < last) & (px.x >= s.x0) & (px.x < s.x1) & (px.y >= s.y0) &
                                  (px.y < s.y1);
                if (!any(in_box) || s.half_rho_cut < 0.0f) continue;
                const LaneHit h = eval_lanes(s, px.x, px.y, in_box, near);
                if (h.none) continue;
                const vf oG = s.opacity * h.G;
                const vf alpha = min_of(splat(kAlphaMax), oG);
                const vi ok = in_box & (alpha >= kAlphaMin);
                if (!any(ok)) continue;
                const vf one_minus = 1.0f - alpha;
                T = select(ok, T / one_minus, T);
                const vf w = alpha * T;
                vi selected = ok;
                if (K > 0) {
                    selected = ok & (next_sel == j);
                    for (unsigned bits = lane_bits(selected); bits != 0; bits &= bits - 1) {
                        const int l = __builtin_ctz(bits);
                        const int kk = --sel_k[l];
                        next_sel[l] = kk >= 0 ? saved.topk_pos[px.pix[l] * K + kk] : -1;
                    }
                }
                // dDist/dw_i = sum_j w_j (m_i - m_j)^2, dDist/dm_i = 2 w_i (m_i A - D), in double.
                const vd d_half[2] = {lo_d(h.d), hi_d(h.d)}, w_half[2] = {lo_d(w), hi_d(w)};
                vd dist_w[2], dist_d[2];
                for (int hf = 0; hf < 2; ++hf) {
                    const vd dd = d_half[hf];
                    const vd m = far_d * (dd - near_d) / ((far_d - near_d) * dd);
                    dist_w[hf] = g_dist_d[hf] * (m * m * A[hf] - 2.0 * m * D[hf] + D2[hf]);
                    const vd dm_dd = far_d * near_d / ((far_d - near_d) * dd * dd);
                    dist_d[hf] = g_dist_d[hf] * 2.0 * w_half[hf] * (m * A[hf] - D[hf]) * dm_dd;
                }
                vf g_w = gr[0] * s.color[0] + gr[1] * s.color[1] + gr[2] * s.color[2] + gnum * h.d +
                         gn[0] * s.normal[0] + gn[1] * s.normal[1] + gn[2] * s.normal[2] +
                         to_float(dist_w[0], dist_w[1]);
                if (C > 0 && any(selected)) {
                    const float* __restrict f = in.feature + static_cast<int64_t>(work.ids[j]) * C;
                    float* __restrict tf = work.grad_feat + static_cast<int64_t>(j) * C;
                    vf dot = vf{};
                    for (int c = 0; c < C; ++c) {
                        vf gf;
                        memcpy(&gf, gF + c * kLanes, sizeof gf);
                        dot += gf * f[c];
                    }
                    g_w = select(selected, g_w + dot, g_w);
                    for (unsigned bits = lane_bits(selected); bits != 0; bits &= bits - 1) {
                        const int l = __builtin_ctz(bits);
                        const float* __restrict gfl = g.feature + px.pix[l] * C;
                        const float wl = w[l];
                        for (int c = 0; c < C; ++c) tf[c] += wl * gfl[c];
                    }
                }
                vf g_d = gnum * w + to_float(dist_d[0], dist_d[1]);
                g_d = select(med_pos == j, g_d + g_med, g_d);
                const vf g_alpha = T * g_w - S / one_minus;
                S = select(ok, S + g_w * w, S);
                const vi unclamped = ok & (oG <= kAlphaMax);
                const vf g_G = select(unclamped, g_alpha * s.opacity, vf{});
                // Chain dL/dG, dL/dd into the surfel's T, centre and depth_key, per branch:
                // low-pass G2 = exp(-rho2), d = depth_key; 3D G3 = exp(-(u^2 + v^2) / 2),
                // d = z3 = T[6] u + T[7] v + T[8], (u, v) = (p0, p1) / p2, p = hx x hy.
                const vi b3 = ok & h.use3, b2 = ok & h.use2;
                const float* Tm = s.T;
                const vf g_rho2 = -g_G * h.G;
                const vf g_rho3 = -0.5f * g_G * h.G;
                const vf g_u = g_rho3 * 2.0f * h.u + g_d * Tm[6];
                const vf g_v = g_rho3 * 2.0f * h.v + g_d * Tm[7];
                const vf hx0 = px.x * Tm[6] - Tm[0], hx1 = px.x * Tm[7] - Tm[1], hx2 = px.x * Tm[8] - Tm[2];
                const vf hy0 = px.y * Tm[6] - Tm[3], hy1 = px.y * Tm[7] - Tm[4], hy2 = px.y * Tm[8] - Tm[5];
                const vf p2 = hx0 * hy1 - hx1 * hy0;
                const vf gp0 = g_u / p2;
                const vf gp1 = g_v / p2;
                const vf gp2 = -(g_u * h.u + g_v * h.v) / p2;
                // p = a x b  =>  dL/da = b x g_p, dL/db = g_p x a (a = x T2 - T0, b = y T2 - T1).
                const vf ga0 = hy1 * gp2 - hy2 * gp1, ga1 = hy2 * gp0 - hy0 * gp2, ga2 = hy0 * gp1 - hy1 * gp0;
                const vf gb0 = gp1 * hx2 - gp2 * hx1, gb1 = gp2 * hx0 - gp0 * hx2, gb2 = gp0 * hx1 - gp1 * hx0;
                vf* acc = lane_acc + static_cast<int64_t>(j) * kGradSlots;
                if (!work.touched[j]) {
                    work.touched[j] = 1;
                    for (int q = 0; q < kGradSlots; ++q) acc[q] = vf{};
                }
                acc[kGradT + 0] += select(b3, -ga0, vf{});
                acc[kGradT + 1] += select(b3, -ga1, vf{});
                acc[kGradT + 2] += select(b3, -ga2, vf{});
                acc[kGradT + 3] += select(b3, -gb0, vf{});
                acc[kGradT + 4] += select(b3, -gb1, vf{});
                acc[kGradT + 5] += select(b3, -gb2, vf{});
                acc[kGradT + 6] += select(b3, g_d * h.u + (px.x * ga0 + px.y * gb0), vf{});
                acc[kGradT + 7] += select(b3, g_d * h.v + (px.x * ga1 + px.y * gb1), vf{});
                acc[kGradT + 8] += select(b3, g_d + (px.x * ga2 + px.y * gb2), vf{});
                acc[kGradCenter] += select(b2, g_rho2 * -2.0f * (px.x - s.cx), vf{});
                acc[kGradCenter + 1] += select(b2, g_rho2 * -2.0f * (px.y - s.cy), vf{});
                acc[kGradDepthKey] += select(b2, g_d, vf{});
                acc[kGradOpacity] += select(unclamped, g_alpha * h.G, vf{});
                for (int c = 0; c < 3; ++c) {
                    acc[kGradNormal + c] += select(ok, w * gn[c], vf{});
                    acc[kGradColor + c] += select(ok, w * gr[c], vf{});
                }
            }
        }
    }
    for (int j = 0; j < work.n; ++j) {
        float* row = work.grad_rows + static_cast<int64_t>(j) * kGradSlots;
        const vf* acc = lane_acc + static_cast<int64_t>(j) * kGradSlots;
        for (int q = 0; q < kGradSlots; ++q) row[q] = work.touched[j] ? lane_sum(acc[q]) : 0.0f;
    }
}

// exp_nonpositive on n values (kLanes at a time), so the tests can measure its error.
void exp_values(const float* x, float* out, int64_t n) {
    for (int64_t i = 0; i < n; i += kLanes) {
        float a[kLanes] = {};
        const int64_t m = n - i < kLanes ? n - i : kLanes;
        for (int64_t l = 0; l < m; ++l) a[l] = x[i + l];
        vf v;
        memcpy(&v, a, sizeof v);
        v = exp_nonpositive(v);
        memcpy(a, &v, sizeof v);
        for (int64_t l = 0; l < m; ++l) out[i + l] = a[l];
    }
}

// The panoptic field's fused per-surfel distribution on the same lanes (field_lanes.inl).
#include "field_lanes.inl"
// ... and the sums its Hungarian matching reads (match_lanes.inl), and its frozen-blend product
// (blend_lanes.inl).
#include "match_lanes.inl"
#include "blend_lanes.inl"

PixelKernels kernels() {
    return PixelKernels{PSIMAP_ISA_NAME,   kLanes,           &forward_tile, &backward_tile, &exp_values,
                        &field_forward_rows, &field_backward_rows, &match_sums_rows,
                        &blend_rows_forward, &field_affinity_rows};
}

}  // namespace PSIMAP_ISA_NS
}  // namespace psimap
