// Stage 3 of psimap/render/SPEC.md, forward only, on a CUDA device: one thread block per 16x16
// tile, one thread per pixel; each warp owns an 8x4 block of the tile and walks the tile's surfel
// list front to back on its own, 32 surfels at a time: each lane stages one surfel in the warp's
// slice of shared memory if the surfel's box (the one it was binned by: the tight box with precise
// tiles, the circle's with the baseline) meets the warp's block, and the warp evaluates only those
// (every lane reads the same staged surfel: a broadcast). A pixel outside a surfel's box has
// alpha < 1/255, so the skip changes nothing; a warp stops when its 32 pixels have.
//
// The torch reference (psimap/render/reference.py: blend_tiles) is the oracle; the per-pixel math
// follows it step for step (the homogeneous ray-splat hit as p = x a + y b + c with the cross
// products of T's rows, the squared edge-on test, the low-pass fallback, the alpha rules), in
// float32 like the reference on float32 inputs; the one-pass distortion is a difference of O(1)
// NDC-depth moments and is summed in double (float32 cancels to ~1e-7 absolute).
//
// Features: with topk = 0 every blended surfel's C channels are added in registers (the paper's
// baseline, templated on a channel capacity); with topk = K each pixel keeps its K largest
// weights (ties: the earlier surfel stays) in registers and sums its K feature rows at the end
// (the paper's Top-K hard selection), so the walk touches no feature.
#include <cuda_runtime.h>

#include <cstdint>

#include "blend.h"

namespace psimap_cuda {
namespace {

constexpr int kTile = 16;
constexpr int kThreads = kTile * kTile;
constexpr int kWarps = kThreads / 32;
constexpr int kBlockW = 8, kBlockH = 4;      // a warp's pixels; kTile / kBlockW = 2 blocks a row
constexpr unsigned kFull = 0xffffffffu;
constexpr float kAlphaMax = 0.99f;
constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kTStop = 1e-4f;
constexpr float kEdgeOnEps2 = 1e-20f;       // EDGE_ON_EPS ** 2
constexpr float kHitBound = 1e10f;          // 1 / EDGE_ON_EPS
constexpr float kChi2 = 9.0f;               // CHI ** 2
constexpr float kLowpassRho2Max = 5.541263545158426f;   // ln 255

// One staged surfel: a, b, c (p = x a + y b + c), T's last row, the edge-on coefficients
// |x T2 - T0|^2 = x^2 t22 + x hx1 + hx0 (and y's), the centre, opacity.
constexpr int kStaged = 20;

// Adds w * row[0:C] to acc (C <= CB), four channels a load when rows are 16-byte aligned.
template <int CB>
__device__ __forceinline__ void add_row(float (&acc)[CB], const float* row, int C, float w, bool vec4) {
  if (vec4) {
#pragma unroll
    for (int c = 0; c < CB; c += 4) {
      if (c < C) {
        const float4 v = *reinterpret_cast<const float4*>(row + c);
        acc[c] += w * v.x; acc[c + 1] += w * v.y; acc[c + 2] += w * v.z; acc[c + 3] += w * v.w;
      }
    }
  } else {
#pragma unroll
    for (int c = 0; c < CB; ++c)
      if (c < C) acc[c] += w * row[c];
  }
}

// Three blocks a multiprocessor (<= 85 registers) for the small instances: the kernel is latency
// bound (a warp issues every ~7 cycles), and on an H200 the cap took C = 32 full blending from
// 0.231 to 0.211 ms (60k surfels); the wide ones would spill under it.
template <int CB, int KMAX>
constexpr int min_blocks() { return CB <= 32 && KMAX <= 8 ? 3 : 1; }

template <int CB, int KMAX>
__global__ void __launch_bounds__(kThreads, min_blocks<CB, KMAX>())
blend_forward_kernel(const BlendForwardArgs args, float far_minus_near) {
  __shared__ float s_surf[kWarps][32][kStaged];
  __shared__ int s_id[kWarps][32];

  const int tile = blockIdx.x;
  const int warp = threadIdx.x >> 5, lane = threadIdx.x & 31;
  const int bx0 = (tile % args.tiles_x) * kTile + (warp & 1) * kBlockW;
  const int by0 = (tile / args.tiles_x) * kTile + (warp >> 1) * kBlockH;
  const int px = bx0 + (lane & (kBlockW - 1));
  const int py = by0 + lane / kBlockW;
  const bool inside = px < args.width && py < args.height;
  const float x = static_cast<float>(px);
  const float y = static_cast<float>(py);
  const int C = args.channels;
  const int K = args.topk;
  // Feature rows and output pixels are 16-byte aligned when C is a multiple of 4 (torch's
  // allocations are 256-byte aligned).
  const bool vec4 = (C & 3) == 0;

  const int start = args.offsets[tile];
  const int count = args.offsets[tile + 1] - start;
  float (*stage)[kStaged] = s_surf[warp];
  int* stage_id = s_id[warp];

  float trans = 1.0f;
  float rgb0 = 0.f, rgb1 = 0.f, rgb2 = 0.f, n0 = 0.f, n1 = 0.f, n2 = 0.f;
  float depth_num = 0.f, median = 0.f;
  double dist = 0.0, acc_w = 0.0, acc_wm = 0.0, acc_wm2 = 0.0;
  constexpr int kAcc = CB > 0 ? CB : 1;
  float feat[kAcc];
#pragma unroll
  for (int c = 0; c < kAcc; ++c) feat[c] = 0.f;
  constexpr int kTop = KMAX > 0 ? KMAX : 1;
  float top_w[kTop];
  int top_id[kTop];
#pragma unroll
  for (int j = 0; j < kTop; ++j) { top_w[j] = -1.f; top_id[j] = -1; }
  float threshold = -1.f;   // the K-th largest weight so far (-1 while fewer than K)
  unsigned int evaluated = 0;
  bool done = !inside;

  for (int b0 = 0; b0 < count; b0 += 32) {
    if (__all_sync(kFull, done)) break;
    const int k = b0 + lane;
    bool meets = false;
    if (k < count) {
      const int id = args.surfel_ids[start + k];
      const int4 box = reinterpret_cast<const int4*>(args.boxes)[id];
      meets = box.x < bx0 + kBlockW && box.z > bx0 && box.y < by0 + kBlockH && box.w > by0;
      if (meets) {
        const float* t = args.T + 9 * static_cast<int64_t>(id);
        const float t00 = t[0], t01 = t[1], t02 = t[2], t10 = t[3], t11 = t[4], t12 = t[5];
        const float t20 = t[6], t21 = t[7], t22 = t[8];
        float* s = stage[lane];
        // a = T1 x T2, b = T2 x T0, c = T0 x T1
        s[0] = t11 * t22 - t12 * t21;  s[1] = t12 * t20 - t10 * t22;  s[2] = t10 * t21 - t11 * t20;
        s[3] = t21 * t02 - t22 * t01;  s[4] = t22 * t00 - t20 * t02;  s[5] = t20 * t01 - t21 * t00;
        s[6] = t01 * t12 - t02 * t11;  s[7] = t02 * t10 - t00 * t12;  s[8] = t00 * t11 - t01 * t10;
        s[9] = t20;  s[10] = t21;  s[11] = t22;
        s[12] = t20 * t20 + t21 * t21 + t22 * t22;
        s[13] = -2.f * (t00 * t20 + t01 * t21 + t02 * t22);
        s[14] = t00 * t00 + t01 * t01 + t02 * t02;
        s[15] = -2.f * (t10 * t20 + t11 * t21 + t12 * t22);
        s[16] = t10 * t10 + t11 * t11 + t12 * t12;
        s[17] = args.center[2 * static_cast<int64_t>(id)];
        s[18] = args.center[2 * static_cast<int64_t>(id) + 1];
        s[19] = args.opacities[id];
        stage_id[lane] = id;
      }
    }
    unsigned todo = __ballot_sync(kFull, meets);
    __syncwarp();
    while (todo && !done) {
      const int j = __ffs(todo) - 1;
      todo &= todo - 1;
      const float* s = stage[j];
      ++evaluated;
      const float p0 = x * s[0] + y * s[3] + s[6];
      const float p1 = x * s[1] + y * s[4] + s[7];
      const float p2 = x * s[2] + y * s[5] + s[8];
      const float hx2 = fmaxf(x * x * s[12] + x * s[13] + s[14], 0.f);
      const float hy2 = fmaxf(y * y * s[12] + y * s[15] + s[16], 0.f);
      const bool hit = p2 * p2 > kEdgeOnEps2 * hx2 * hy2;
      float u = 0.f, v = 0.f;
      if (hit) {
        u = fminf(fmaxf(p0 / p2, -kHitBound), kHitBound);
        v = fminf(fmaxf(p1 / p2, -kHitBound), kHitBound);
      }
      const float rho3 = u * u + v * v;
      const float z3 = s[9] * u + s[10] * v + s[11];
      const bool valid3 = hit && rho3 <= kChi2 && z3 > args.near_plane;
      const float g3 = valid3 ? expf(-0.5f * rho3) : 0.f;
      const float dx = x - s[17], dy = y - s[18];
      const float rho2 = dx * dx + dy * dy;
      const float g2 = rho2 <= kLowpassRho2Max ? expf(-rho2) : 0.f;
      const bool use3 = valid3 && g3 >= g2;
      const float g = use3 ? g3 : g2;
      const float alpha = fminf(kAlphaMax, s[19] * g);
      if (alpha < kAlphaMin) continue;
      const float next = trans * (1.f - alpha);
      if (next < kTStop) { done = true; break; }
      const int id = stage_id[j];
      const float d = use3 ? z3 : args.depth_key[id];
      const float w = alpha * trans;
      const float* col = args.colors + 3 * static_cast<int64_t>(id);
      rgb0 += w * col[0]; rgb1 += w * col[1]; rgb2 += w * col[2];
      const float* nc = args.normal_c + 3 * static_cast<int64_t>(id);
      n0 += w * nc[0]; n1 += w * nc[1]; n2 += w * nc[2];
      depth_num += w * d;
      if (trans > 0.5f) median = d;
      const double dd = d, wd = w;
      const double m = args.far_plane * (dd - args.near_plane) / (far_minus_near * dd);
      dist += wd * (m * m * acc_w + acc_wm2 - 2.0 * m * acc_wm);
      acc_w += wd; acc_wm += wd * m; acc_wm2 += wd * m * m;
      if constexpr (CB > 0) add_row<CB>(feat, args.features + static_cast<int64_t>(C) * id, C, w, vec4);
      if constexpr (KMAX > 0) {
        if (w > threshold) {
          // Insert into the descending list: a strictly larger weight moves ahead, so among
          // equal weights the earlier surfel stays first; the K-th slot's old entry drops out.
          float cw = w;
          int ci = id;
#pragma unroll
          for (int q = 0; q < KMAX; ++q) {
            if (q >= K) break;
            if (cw > top_w[q]) {
              const float tw = top_w[q]; const int ti = top_id[q];
              top_w[q] = cw; top_id[q] = ci; cw = tw; ci = ti;
            }
          }
#pragma unroll
          for (int q = 0; q < KMAX; ++q)
            if (q == K - 1) threshold = top_w[q];
        }
      }
      trans = next;
    }
    __syncwarp();   // the warp's stage is read before the next batch overwrites it
  }

  // Warp sums of the evaluation counts, one atomic per warp.
  unsigned long long ev = evaluated;
#pragma unroll
  for (int off = 16; off > 0; off >>= 1) ev += __shfl_down_sync(kFull, ev, off);
  if (lane == 0 && ev) atomicAdd(args.evaluated, ev);

  if (inside) {
    const int64_t pix = static_cast<int64_t>(py) * args.width + px;
    const float a = 1.f - trans;
    args.rgb[3 * pix] = rgb0 + trans * args.bg_r;
    args.rgb[3 * pix + 1] = rgb1 + trans * args.bg_g;
    args.rgb[3 * pix + 2] = rgb2 + trans * args.bg_b;
    args.alpha[pix] = a;
    args.depth[pix] = a > 1e-6f ? depth_num / a : 0.f;
    args.median[pix] = median;
    args.normal[3 * pix] = n0; args.normal[3 * pix + 1] = n1; args.normal[3 * pix + 2] = n2;
    args.distortion[pix] = static_cast<float>(dist);
    if constexpr (CB > 0) {
      float* out = args.out_features + static_cast<int64_t>(C) * pix;
      if (vec4) {
#pragma unroll
        for (int c = 0; c < CB; c += 4)
          if (c < C) *reinterpret_cast<float4*>(out + c) = make_float4(feat[c], feat[c + 1], feat[c + 2], feat[c + 3]);
      } else {
#pragma unroll
        for (int c = 0; c < CB; ++c)
          if (c < C) out[c] = feat[c];
      }
    }
  }
  if constexpr (KMAX > 0) {
    // The Top-K features: each lane sums its pixel's K rows, four channels a load, in descending
    // weight. Measured on an H200 (60k and 600k surfels, C = 32 to 128, K = 8), this beat the
    // warp's lanes sharing one pixel's channels (coalesced rows, but two shuffles a row and 32
    // pixels in turn) by 10-30 %: neighbouring pixels share most surfels, so the rows hit L1.
    if (inside) {
      float* out = args.out_features + static_cast<int64_t>(C) * (static_cast<int64_t>(py) * args.width + px);
      if (vec4) {
        for (int c = 0; c < C; c += 4) {
          float4 sum = make_float4(0.f, 0.f, 0.f, 0.f);
#pragma unroll
          for (int q = 0; q < KMAX; ++q) {
            if (q >= K) break;
            if (top_id[q] >= 0) {
              const float4 v = *reinterpret_cast<const float4*>(args.features + static_cast<int64_t>(C) * top_id[q] + c);
              sum.x += top_w[q] * v.x; sum.y += top_w[q] * v.y; sum.z += top_w[q] * v.z; sum.w += top_w[q] * v.w;
            }
          }
          *reinterpret_cast<float4*>(out + c) = sum;
        }
      } else {
        for (int c = 0; c < C; ++c) {
          float sum = 0.f;
#pragma unroll
          for (int q = 0; q < KMAX; ++q) {
            if (q >= K) break;
            if (top_id[q] >= 0) sum += top_w[q] * args.features[static_cast<int64_t>(C) * top_id[q] + c];
          }
          out[c] = sum;
        }
      }
    }
  }
}

template <int CB, int KMAX>
const char* launch(const BlendForwardArgs& args, cudaStream_t stream) {
  const dim3 grid(args.tiles_x * args.tiles_y);
  const dim3 block(kThreads);
  const float far_minus_near = static_cast<float>(static_cast<double>(args.far_plane) - args.near_plane);
  blend_forward_kernel<CB, KMAX><<<grid, block, 0, stream>>>(args, far_minus_near);
  const cudaError_t err = cudaGetLastError();
  return err == cudaSuccess ? nullptr : cudaGetErrorString(err);
}

}  // namespace

bool blend_forward_supported(int channels, int topk) {
  if (channels < 0 || topk < 0) return false;
  if (channels == 0) return true;
  return topk > 0 ? topk <= kMaxTopK : channels <= kMaxChannelsAll;
}

const char* launch_blend_forward(const BlendForwardArgs& args, void* stream_ptr) {
  const cudaStream_t stream = static_cast<cudaStream_t>(stream_ptr);
  if (args.tiles_x <= 0 || args.tiles_y <= 0) return nullptr;
  const int C = args.channels, K = args.topk;
  if (!blend_forward_supported(C, K)) return "feature width / topk beyond the CUDA kernel's registers";
  if (C == 0) return launch<0, 0>(args, stream);
  if (K > 0) {
    if (K <= 4) return launch<0, 4>(args, stream);
    if (K <= 8) return launch<0, 8>(args, stream);
    if (K <= 16) return launch<0, 16>(args, stream);
    return launch<0, 32>(args, stream);
  }
  if (C <= 4) return launch<4, 0>(args, stream);
  if (C <= 8) return launch<8, 0>(args, stream);
  if (C <= 16) return launch<16, 0>(args, stream);
  if (C <= 32) return launch<32, 0>(args, stream);
  return launch<64, 0>(args, stream);
}

}  // namespace psimap_cuda
