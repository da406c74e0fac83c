// Native CPU surfel rasterizer: declarations shared by binning / forward / backward / bindings.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "surfel_math.h"

namespace psimap {

// Per-surfel stage-1 inputs (contiguous float32, N rows).
struct SurfelInputs {
    int64_t n = 0;
    int channels = 0;              // C feature channels
    const float* T = nullptr;      // [N, 9]
    const float* center = nullptr; // [N, 2]
    const float* depth_key = nullptr;  // [N]
    const float* normal = nullptr; // [N, 3]
    const float* opacity = nullptr;  // [N]
    const float* color = nullptr;  // [N, 3]
    const float* feature = nullptr;  // [N, C]
    const int32_t* box = nullptr;    // [N, 4] (x0, y0, x1, y1) half-open pixel boxes used to bin
};

// Tiles in row-major order; surfels of tile t are ids[offsets[t] .. offsets[t+1]) front to back.
struct TileBins {
    int tiles_x = 0, tiles_y = 0;
    const int32_t* offsets = nullptr;  // [tiles + 1]
    const int32_t* ids = nullptr;      // [pairs]
};

inline int tiles_along(int pixels) { return (pixels + kTile - 1) / kTile; }

struct RasterConfig {
    int width = 0, height = 0;
    int topk = 0;  // 0: blend features over every surfel
    // Precise tiles: besides its tight box, a surfel reaches a 4x4 pixel block only when the block
    // meets its footprint (the ellipse where alpha can reach 1/255, and the low-pass disk).
    bool exact_footprint = false;
    float near = 0.2f, far = 1000.0f;
    float background[3] = {0.0f, 0.0f, 0.0f};
};

// Forward outputs [H, W, ...] and what the backward needs per pixel.
struct ForwardBuffers {
    float* rgb;          // [H, W, 3]
    float* alpha;        // [H, W]
    float* depth;        // [H, W]
    float* median;       // [H, W]
    float* normal;       // [H, W, 3]
    float* distortion;   // [H, W]
    float* feature;      // [H, W, C]
    float* t_final;      // [H, W] final transmittance
    int32_t* n_last;     // [H, W] tile-list position after the last blended surfel
    int32_t* median_pos; // [H, W] tile-list position of the median surfel, -1 if none
    double* dist_sums;   // [H, W, 3] sum w, sum w m, sum w m^2 (distortion totals, double: the
                         // distortion is a small difference of O(1) moments)
    int32_t* topk_pos;   // [H, W, K] selected tile-list positions, -1 padded (K = topk > 0)
    float* topk_w = nullptr;  // [H, W, K] their blending weights w = alpha T, 0 padded; optional
                              // (a frozen geometry's feature renders are then a gather: panoptic)
};

struct BackwardGrads {
    // dL/d outputs
    const float* rgb;
    const float* alpha;
    const float* depth;
    const float* median;
    const float* normal;
    const float* distortion;
    const float* feature;
    // dL/d surfel inputs (written, not accumulated)
    float* T;          // [N, 9]
    float* center;     // [N, 2]
    float* depth_key;  // [N]
    float* normal_c;   // [N, 3]
    float* opacity;    // [N]
    float* color;      // [N, 3]
    float* feat;       // [N, C]
};

// Fills offsets [tiles + 1] and ids [pairs] (see TileBins).
void bin_tiles(const int32_t* boxes, const uint8_t* valid, const float* depth_key, int64_t n,
               int width, int height, std::vector<int32_t>& offsets, std::vector<int32_t>& ids);

int64_t rasterize_forward(const SurfelInputs& in, const TileBins& bins, const RasterConfig& cfg,
                          const ForwardBuffers& out);

void rasterize_backward(const SurfelInputs& in, const TileBins& bins, const RasterConfig& cfg,
                        const ForwardBuffers& saved, const BackwardGrads& g);

// Where a surfel can reach alpha >= 1/255 in the image (for culling pixel blocks): the ellipse
// (x - e)^T adj(M) (x - e) <= det(M) (M: the 2x2 shape of the image of the disk u^2 + v^2 <= r3^2,
// r3^2 = min(chi^2, 2 half_rho_cut)) united with the low-pass disk |x - c|^2 <= r2^2.
struct Footprint {
    double ex, ey;        // ellipse centre
    double a, b, c, det;  // adj(M) = [[a, b], [b, c]], det(M)
    bool ellipse;         // false: unbounded or degenerate, test the box only
    bool any;             // false: nothing of this surfel reaches 1/255
    double cx, cy, r2;    // low-pass disk centre and squared radius (r2 < 0: none)
};

// Gathers tile `t`'s surfels into `params` (front to back); `footprints` too when not null.
void gather_tile(const SurfelInputs& in, const TileBins& bins, int t,
                 std::vector<SurfelParams>& params, std::vector<Footprint>* footprints = nullptr);

// A tile is split in kBlocks x kBlocks pixel blocks; each pixel only walks the surfels whose box
// meets its block (tile-list positions, front to back): positions
// pos[starts[b] .. starts[b+1]) for block b = by * kBlocks + bx.
constexpr int kBlockPx = 4;
constexpr int kBlocks = kTile / kBlockPx;
// With `footprints`, a surfel joins a block only when the block also meets its footprint.
void block_lists(const std::vector<SurfelParams>& params, int tile_x0, int tile_y0,
                 std::vector<int32_t>& pos, int32_t* starts,
                 const std::vector<Footprint>* footprints = nullptr);

inline int block_of(int px, int py, int tile_x0, int tile_y0) {
    return ((py - tile_y0) / kBlockPx) * kBlocks + (px - tile_x0) / kBlockPx;
}

// One tile's pixel work, handed to the SIMD pixel kernels (raster_lanes.inl).
struct TileWork {
    int x0, y0;                   // the tile's first pixel
    const SurfelParams* params;   // the tile's surfels, front to back (gather_tile)
    const int32_t* ids;           // their surfel indices (bins.ids + offsets[t])
    const int32_t* block_pos;     // block lists (block_lists)
    const int32_t* block_start;   // [kBlocks * kBlocks + 1]
    float* scratch;               // kernel_scratch_floats(C) floats, one buffer per thread
    // Backward only: the tile's gradient rows (kGradSlots floats per surfel, then C), written, and
    // per-lane partial sums (n x kGradSlots x 16 floats, with `touched` [n] flags), scratch.
    int n = 0;
    float* grad_rows = nullptr;
    float* grad_feat = nullptr;
    float* lane_acc = nullptr;
    uint8_t* touched = nullptr;
};

// Per (tile, surfel) gradient slots besides the features: dL/dT [9], center [2], depth_key,
// normal_c [3], opacity, color [3].
constexpr int kGradT = 0, kGradCenter = 9, kGradDepthKey = 11, kGradNormal = 12, kGradOpacity = 15,
              kGradColor = 16, kGradSlots = 19;
constexpr int kMaxLanes = 16;

inline int64_t kernel_scratch_floats(int channels) { return static_cast<int64_t>(channels) * 16 + 16; }
// match_sums' scratch: a row's three values and five block sums per mask, Q rounded up to the
// widest lanes, then a byte per mask.
inline int64_t match_scratch_floats(int64_t Q, int64_t M) {
    return (3 + 5 * M) * ((Q + kMaxLanes - 1) / kMaxLanes * kMaxLanes) + M / 4 + 1;
}

// The pixel kernels compiled for one instruction set (raster_isa_*.cpp); every set gives the
// same forward bits (the lanes are pixels: each makes the per-pixel decisions in the same order).
struct PixelKernels {
    const char* isa;   // "avx512", "avx2", "baseline"
    int lanes;         // pixels per vector
    int64_t (*forward)(const SurfelInputs& in, const RasterConfig& cfg, const ForwardBuffers& out,
                       const TileWork& work);  // returns the (pixel, surfel) evaluations
    void (*backward)(const SurfelInputs& in, const RasterConfig& cfg, const ForwardBuffers& saved,
                     const BackwardGrads& g, const TileWork& work);  // fills work.grad_rows / grad_feat
    void (*exp)(const float* x, float* out, int64_t n);  // the kernels' exp_nonpositive, for tests
    // the panoptic field's per-surfel distribution on rows [v0, v1) (field_lanes.inl)
    void (*field_forward)(const float* dot, const double* terms, const double* coef_t, int64_t K,
                          const float* p_thing, int64_t v0, int64_t v1, int64_t Q, float temperature, float* out,
                          float* soft);
    void (*field_backward)(const float* dot, const double* terms, const double* coef_t, int64_t K,
                           const float* p_thing, const float* soft, const float* v_out, int64_t v0, int64_t v1,
                           int64_t Q, float temperature, float* v_dot, double* v_coef_t, float* v_p_thing);
    // the matching's per-mask sums over pixels [p0, p1) (match_lanes.inl); scratch:
    // match_scratch_floats(Q, M) floats
    void (*match_sums)(const float* x, const uint8_t* codes, int64_t P, int64_t p0, int64_t p1, int64_t Q,
                       int64_t M, float lo, float hi, double* sums, float* scratch);
    // the frozen blend's CSR product on rows [r0, r1) (blend_lanes.inl): out = A f
    void (*blend_forward)(const int64_t* indptr, const int32_t* indices, const float* data, const float* f,
                          int64_t r0, int64_t r1, int64_t C, float* out);
    // the panoptic field's affinity alone on rows [v0, v1) (field_lanes.inl)
    void (*field_affinity)(const float* dot, const double* terms, const double* coef_t, int64_t K, int64_t v0,
                           int64_t v1, int64_t Q, float* out);
};

// The kernels in use: the widest instruction set this CPU runs, unless select_kernels chose one.
const PixelKernels& pixel_kernels();
// Names of the instruction sets built into the module that this CPU can run, widest first.
std::vector<std::string> available_kernels();
// Use the named set ("" = the widest available); false when it is not available.
bool select_kernels(const std::string& isa);

}  // namespace psimap
