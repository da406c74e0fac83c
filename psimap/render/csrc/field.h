// The panoptic field's fused per-surfel instance distribution (field_lanes.inl: the math), on the
// calling thread: psimap.render.native.instance_distribution wraps it for torch.
#pragma once

#include <cstdint>

namespace psimap {

// dot [V, Q] float32, m2 [V, Q] float64, p_thing [V] or null -> out [V, Q], soft [V, Q].
void field_distribution_forward(const float* dot, const double* m2, const float* p_thing, int64_t V,
                                int64_t Q, float temperature, float* out, float* soft);

// v_out [V, Q] -> v_dot [V, Q], v_m2 [V, Q] float64, v_p_thing [V] (written when p_thing is given).
void field_distribution_backward(const float* dot, const double* m2, const float* p_thing,
                                 const float* soft, const float* v_out, int64_t V, int64_t Q,
                                 float temperature, float* v_dot, double* v_m2, float* v_p_thing);

}  // namespace psimap
