// Stage 1 of SPEC.md (projection) and its backward, per surfel, OpenMP over surfels. The torch
// version in psimap/render/project.py is the readable reference; this one does the same math per
// surfel: the forward in the inputs' precision (as torch does), the tile boxes in double from the
// outputs T and centre (as the reference's _tile_boxes), the backward in double.
#include <algorithm>
#include <cmath>
#include <cstdint>

#include <omp.h>

#include "threads.h"

#include "project.h"

namespace psimap {

namespace {

constexpr double kChi = 3.0;
const double kLowPassRadius = std::sqrt(std::log(255.0));  // project.R_LOWPASS
constexpr double kBoxSlack = 1e-3;                       // project.BOX_SLACK

template <typename S>
struct Frame {
    S Rc[9], tc[3], K[9];
};

template <typename S>
Frame<S> frame_of(const double* viewmat, const double* K) {
    Frame<S> f;
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) {
            f.Rc[3 * r + c] = static_cast<S>(viewmat[4 * r + c]);
            f.K[3 * r + c] = static_cast<S>(K[3 * r + c]);
        }
        f.tc[r] = static_cast<S>(viewmat[4 * r + 3]);
    }
    return f;
}

// Inputs of surfel i after the reference's replacement of culled (non-finite / zero-quaternion)
// rows by harmless values; returns whether the row was finite. q comes back normalised, |q| in qnorm.
template <typename S, typename F>
bool safe_inputs(const F* means, const F* quats, const F* scales, const F* opac, int64_t i,
                 S mu[3], S q[4], S s[2], S& qnorm) {
    bool finite = std::isfinite(opac[i]);
    S qq = 0;
    for (int k = 0; k < 3; ++k) finite = finite && std::isfinite(means[3 * i + k]);
    for (int k = 0; k < 4; ++k) {
        const S v = static_cast<S>(quats[4 * i + k]);
        finite = finite && std::isfinite(v);
        qq += v * v;
    }
    for (int k = 0; k < 2; ++k) finite = finite && std::isfinite(scales[2 * i + k]);
    finite = finite && qq > 0;
    for (int k = 0; k < 3; ++k) mu[k] = finite ? static_cast<S>(means[3 * i + k]) : S(0);
    for (int k = 0; k < 2; ++k) s[k] = finite ? static_cast<S>(scales[2 * i + k]) : S(1);
    qnorm = finite ? std::sqrt(qq) : S(1);
    for (int k = 0; k < 4; ++k) q[k] = finite ? static_cast<S>(quats[4 * i + k]) / qnorm : S(k == 0 ? 1 : 0);
    return finite;
}

// Rotation matrix (row major, columns = tangent u, tangent v, normal) of the unit quaternion q.
template <typename S>
void rotation(const S q[4], S R[9]) {
    const S w = q[0], x = q[1], y = q[2], z = q[3];
    R[0] = 1 - 2 * (y * y + z * z); R[1] = 2 * (x * y - w * z); R[2] = 2 * (x * z + w * y);
    R[3] = 2 * (x * y + w * z); R[4] = 1 - 2 * (x * x + z * z); R[5] = 2 * (y * z - w * x);
    R[6] = 2 * (x * z - w * y); R[7] = 2 * (y * z + w * x); R[8] = 1 - 2 * (x * x + y * y);
}

// Camera-frame quantities of one surfel: mu_c, axes_c = Rc R (row major), T = K [a0 s0, a1 s1, mu_c].
template <typename S>
void camera_terms(const Frame<S>& f, const S mu[3], const S R[9], const S s[2], S mu_c[3], S axes[9],
                  S T[9]) {
    for (int r = 0; r < 3; ++r) {
        mu_c[r] = f.Rc[3 * r] * mu[0] + f.Rc[3 * r + 1] * mu[1] + f.Rc[3 * r + 2] * mu[2] + f.tc[r];
        for (int c = 0; c < 3; ++c)
            axes[3 * r + c] = f.Rc[3 * r] * R[c] + f.Rc[3 * r + 1] * R[3 + c] + f.Rc[3 * r + 2] * R[6 + c];
    }
    S cols[9];  // row major: cols[3 r + c]
    for (int r = 0; r < 3; ++r) {
        cols[3 * r] = axes[3 * r] * s[0];
        cols[3 * r + 1] = axes[3 * r + 1] * s[1];
        cols[3 * r + 2] = mu_c[r];
    }
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            T[3 * r + c] = f.K[3 * r] * cols[c] + f.K[3 * r + 1] * cols[3 + c] + f.K[3 * r + 2] * cols[6 + c];
}

// Pixel box (x0, y0, x1, y1) half-open, clipped to the image: project._tile_boxes' to_box.
void to_box(double lox, double loy, double hix, double hiy, bool ok, bool valid, int width,
            int height, int32_t* box) {
    const double size[2] = {static_cast<double>(width), static_cast<double>(height)};
    double lo[2] = {lox, loy}, hi[2] = {hix, hiy}, b[4];
    for (int k = 0; k < 2; ++k) {
        // fmax / fmin would drop a NaN; the reference keeps it, and then `ok` is false anyway.
        lo[k] = std::isnan(lo[k]) ? lo[k] : std::min(std::max(lo[k], -1.0), size[k] + 1);
        hi[k] = std::isnan(hi[k]) ? hi[k] : std::min(std::max(hi[k], -1.0), size[k] + 1);
        b[k] = ok ? std::ceil(lo[k]) : 0.0;
        b[k + 2] = ok ? std::floor(hi[k]) + 1 : size[k];
    }
    for (int k = 0; k < 4; ++k) b[k] = std::min(std::max(b[k], 0.0), size[k % 2]);
    const bool empty = b[2] <= b[0] || b[3] <= b[1] || !valid;
    for (int k = 0; k < 4; ++k) box[k] = empty ? 0 : static_cast<int32_t>(b[k]);
}

// Precise and circle boxes from the (rounded) outputs T and centre; see project._tile_boxes.
void tile_boxes(const double T[9], double cx, double cy, bool valid, int width, int height,
                int32_t* box_precise, int32_t* box_circle) {
    const double D[3] = {1.0, 1.0, -1.0 / (kChi * kChi)};
    double Cs[9];
    for (int i = 0; i < 3; ++i)
        for (int k = 0; k < 3; ++k)
            Cs[3 * i + k] = T[3 * i] * D[0] * T[3 * k] + T[3 * i + 1] * D[1] * T[3 * k + 1] +
                            T[3 * i + 2] * D[2] * T[3 * k + 2];
    const double c22 = Cs[8];
    const bool bounded = c22 < 0;
    const double c22s = bounded ? c22 : -1.0;
    const double ex = Cs[2] / c22s, ey = Cs[5] / c22s;
    double M[4];
    for (int i = 0; i < 2; ++i)
        for (int k = 0; k < 2; ++k)
            M[2 * i + k] = (Cs[3 * i + 2] * Cs[6 + k] - Cs[3 * i + k] * c22s) / (c22s * c22s);
    const double hx = std::sqrt(std::max(M[0], 0.0)), hy = std::sqrt(std::max(M[3], 0.0));
    bool ok = bounded && std::isfinite(ex) && std::isfinite(ey) && std::isfinite(hx) && std::isfinite(hy);
    for (int k = 0; k < 4; ++k) ok = ok && std::isfinite(M[k]);
    const double r = kLowPassRadius;
    to_box(std::min(ex - hx, cx - r) - kBoxSlack, std::min(ey - hy, cy - r) - kBoxSlack,
           std::max(ex + hx, cx + r) + kBoxSlack, std::max(ey + hy, cy + r) + kBoxSlack, ok, valid,
           width, height, box_precise);
    const double a = M[0], d = M[3], b = 0.5 * (M[1] + M[2]);
    const double lam = 0.5 * (a + d) + std::sqrt(0.25 * (a - d) * (a - d) + b * b);
    const double semi = std::sqrt(std::max(ok ? lam : 0.0, 0.0));
    const double radius = std::max(semi, std::sqrt((ex - cx) * (ex - cx) + (ey - cy) * (ey - cy)) + r) + kBoxSlack;
    to_box(ex - radius, ey - radius, ex + radius, ey + radius, ok, valid, width, height, box_circle);
}

}  // namespace

template <typename F>
void project_forward(const ProjectInputs<F>& in, const ProjectOutputs<F>& out) {
    // In the caller's precision F, as the reference computes in the tensors' dtype: then the
    // discrete decisions (near / far culling, the facing sign of an edge-on normal) agree with it.
    const Frame<F> f = frame_of<F>(in.viewmat, in.K);
    const F near = static_cast<F>(in.near), far = static_cast<F>(in.far);
#pragma omp parallel for schedule(static) num_threads(kernel_threads())
    for (int64_t i = 0; i < in.n; ++i) {
        F mu[3], q[4], s[2], qnorm, R[9], mu_c[3], axes[9], T[9];
        const bool finite = safe_inputs(in.means, in.quats, in.scales, in.opacity, i, mu, q, s, qnorm);
        rotation(q, R);
        camera_terms(f, mu, R, s, mu_c, axes, T);
        double Td[9];
        for (int k = 0; k < 9; ++k) {
            out.T[9 * i + k] = T[k];
            Td[k] = static_cast<double>(T[k]);
        }
        const F key = mu_c[2];
        const bool valid = finite && key > near && key <= far && in.opacity[i] > F(0);
        const F z_safe = valid ? T[8] : F(1);
        out.center[2 * i] = T[2] / z_safe;
        out.center[2 * i + 1] = T[5] / z_safe;
        out.depth_key[i] = key;
        const F facing = axes[2] * mu_c[0] + axes[5] * mu_c[1] + axes[8] * mu_c[2];
        const bool flip = facing > F(0);
        for (int k = 0; k < 3; ++k) out.normal[3 * i + k] = flip ? -axes[3 * k + 2] : axes[3 * k + 2];
        out.valid[i] = valid;
        out.flip[i] = flip;
        // Boxes in double from the outputs, like the reference's _tile_boxes.
        tile_boxes(Td, out.center[2 * i], out.center[2 * i + 1], valid, in.width, in.height,
                   out.box_precise + 4 * i, out.box_circle + 4 * i);
    }
}

template <typename F>
void project_backward(const ProjectInputs<F>& in, const uint8_t* valid, const uint8_t* flip,
                      const ProjectGrads<F>& g) {
    // In double (the gradients are sums of products; float32 loses digits to cancellation).
    const Frame<double> f = frame_of<double>(in.viewmat, in.K);
#pragma omp parallel for schedule(static) num_threads(kernel_threads())
    for (int64_t i = 0; i < in.n; ++i) {
        double mu[3], q[4], s[2], qnorm, R[9], mu_c[3], axes[9], T[9];
        const bool finite = safe_inputs(in.means, in.quats, in.scales, in.opacity, i, mu, q, s, qnorm);
        if (!finite) {  // the reference's torch.where passes no gradient to a replaced row
            for (int k = 0; k < 3; ++k) g.means[3 * i + k] = F(0);
            for (int k = 0; k < 4; ++k) g.quats[4 * i + k] = F(0);
            for (int k = 0; k < 2; ++k) g.scales[2 * i + k] = F(0);
            continue;
        }
        rotation(q, R);
        camera_terms(f, mu, R, s, mu_c, axes, T);
        double gT[9];
        for (int k = 0; k < 9; ++k) gT[k] = g.T[9 * i + k];
        // centre = (T02, T12) / z with z = T22 for valid surfels, 1 otherwise.
        const double gcx = g.center[2 * i], gcy = g.center[2 * i + 1];
        if (valid[i]) {
            const double z = T[8];
            gT[2] += gcx / z;
            gT[5] += gcy / z;
            gT[8] -= (gcx * T[2] + gcy * T[5]) / (z * z);
        } else {
            gT[2] += gcx;
            gT[5] += gcy;
        }
        // T = K cols  =>  g_cols = K^T g_T.
        double gcols[9];
        for (int r = 0; r < 3; ++r)
            for (int c = 0; c < 3; ++c)
                gcols[3 * r + c] = f.K[r] * gT[c] + f.K[3 + r] * gT[3 + c] + f.K[6 + r] * gT[6 + c];
        double g_muc[3], g_axes[9];
        const double sign = flip[i] ? -1.0 : 1.0;
        double g_s0 = 0.0, g_s1 = 0.0;
        for (int r = 0; r < 3; ++r) {
            g_muc[r] = gcols[3 * r + 2];
            g_axes[3 * r] = gcols[3 * r] * s[0];
            g_axes[3 * r + 1] = gcols[3 * r + 1] * s[1];
            g_axes[3 * r + 2] = sign * static_cast<double>(g.normal[3 * i + r]);
            g_s0 += gcols[3 * r] * axes[3 * r];
            g_s1 += gcols[3 * r + 1] * axes[3 * r + 1];
        }
        g_muc[2] += static_cast<double>(g.depth_key[i]);
        // mu_c = Rc mu + tc, axes = Rc R  =>  g_mu = Rc^T g_muc, g_R = Rc^T g_axes.
        double G[9];
        for (int r = 0; r < 3; ++r) {
            g.means[3 * i + r] = static_cast<F>(f.Rc[r] * g_muc[0] + f.Rc[3 + r] * g_muc[1] + f.Rc[6 + r] * g_muc[2]);
            for (int c = 0; c < 3; ++c)
                G[3 * r + c] = f.Rc[r] * g_axes[c] + f.Rc[3 + r] * g_axes[3 + c] + f.Rc[6 + r] * g_axes[6 + c];
        }
        g.scales[2 * i] = static_cast<F>(g_s0);
        g.scales[2 * i + 1] = static_cast<F>(g_s1);
        // R(q) of the unit quaternion, then through q = quats / |quats|.
        const double w = q[0], x = q[1], y = q[2], z = q[3];
        double gq[4];
        gq[0] = 2 * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7]);
        gq[1] = 2 * (y * G[1] + z * G[2] + y * G[3] - 2 * x * G[4] - w * G[5] + z * G[6] + w * G[7] - 2 * x * G[8]);
        gq[2] = 2 * (-2 * y * G[0] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] + z * G[7] - 2 * y * G[8]);
        gq[3] = 2 * (-2 * z * G[0] - w * G[1] + x * G[2] + w * G[3] - 2 * z * G[4] + y * G[5] + x * G[6] + y * G[7]);
        const double dot = q[0] * gq[0] + q[1] * gq[1] + q[2] * gq[2] + q[3] * gq[3];
        for (int k = 0; k < 4; ++k) g.quats[4 * i + k] = static_cast<F>((gq[k] - q[k] * dot) / qnorm);
    }
}

template void project_forward<float>(const ProjectInputs<float>&, const ProjectOutputs<float>&);
template void project_forward<double>(const ProjectInputs<double>&, const ProjectOutputs<double>&);
template void project_backward<float>(const ProjectInputs<float>&, const uint8_t*, const uint8_t*,
                                      const ProjectGrads<float>&);
template void project_backward<double>(const ProjectInputs<double>&, const uint8_t*, const uint8_t*,
                                       const ProjectGrads<double>&);

}  // namespace psimap
