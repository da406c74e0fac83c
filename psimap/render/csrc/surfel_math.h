// Per-surfel constants and parameters of the surfel renderer (psimap/render/SPEC.md, stage 3); the
// per-pixel math is in raster_lanes.inl (SIMD lanes of pixels). No STL, so a CUDA build could share
// this header.
#pragma once

#include <math.h>

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

// rho/2 beyond which o * exp(-rho/2) < 1/255 for sure (the margin covers the 2-ulp error of
// exp_nonpositive, simd_lanes.h), so the pixel loop can skip the exponential without changing any
// decision of the exact test.
PSIMAP_HD float half_rho_cut(float opacity) {
    if (!(opacity >= kAlphaMin)) return -1.0f;  // alpha = o G <= o < 1/255 everywhere
    return logf(255.0f * opacity) * (1.0f + 1e-5f) + 1e-5f;
}

}  // namespace psimap
