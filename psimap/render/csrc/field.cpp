// Rows of the panoptic field's distribution split over `threads` threads, each block on the pixel
// kernels' instruction set (field_lanes.inl). Compiled with the default flags.
#include "field.h"

#include "rasterize.h"

namespace psimap {

namespace {
constexpr int64_t kRowBlock = 64;        // rows per task
constexpr int64_t kParallelFrom = 32768; // fewer values than this: one thread (no region to start)

int64_t blocks_of(int64_t V) { return (V + kRowBlock - 1) / kRowBlock; }
int64_t block_end(int64_t b, int64_t V) { return b * kRowBlock + kRowBlock < V ? b * kRowBlock + kRowBlock : V; }
}  // namespace

void field_distribution_forward(const float* dot, const double* m2, const float* p_thing, int64_t V,
                                int64_t Q, float temperature, float* out, float* soft, int threads) {
    const PixelKernels& k = pixel_kernels();
    const int64_t nb = blocks_of(V);
#pragma omp parallel for schedule(static) num_threads(threads) if (threads > 1 && V * Q >= kParallelFrom)
    for (int64_t b = 0; b < nb; ++b)
        k.field_forward(dot, m2, p_thing, b * kRowBlock, block_end(b, V), Q, temperature, out, soft);
}

void field_distribution_backward(const float* dot, const double* m2, const float* p_thing,
                                 const float* soft, const float* v_out, int64_t V, int64_t Q,
                                 float temperature, float* v_dot, double* v_m2, float* v_p_thing,
                                 int threads) {
    const PixelKernels& k = pixel_kernels();
    const int64_t nb = blocks_of(V);
#pragma omp parallel for schedule(static) num_threads(threads) if (threads > 1 && V * Q >= kParallelFrom)
    for (int64_t b = 0; b < nb; ++b)
        k.field_backward(dot, m2, p_thing, soft, v_out, b * kRowBlock, block_end(b, V), Q, temperature,
                         v_dot, v_m2, v_p_thing);
}

}  // namespace psimap
