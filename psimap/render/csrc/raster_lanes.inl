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

// One surfel at every lane's pixel (SPEC.md stage 3; the scalar definition is eval_surfel in
// surfel_math.h). `none` is set when no lane can reach alpha >= 1/255.
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
    // Edge-on test and the division-free rejection of eval_surfel (same decisions).
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
    // Lanes where alpha can reach 1/255 (the exponentials are skipped elsewhere, as in eval_surfel).
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
// [K] vectors; `threshold` is the weight a new surfel must beat (-1 while the list is not full),
// `evict` the slot it replaces (smallest weight, latest position among equal ones).
struct LaneTopK {
    vf w[kMaxTopK];
    vi pos[kMaxTopK];
    vi count, evict;
    vf threshold;
};

PSIMAP_LANE_FN void topk_lanes_insert(LaneTopK& top, int K, vi take, vf w, int pos) {
    const vi full_before = top.count >= K;
    const vi slot = select(full_before, top.evict, top.count);
    for (int k = 0; k < K; ++k) {
        const vi here = take & (slot == k);
        top.w[k] = select(here, w, top.w[k]);
        top.pos[k] = select(here, splat_i(pos), top.pos[k]);
    }
    top.count = select(take & ~full_before, top.count + 1, top.count);
    const vi full = top.count >= K;
    if (!any(take & full)) return;
    vf mw = top.w[0];
    vi mp = top.pos[0], e = vi{};
    for (int k = 1; k < K; ++k) {
        const vi smaller = (top.w[k] < mw) | ((top.w[k] == mw) & (top.pos[k] > mp));
        mw = select(smaller, top.w[k], mw);
        mp = select(smaller, top.pos[k], mp);
        e = select(smaller, splat_i(k), e);
    }
    top.evict = select(full, e, top.evict);
    top.threshold = select(full, mw, splat(-1.0f));
}

// Sorts every lane's slots by position (bitonic network over the slots, padded to a power of
// two; empty slots hold position INT32_MAX and sort last): a compare-exchange costs a few vector
// instructions for all lanes, where sorting each pixel's list alone branches at every step.
PSIMAP_LANE_FN void topk_lanes_sort(LaneTopK& top, int K) {
    int padded = 1;
    while (padded < K) padded *= 2;
    for (int k = K; k < padded; ++k) {
        top.pos[k] = splat_i(INT32_MAX);
        top.w[k] = vf{};
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
                top.count = vi{};
                top.evict = vi{};
                top.threshold = splat(-1.0f);
                for (int k = 0; k < K; ++k) {
                    top.pos[k] = splat_i(INT32_MAX);
                    top.w[k] = vf{};
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
                    // Distortion in double (ndc_depth_d), both halves of the lanes.
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
                        const vi take = blend & (w > top.threshold);
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
            if (K > 0) topk_lanes_sort(top, K);
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
                const int n_top = top.count[l];
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

PixelKernels kernels() { return PixelKernels{PSIMAP_ISA_NAME, kLanes, &forward_tile}; }

}  // namespace PSIMAP_ISA_NS
}  // namespace psimap
