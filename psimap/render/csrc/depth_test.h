// Depth-map tests of world points for shape completion (psimap.completion.freespace): does a
// camera see a point in front of its observed surface, or on it? The numpy forms of the same
// name (known_free_reference, seen_on_surface_reference) are the readable references; the
// arithmetic is theirs, operation by operation (no FMA contraction: CMakeLists), so the answers
// are the same bits.
#pragma once

#include <cstdint>

namespace psimap {

enum class DepthTestMode : int { kFree = 0, kSurface = 1 };

// points [Q, 3] float64 world; c2w [4, 4] row-major (OpenCV camera to world); K [3, 3] row-major;
// depth [h, w] float64 metres (0 / non-finite: no return). Points whose state is non-zero are
// skipped (an earlier camera decided them); a hit sets state to 1. kFree hits: in front of the
// camera (z > 1e-6), inside the image, a finite positive depth d at its pixel and z < d - tol;
// kSurface: the same with |z - d| <= tol. Returns the number of new hits.
int64_t depth_test(const double* points, int64_t n, const double* c2w, const double* K, int64_t w,
                   int64_t h, const double* depth, double tol, DepthTestMode mode, uint8_t* state);

}  // namespace psimap
