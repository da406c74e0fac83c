// Stage 1 of SPEC.md (projection) in C++: declarations shared by project.cpp and the bindings.
#pragma once

#include <cstdint>

namespace psimap {

// Surfel parameters (N rows, contiguous, float or double) and the camera (double).
template <typename F>
struct ProjectInputs {
    int64_t n = 0;
    const F* means = nullptr;    // [N, 3]
    const F* quats = nullptr;    // [N, 4] (w, x, y, z), normalised inside
    const F* scales = nullptr;   // [N, 2]
    const F* opacity = nullptr;  // [N]
    const double* viewmat = nullptr;  // [4, 4] world-to-camera (OpenCV)
    const double* K = nullptr;        // [3, 3]
    int width = 0, height = 0;
    double near = 0.2, far = 1000.0;
};

template <typename F>
struct ProjectOutputs {
    F* T;                  // [N, 9] splat-to-pixel homography, row major
    F* center;             // [N, 2]
    F* depth_key;          // [N]
    F* normal;             // [N, 3] camera frame, facing the camera
    uint8_t* valid;        // [N] not culled
    uint8_t* flip;         // [N] the normal was flipped to face the camera (for the backward)
    int32_t* box_precise;  // [N, 4]
    int32_t* box_circle;   // [N, 4]
};

// dL/d outputs in, dL/d (means, quats, scales) out (written, not accumulated).
template <typename F>
struct ProjectGrads {
    const F* T;
    const F* center;
    const F* depth_key;
    const F* normal;
    F* means;
    F* quats;
    F* scales;
};

template <typename F>
void project_forward(const ProjectInputs<F>& in, const ProjectOutputs<F>& out);

template <typename F>
void project_backward(const ProjectInputs<F>& in, const uint8_t* valid, const uint8_t* flip,
                      const ProjectGrads<F>& g);

}  // namespace psimap
