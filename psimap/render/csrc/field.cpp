// The panoptic field's distribution on the pixel kernels' instruction set (field_lanes.inl), all
// rows on the calling thread: the panoptic steps run on one core while the second builds the frozen
// blends or steps the surfel features' optimizer (psimap.panoptic.fit), and a team of two waiting on
// that core took ~10 ms a room step where one thread took ~5. Compiled with the default flags.
#include "field.h"

#include "rasterize.h"

namespace psimap {

void field_distribution_forward(const float* dot, const double* m2, const float* p_thing, int64_t V,
                                int64_t Q, float temperature, float* out, float* soft) {
    pixel_kernels().field_forward(dot, m2, p_thing, 0, V, Q, temperature, out, soft);
}

void field_distribution_backward(const float* dot, const double* m2, const float* p_thing,
                                 const float* soft, const float* v_out, int64_t V, int64_t Q,
                                 float temperature, float* v_dot, double* v_m2, float* v_p_thing) {
    pixel_kernels().field_backward(dot, m2, p_thing, soft, v_out, 0, V, Q, temperature, v_dot, v_m2,
                                   v_p_thing);
}

}  // namespace psimap
