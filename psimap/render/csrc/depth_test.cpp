#include "depth_test.h"

#include <cmath>

namespace psimap {

int64_t depth_test(const double* points, int64_t n, const double* c2w, const double* K, int64_t w,
                   int64_t h, const double* depth, double tol, DepthTestMode mode, uint8_t* state) {
    // world -> camera: R^T (x - t), R = c2w[:3, :3], t = c2w[:3, 3]; the reference's column sums
    const double r00 = c2w[0], r01 = c2w[1], r02 = c2w[2], tx = c2w[3];
    const double r10 = c2w[4], r11 = c2w[5], r12 = c2w[6], ty = c2w[7];
    const double r20 = c2w[8], r21 = c2w[9], r22 = c2w[10], tz = c2w[11];
    const double fx = K[0], cx = K[2], fy = K[4], cy = K[5];
    const double wd = static_cast<double>(w), hd = static_cast<double>(h);
    int64_t hits = 0;
    for (int64_t i = 0; i < n; ++i) {
        if (state[i]) continue;
        const double dx = points[3 * i] - tx, dy = points[3 * i + 1] - ty, dz = points[3 * i + 2] - tz;
        const double z = dx * r02 + dy * r12 + dz * r22;
        if (!(z > 1e-6)) continue;  // behind the camera (or NaN)
        const double x = dx * r00 + dy * r10 + dz * r20;
        const double y = dx * r01 + dy * r11 + dz * r21;
        // the reference floors u and v and asks 0 <= floor(u) < w: for an integer w the same as 0 <=
        // u < w, and for u >= 0 the cast truncates as floor does (floor is a libm call on baseline
        // x86-64, which has no rounding instruction)
        const double u = fx * x / z + cx;
        const double v = fy * y / z + cy;
        if (!(u >= 0.0 && u < wd && v >= 0.0 && v < hd)) continue;
        const double d = depth[static_cast<int64_t>(v) * w + static_cast<int64_t>(u)];
        if (!(std::isfinite(d) && d > 0.0)) continue;
        const bool hit = mode == DepthTestMode::kFree ? z < d - tol : std::fabs(z - d) <= tol;
        if (hit) {
            state[i] = 1;
            ++hits;
        }
    }
    return hits;
}

}  // namespace psimap
