// Per-surfel / per-pixel math of the surfel renderer (psimap/render/SPEC.md, stage 3).
// Plain inline functions on raw floats, no STL, so a CUDA build can share this header.
#pragma once

#include <math.h>
#include <stdint.h>
#include <string.h>

#if defined(__CUDACC__)
#define PSIMAP_HD __host__ __device__ __forceinline__
#else
#define PSIMAP_HD inline
#endif

namespace psimap {

constexpr int kTile = 16;
constexpr int kMaxTopK = 64;
constexpr float kChi2 = 9.0f;                  // 3-sigma disk: u^2 + v^2 <= 9
constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.99f;
constexpr float kTransmitMin = 1e-4f;
constexpr float kEdgeOnEps2 = 1e-20f;  // (1e-10)^2
constexpr float kLowPass2 = 5.541263545158426f;  // R_LP^2 = ln 255
constexpr float kAlphaOutMin = 1e-6f;

// One surfel's parameters gathered for a tile (array of structs: one cache line-ish each).
struct SurfelParams {
    float T[9];          // splat-to-pixel homography, row major
    float x0, y0, x1, y1;  // pixel box (half-open) holding every pixel the surfel can reach (float:
                           // compared with float pixel coordinates, no int conversion per test)
    float cx, cy;        // projected centre
    float depth_key;     // camera depth of the centre
    float opacity;
    float half_rho_cut;  // above this rho/2 (either kernel) alpha is surely < 1/255: skip exp
    float color[3];
    float normal[3];
};

// Result of evaluating one surfel at one pixel.
struct SurfelHit {
    float G;       // kernel value max(G3, G2), 0 when neither branch is valid
    float d;       // hit depth (z3 for the 3D branch, depth_key for the low-pass)
    float u, v;    // tangent-plane coordinates of the ray hit (3D branch)
    int branch;    // 0: none, 3: ray-splat intersection, 2: low-pass fallback
};

// exp(x) for -6 <= x <= 0 (the kernels' range), within 1 ulp of glibc's expf (max relative error
// 1.02e-7, measured over every float in the range): x = n ln2 + r, |r| <= ln2/2, exp(r) by its
// degree-7 Taylor polynomial, times 2^n through the exponent bits. Plain + - * in this order, so
// the SIMD pixel kernels (simd_lanes.h: exp_nonpositive, the same steps on lanes) and this scalar
// twin give the same bits: the backward re-evaluates the forward's alphas exactly.
PSIMAP_HD float exp_nonpositive(float x) {
    const float round_magic = 12582912.0f;  // 1.5 * 2^23: adding it rounds to an integer
    const float t = x * 1.44269504088896341f + round_magic;
    const float n = t - round_magic;
    int32_t t_bits, magic_bits;
    memcpy(&t_bits, &t, 4);
    memcpy(&magic_bits, &round_magic, 4);
    // ln 2 = 0.693359375 (9 bits: n * it is exact) - 2.12194440e-4
    const float r = (x - n * 0.693359375f) - n * -2.12194440e-4f;
    float p = 1.0f / 5040.0f;
    p = p * r + 1.0f / 720.0f;
    p = p * r + 1.0f / 120.0f;
    p = p * r + 1.0f / 24.0f;
    p = p * r + 1.0f / 6.0f;
    p = p * r + 0.5f;
    p = p * r + 1.0f;
    p = p * r + 1.0f;
    const int32_t scale_bits = (t_bits - magic_bits + 127) << 23;
    float scale;
    memcpy(&scale, &scale_bits, 4);
    return p * scale;
}

// rho/2 beyond which o * exp(-rho/2) < 1/255 for sure (margin covers exp_nonpositive's 2-ulp error), so
// the pixel loop can skip the exponential without changing any decision of the exact test.
PSIMAP_HD float half_rho_cut(float opacity) {
    if (!(opacity >= kAlphaMin)) return -1.0f;  // alpha = o G <= o < 1/255 everywhere
    return logf(255.0f * opacity) * (1.0f + 1e-5f) + 1e-5f;
}

PSIMAP_HD double ndc_depth_d(float d, float near, float far) {
    return static_cast<double>(far) * (static_cast<double>(d) - near) /
           ((static_cast<double>(far) - near) * d);
}

// Kernel value and hit depth of surfel `s` at pixel coordinate (x, y).
PSIMAP_HD void eval_surfel(const SurfelParams& s, float x, float y, float near, SurfelHit& h) {
    const float* T = s.T;
    h.G = 0.0f;
    h.d = s.depth_key;
    h.u = 0.0f;
    h.v = 0.0f;
    h.branch = 0;
    if (s.half_rho_cut < 0.0f) return;
    // Outside its (precise or circle) box the surfel cannot reach alpha >= 1/255: stage 1 built
    // the box from the 3-sigma ellipse and the low-pass disk with slack. Skip all the math.
    if (x < s.x0 || x >= s.x1 || y < s.y0 || y >= s.y1) return;
    // 3D branch: intersect the pixel ray (two planes h_x, h_y) with the tangent plane.
    const float hx0 = x * T[6] - T[0], hx1 = x * T[7] - T[1], hx2 = x * T[8] - T[2];
    const float hy0 = y * T[6] - T[3], hy1 = y * T[7] - T[4], hy2 = y * T[8] - T[5];
    const float p0 = hx1 * hy2 - hx2 * hy1;
    const float p1 = hx2 * hy0 - hx0 * hy2;
    const float p2 = hx0 * hy1 - hx1 * hy0;
    const float hx_sq = hx0 * hx0 + hx1 * hx1 + hx2 * hx2;
    const float hy_sq = hy0 * hy0 + hy1 * hy1 + hy2 * hy2;
    bool valid3 = false;
    float rho3 = 0.0f, u = 0.0f, v = 0.0f, z3 = 0.0f;
    // |p2| > eps |hx| |hy|, squared (as the reference does), else the surfel is edge-on.
    const float den = p2 * p2;
    if (den > kEdgeOnEps2 * hx_sq * hy_sq) {
        // Division-free rejection first (most evaluations miss the splat): rho3 = |p01|^2 / p2^2.
        // Beyond min(chi^2, 2 cut) by a 1e-4 margin (>> rounding) the divided rho3 would fail
        // too: either rho3 > chi^2, or G3 < 1/(255 o) < G2 whenever the low-pass is tried.
        const float lim = fminf(kChi2, 2.0f * s.half_rho_cut);
        if (p0 * p0 + p1 * p1 <= lim * den * 1.0001f) {
            u = p0 / p2;
            v = p1 / p2;
            rho3 = u * u + v * v;
            z3 = T[6] * u + T[7] * v + T[8];
            valid3 = (rho3 <= kChi2) && (z3 > near);
        }
    }
    const float dx = x - s.cx, dy = y - s.cy;
    const float rho2 = dx * dx + dy * dy;
    const bool valid2 = rho2 <= kLowPass2;
    // Skip the exponentials when alpha would surely be below 1/255 (same decisions as exact).
    const bool try3 = valid3 && 0.5f * rho3 <= s.half_rho_cut;
    const bool try2 = valid2 && rho2 <= s.half_rho_cut;
    if (!try3 && !try2) return;
    const float G3 = valid3 ? exp_nonpositive(-rho3 / 2.0f) : 0.0f;
    const float G2 = valid2 ? exp_nonpositive(-rho2) : 0.0f;
    if (valid3 && G3 >= G2) {
        h.G = G3;
        h.d = z3;
        h.u = u;
        h.v = v;
        h.branch = 3;
    } else if (valid2) {
        h.G = G2;
        h.branch = 2;
    }
}

// Chain dL/dG and dL/dd of one evaluation into the stage-1 quantities of the surfel:
// g_T [9] (row major), g_center [2], g_depth_key (accumulated, +=).
PSIMAP_HD void eval_surfel_backward(const SurfelParams& s, float x, float y, const SurfelHit& h,
                                    float g_G, float g_d, float* g_T, float* g_center,
                                    float* g_depth_key) {
    const float* T = s.T;
    if (h.branch == 2) {
        // G2 = exp(-rho2), rho2 = (x - cx)^2 + (y - cy)^2; d = depth_key.
        const float g_rho2 = -g_G * h.G;
        g_center[0] += g_rho2 * -2.0f * (x - s.cx);
        g_center[1] += g_rho2 * -2.0f * (y - s.cy);
        *g_depth_key += g_d;
        return;
    }
    if (h.branch != 3) return;
    // G3 = exp(-(u^2+v^2)/2), d = z3 = T[6] u + T[7] v + T[8], (u, v) = (p0, p1) / p2, p = hx x hy.
    const float u = h.u, v = h.v;
    const float g_rho3 = -0.5f * g_G * h.G;
    const float g_u = g_rho3 * 2.0f * u + g_d * T[6];
    const float g_v = g_rho3 * 2.0f * v + g_d * T[7];
    g_T[6] += g_d * u;
    g_T[7] += g_d * v;
    g_T[8] += g_d;
    const float hx0 = x * T[6] - T[0], hx1 = x * T[7] - T[1], hx2 = x * T[8] - T[2];
    const float hy0 = y * T[6] - T[3], hy1 = y * T[7] - T[4], hy2 = y * T[8] - T[5];
    const float p2 = hx0 * hy1 - hx1 * hy0;
    const float gp0 = g_u / p2;
    const float gp1 = g_v / p2;
    const float gp2 = -(g_u * u + g_v * v) / p2;
    // p = a x b  =>  dL/da = b x g_p, dL/db = g_p x a.
    const float ga0 = hy1 * gp2 - hy2 * gp1;
    const float ga1 = hy2 * gp0 - hy0 * gp2;
    const float ga2 = hy0 * gp1 - hy1 * gp0;
    const float gb0 = gp1 * hx2 - gp2 * hx1;
    const float gb1 = gp2 * hx0 - gp0 * hx2;
    const float gb2 = gp0 * hx1 - gp1 * hx0;
    // a = x T2 - T0, b = y T2 - T1 (rows).
    g_T[0] -= ga0;
    g_T[1] -= ga1;
    g_T[2] -= ga2;
    g_T[3] -= gb0;
    g_T[4] -= gb1;
    g_T[5] -= gb2;
    g_T[6] += x * ga0 + y * gb0;
    g_T[7] += x * ga1 + y * gb1;
    g_T[8] += x * ga2 + y * gb2;
}

// Keep the K largest weights seen so far (ties: the earlier position stays). The list is not
// sorted: `evict` is the slot the next larger weight replaces, the smallest weight (the latest
// position among equal ones). Most blended surfels of a pixel do not enter a full list, so the
// common case is one comparison, not an insertion that shifts the list.
PSIMAP_HD void topk_insert(float* top_w, int* top_pos, int& count, int& evict, int K, float w, int pos) {
    if (count < K) {
        top_w[count] = w;
        top_pos[count] = pos;
        if (++count < K) return;
    } else {
        if (!(w > top_w[evict])) return;
        top_w[evict] = w;
        top_pos[evict] = pos;
    }
    int e = 0;
    for (int k = 1; k < K; ++k)
        if (top_w[k] < top_w[e] || (top_w[k] == top_w[e] && top_pos[k] > top_pos[e])) e = k;
    evict = e;
}

}  // namespace psimap
