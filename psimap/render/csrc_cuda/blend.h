// Stage 3 forward (SPEC.md) on a CUDA device: the launcher the torch bindings call.
// Plain pointers and a stream, so this header needs neither torch nor the CUDA runtime's headers.
#pragma once

#include <cstdint>

namespace psimap_cuda {

// Inputs are float32, contiguous, on the device; N surfels, C feature channels.
struct BlendForwardArgs {
  // Tile lists (stage 2): tile t owns surfel_ids[offsets[t] : offsets[t + 1]], front to back.
  const int32_t* offsets;   // [tiles + 1]
  const int32_t* surfel_ids;  // [pairs]
  const int32_t* boxes;     // [N, 4] the boxes the surfels were binned by (x0, y0, x1, y1), half-open
  int tiles_x, tiles_y, width, height;
  const float* T;           // [N, 3, 3] splat-to-pixel homography, row-major
  const float* center;      // [N, 2]
  const float* depth_key;   // [N]
  const float* normal_c;    // [N, 3]
  const float* opacities;   // [N]
  const float* colors;      // [N, 3]
  const float* features;    // [N, C] (nullptr when C = 0)
  int channels;             // C
  int topk;                 // 0 = blend every surfel's features, else the K largest weights
  float near_plane, far_plane;
  float bg_r, bg_g, bg_b;   // background added to rgb with the final transmittance
  // Outputs, [H * W] (x C): every pixel of the image is written.
  float* rgb;               // [H * W, 3]
  float* alpha;             // [H * W]
  float* depth;             // [H * W] expected depth (normalised by alpha; 0 where alpha <= 1e-6)
  float* median;            // [H * W]
  float* normal;            // [H * W, 3]
  float* distortion;        // [H * W]
  float* out_features;      // [H * W, C]
  unsigned long long* evaluated;  // [1] (pixel, surfel) evaluations, added to
};

// Largest feature width / Top-K the kernels hold in registers; larger ones are refused by
// `blend_forward_supported` (the bindings then raise and Python renders with torch).
constexpr int kMaxChannelsAll = 64;
constexpr int kMaxTopK = 32;

bool blend_forward_supported(int channels, int topk);
// Returns nullptr on success, else the CUDA error's text.
const char* launch_blend_forward(const BlendForwardArgs& args, void* stream);

}  // namespace psimap_cuda
