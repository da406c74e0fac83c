// nanobind module psimap.render._native: contiguous float32 / int32 numpy buffers in and out (no
// torch headers). Output buffers are allocated (and, in tests, poisoned) by the caller.
#include <algorithm>
#include <stdexcept>
#include <string>

#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>
#include <nanobind/stl/vector.h>
#include <omp.h>

#include "threads.h"

#include "depth_test.h"
#include "project.h"
#include "rasterize.h"

namespace nb = nanobind;
using namespace psimap;

template <typename T>
using Array = nb::ndarray<T, nb::c_contig, nb::device::cpu>;

namespace {

template <typename T>
T* checked(Array<T>& a, size_t expected, const char* name) {
    if (a.size() != expected)
        throw std::invalid_argument(std::string("psimap native: ") + name + " has " +
                                    std::to_string(a.size()) + " elements, expected " +
                                    std::to_string(expected));
    return a.data();
}

template <typename T>
nb::ndarray<nb::numpy, T, nb::ndim<1>> to_numpy(std::vector<T>&& v) {
    auto* heap = new std::vector<T>(std::move(v));
    nb::capsule owner(heap, [](void* p) noexcept { delete static_cast<std::vector<T>*>(p); });
    size_t shape[1] = {heap->size()};
    return nb::ndarray<nb::numpy, T, nb::ndim<1>>(heap->data(), 1, shape, owner);
}

struct Common {
    SurfelInputs in;
    TileBins bins;
    RasterConfig cfg;
};

Common make_common(Array<const float>& T, Array<const float>& center,
                   Array<const float>& depth_key, Array<const float>& normal,
                   Array<const float>& opacity, Array<const float>& color,
                   Array<const float>& feature, int channels, Array<const int32_t>& box,
                   Array<const int32_t>& offsets,
                   Array<const int32_t>& ids, int width, int height, int topk, bool exact_footprint,
                   float near, float far, Array<const float>& background) {
    Common c;
    const size_t n = opacity.size();
    if (width <= 0 || height <= 0) throw std::invalid_argument("psimap native: empty image");
    if (topk < 0 || topk > kMaxTopK)
        throw std::invalid_argument("psimap native: topk must be in [0, " +
                                    std::to_string(kMaxTopK) + "]");
    if (channels < 0) throw std::invalid_argument("psimap native: negative channel count");
    c.in.n = static_cast<int64_t>(n);
    c.in.channels = channels;
    c.in.T = checked(T, 9 * n, "T");
    c.in.center = checked(center, 2 * n, "center");
    c.in.depth_key = checked(depth_key, n, "depth_key");
    c.in.normal = checked(normal, 3 * n, "normal_c");
    c.in.opacity = opacity.data();
    c.in.color = checked(color, 3 * n, "colors");
    c.in.feature = checked(feature, static_cast<size_t>(channels) * n, "features");
    c.in.box = checked(box, 4 * n, "boxes");
    c.bins.tiles_x = tiles_along(width);
    c.bins.tiles_y = tiles_along(height);
    const size_t tiles = static_cast<size_t>(c.bins.tiles_x) * c.bins.tiles_y;
    c.bins.offsets = checked(offsets, tiles + 1, "tile offsets");
    if (static_cast<size_t>(c.bins.offsets[tiles]) != ids.size())
        throw std::invalid_argument("psimap native: tile offsets do not match tile ids");
    c.bins.ids = ids.data();
    for (size_t k = 0; k < ids.size(); ++k)
        if (c.bins.ids[k] < 0 || static_cast<size_t>(c.bins.ids[k]) >= n)
            throw std::invalid_argument("psimap native: tile id out of range");
    c.cfg.width = width;
    c.cfg.height = height;
    c.cfg.topk = topk;
    c.cfg.exact_footprint = exact_footprint;
    c.cfg.near = near;
    c.cfg.far = far;
    const float* b = checked(background, 3, "background");
    for (int k = 0; k < 3; ++k) c.cfg.background[k] = b[k];
    return c;
}

ForwardBuffers make_buffers(const Common& c, Array<float>& rgb, Array<float>& alpha,
                            Array<float>& depth, Array<float>& median, Array<float>& normal,
                            Array<float>& distortion, Array<float>& feature, Array<float>& t_final,
                            Array<int32_t>& n_last, Array<int32_t>& median_pos,
                            Array<double>& dist_sums, Array<int32_t>& topk_pos) {
    const size_t px = static_cast<size_t>(c.cfg.width) * c.cfg.height;
    ForwardBuffers b;
    b.rgb = checked(rgb, 3 * px, "rgb");
    b.alpha = checked(alpha, px, "alpha");
    b.depth = checked(depth, px, "depth");
    b.median = checked(median, px, "median_depth");
    b.normal = checked(normal, 3 * px, "normal");
    b.distortion = checked(distortion, px, "distortion");
    b.feature = checked(feature, px * c.in.channels, "feature image");
    b.t_final = checked(t_final, px, "t_final");
    b.n_last = checked(n_last, px, "n_last");
    b.median_pos = checked(median_pos, px, "median_pos");
    b.dist_sums = checked(dist_sums, 3 * px, "dist_sums");
    b.topk_pos = checked(topk_pos, px * c.cfg.topk, "topk_pos");
    return b;
}

// Stage 1 for one float type F ("f32" / "f64"): the Python side picks by the inputs' dtype.
template <typename F>
void bind_project(nb::module_& m, const char* suffix) {
    auto inputs = [](Array<const F>& means, Array<const F>& quats, Array<const F>& scales,
                     Array<const F>& opacity, Array<const double>& viewmat, Array<const double>& K,
                     int width, int height, double near, double far) {
        ProjectInputs<F> in;
        const size_t n = opacity.size();
        in.n = static_cast<int64_t>(n);
        in.means = checked(means, 3 * n, "means");
        in.quats = checked(quats, 4 * n, "quats");
        in.scales = checked(scales, 2 * n, "scales");
        in.opacity = opacity.data();
        in.viewmat = checked(viewmat, 16, "viewmat");
        in.K = checked(K, 9, "K");
        if (width <= 0 || height <= 0) throw std::invalid_argument("psimap native: empty image");
        in.width = width;
        in.height = height;
        in.near = near;
        in.far = far;
        return in;
    };
    m.def(
        (std::string("project_forward_") + suffix).c_str(),
        [inputs](Array<const F> means, Array<const F> quats, Array<const F> scales,
                 Array<const F> opacity, Array<const double> viewmat, Array<const double> K, int width,
                 int height, double near, double far, Array<F> T, Array<F> center, Array<F> depth_key,
                 Array<F> normal, Array<uint8_t> valid, Array<uint8_t> flip, Array<int32_t> box_precise,
                 Array<int32_t> box_circle) {
            ProjectInputs<F> in = inputs(means, quats, scales, opacity, viewmat, K, width, height, near, far);
            const size_t n = static_cast<size_t>(in.n);
            ProjectOutputs<F> out{checked(T, 9 * n, "T"), checked(center, 2 * n, "center"),
                                  checked(depth_key, n, "depth_key"), checked(normal, 3 * n, "normal_c"),
                                  checked(valid, n, "valid"), checked(flip, n, "flip"),
                                  checked(box_precise, 4 * n, "box_precise"),
                                  checked(box_circle, 4 * n, "box_circle")};
            nb::gil_scoped_release release;
            project_forward(in, out);
        },
        "Stage 1 (SPEC.md): writes T, center, depth_key, normal_c, valid, flip and both tile boxes.");
    m.def(
        (std::string("project_backward_") + suffix).c_str(),
        [inputs](Array<const F> means, Array<const F> quats, Array<const F> scales,
                 Array<const F> opacity, Array<const double> viewmat, Array<const double> K, int width,
                 int height, double near, double far, Array<const uint8_t> valid,
                 Array<const uint8_t> flip, Array<const F> gT, Array<const F> g_center,
                 Array<const F> g_depth_key, Array<const F> g_normal, Array<F> g_means,
                 Array<F> g_quats, Array<F> g_scales) {
            ProjectInputs<F> in = inputs(means, quats, scales, opacity, viewmat, K, width, height, near, far);
            const size_t n = static_cast<size_t>(in.n);
            ProjectGrads<F> g{checked(gT, 9 * n, "grad T"), checked(g_center, 2 * n, "grad center"),
                              checked(g_depth_key, n, "grad depth_key"),
                              checked(g_normal, 3 * n, "grad normal_c"), checked(g_means, 3 * n, "grad means"),
                              checked(g_quats, 4 * n, "grad quats"), checked(g_scales, 2 * n, "grad scales")};
            const uint8_t* v = checked(valid, n, "valid");
            const uint8_t* fl = checked(flip, n, "flip");
            nb::gil_scoped_release release;
            project_backward(in, v, fl, g);
        },
        "Backward of stage 1: writes dL/d(means, quats, scales).");
}

// The inputs both field_distribution bindings read: dot [V, Q], terms [V, K], coef_t [K, Q], p_thing [V]
// or empty, temperature > 0.
void check_field_inputs(Array<const float>& dot, Array<const double>& terms, Array<const double>& coef_t,
                        Array<const float>& p_thing, int64_t V, int64_t Q, int64_t K, float temperature) {
    checked(dot, static_cast<size_t>(V) * static_cast<size_t>(Q), "dot");
    checked(terms, static_cast<size_t>(V) * static_cast<size_t>(K), "terms");
    checked(coef_t, static_cast<size_t>(K) * static_cast<size_t>(Q), "coef_t");
    if (p_thing.size() != 0) checked(p_thing, static_cast<size_t>(V), "p_thing");
    if (!(temperature > 0.0f)) throw std::invalid_argument("psimap native: temperature must be > 0");
}

}  // namespace

NB_MODULE(_native, m) {
    m.doc() = "psimap native CPU surfel rasterizer (C++17 / OpenMP)";

    m.def("set_num_threads", [](int n) { set_kernel_threads(n); }, nb::arg("n"));
    m.def("get_num_threads", []() { return kernel_threads(); });
    m.def("pixel_kernels", []() { return std::string(pixel_kernels().isa); },
          "Instruction set of the SIMD pixel kernels in use (avx512, avx2 or baseline).");
    m.def("available_pixel_kernels", []() { return available_kernels(); },
          "Instruction sets of the pixel kernels this CPU can run, widest first.");
    m.def(
        "use_pixel_kernels",
        [](const std::string& isa) {
            if (!select_kernels(isa))
                throw std::invalid_argument("psimap native: no pixel kernels for '" + isa + "' on this CPU");
        },
        nb::arg("isa"), "Run the pixel kernels built for `isa` ('' = the widest this CPU runs).");
    m.def(
        "exp_nonpositive",
        [](Array<const float>& x, Array<float>& out) {
            checked(out, x.size(), "out");
            pixel_kernels().exp(x.data(), out.data(), static_cast<int64_t>(x.size()));
        },
        nb::arg("x"), nb::arg("out"), "The pixel kernels' exp (for x in [-6, 0]) into `out` (tests).");
    m.def(
        "field_distribution_forward",
        [](Array<const float> dot, Array<const double> terms, Array<const double> coef_t, Array<const float> p_thing,
           int64_t V, int64_t Q, int64_t K, float temperature, Array<float> out, Array<float> soft) {
            const size_t n = static_cast<size_t>(V) * static_cast<size_t>(Q);
            check_field_inputs(dot, terms, coef_t, p_thing, V, Q, K, temperature);
            checked(out, n, "out");
            checked(soft, n, "soft");
            // all rows on the calling thread: the panoptic steps run on one core while the second
            // builds the frozen blends or steps the surfel optimizer (psimap.panoptic.fit), and a team
            // of two waiting on that core took ~10 ms a room step where one thread took ~5
            nb::gil_scoped_release release;
            pixel_kernels().field_forward(dot.data(), terms.data(), coef_t.data(), K,
                                          p_thing.size() ? p_thing.data() : nullptr, 0, V, Q, temperature, out.data(),
                                          soft.data());
        },
        nb::arg("dot"), nb::arg("terms"), nb::arg("coef_t"), nb::arg("p_thing"), nb::arg("V"), nb::arg("Q"),
        nb::arg("K"), nb::arg("temperature"), nb::arg("out"), nb::arg("soft"),
        "Panoptic field distribution softmax_q(sigmoid(dot) exp(-min(m2, 160) / 2) / T) * p_thing into "
        "out [V, Q] (softmax into soft), m2 = terms [V, K] x coef_t [K, Q] in float64; p_thing empty = 1.");
    m.def(
        "field_affinity",
        [](Array<const float> dot, Array<const double> terms, Array<const double> coef_t, int64_t V, int64_t Q,
           int64_t K, Array<float> out) {
            checked(dot, static_cast<size_t>(V) * static_cast<size_t>(Q), "dot");
            checked(terms, static_cast<size_t>(V) * static_cast<size_t>(K), "terms");
            checked(coef_t, static_cast<size_t>(K) * static_cast<size_t>(Q), "coef_t");
            checked(out, static_cast<size_t>(V) * static_cast<size_t>(Q), "out");
            // on the calling thread, as the field's distribution (see field_distribution_forward)
            nb::gil_scoped_release release;
            pixel_kernels().field_affinity(dot.data(), terms.data(), coef_t.data(), K, 0, V, Q, out.data());
        },
        nb::arg("dot"), nb::arg("terms"), nb::arg("coef_t"), nb::arg("V"), nb::arg("Q"), nb::arg("K"), nb::arg("out"),
        "Panoptic field affinity sigmoid(dot) exp(-min(m2, 160) / 2) into out [V, Q], m2 = terms [V, K] x "
        "coef_t [K, Q] in float64.");
    m.def(
        "field_distribution_backward",
        [](Array<const float> dot, Array<const double> terms, Array<const double> coef_t, Array<const float> p_thing,
           Array<const float> soft, Array<const float> v_out, int64_t V, int64_t Q, int64_t K, float temperature,
           Array<float> v_dot, Array<double> v_coef_t, Array<float> v_p_thing) {
            const size_t n = static_cast<size_t>(V) * static_cast<size_t>(Q);
            check_field_inputs(dot, terms, coef_t, p_thing, V, Q, K, temperature);
            checked(soft, n, "soft");
            checked(v_out, n, "v_out");
            checked(v_dot, n, "v_dot");
            checked(v_coef_t, static_cast<size_t>(K) * static_cast<size_t>(Q), "v_coef_t");
            const bool pt = p_thing.size() != 0;
            if (pt) checked(v_p_thing, static_cast<size_t>(V), "v_p_thing");
            std::fill(v_coef_t.data(), v_coef_t.data() + v_coef_t.size(), 0.0);
            nb::gil_scoped_release release;
            pixel_kernels().field_backward(dot.data(), terms.data(), coef_t.data(), K, pt ? p_thing.data() : nullptr,
                                           soft.data(), v_out.data(), 0, V, Q, temperature, v_dot.data(),
                                           v_coef_t.data(), pt ? v_p_thing.data() : nullptr);
        },
        nb::arg("dot"), nb::arg("terms"), nb::arg("coef_t"), nb::arg("p_thing"), nb::arg("soft"), nb::arg("v_out"),
        nb::arg("V"), nb::arg("Q"), nb::arg("K"), nb::arg("temperature"), nb::arg("v_dot"), nb::arg("v_coef_t"),
        nb::arg("v_p_thing"),
        "Backward of field_distribution_forward: v_dot [V, Q], v_coef_t [K, Q] float64, v_p_thing [V].");
    m.def(
        "match_sums",
        [](Array<const float> x, Array<const uint8_t> codes, int64_t P, int64_t Q, int64_t M, float lo, float hi,
           Array<double> sums) {
            checked(x, static_cast<size_t>(P) * static_cast<size_t>(Q), "x");
            checked(codes, static_cast<size_t>(P) * static_cast<size_t>(M), "codes");
            checked(sums, 5 * static_cast<size_t>(M) * static_cast<size_t>(Q), "sums");
            if (!(lo > 0.0f && hi < 1.0f && lo <= hi))
                throw std::invalid_argument("psimap native: match_sums needs 0 < lo <= hi < 1");
            std::vector<float> scratch(static_cast<size_t>(match_scratch_floats(Q, M)));
            std::fill(sums.data(), sums.data() + sums.size(), 0.0);
            // on the calling thread, as the field's distribution (see field_distribution_forward)
            nb::gil_scoped_release release;
            pixel_kernels().match_sums(x.data(), codes.data(), P, 0, P, Q, M, lo, hi, sums.data(), scratch.data());
        },
        nb::arg("x"), nb::arg("codes"), nb::arg("P"), nb::arg("Q"), nb::arg("M"), nb::arg("lo"), nb::arg("hi"),
        nb::arg("sums"),
        "The matching's sums [5, M, Q] float64 (x, log x, log(1 - x) on each mask; x, log(1 - x) on its "
        "window) over x [P, Q] clamped to [lo, hi]; codes [M, P] uint8: 0 outside mask m's window, 1 in it, "
        "2 on the mask.");
    m.def(
        "blend_rows",
        [](Array<const int64_t> indptr, Array<const int32_t> indices, Array<const float> data, Array<const float> f,
           int64_t R, int64_t V, int64_t C, Array<float> out) {
            checked(indptr, static_cast<size_t>(R) + 1, "indptr");
            const int64_t* ip = indptr.data();
            if (ip[0] != 0) throw std::invalid_argument("psimap native: blend_rows: indptr[0] != 0");
            for (int64_t r = 0; r < R; ++r)
                if (ip[r + 1] < ip[r]) throw std::invalid_argument("psimap native: blend_rows: indptr decreases");
            const int64_t nnz = ip[R];
            checked(indices, static_cast<size_t>(nnz), "indices");
            checked(data, static_cast<size_t>(nnz), "data");
            for (int64_t j = 0; j < nnz; ++j)   // a bad column would read outside f
                if (indices.data()[j] < 0 || indices.data()[j] >= V)
                    throw std::invalid_argument("psimap native: blend_rows: a column index out of range");
            checked(f, static_cast<size_t>(V) * static_cast<size_t>(C), "f");
            checked(out, static_cast<size_t>(R) * static_cast<size_t>(C), "out");
            // on the calling thread, as the field's distribution (see field_distribution_forward)
            nb::gil_scoped_release release;
            pixel_kernels().blend_forward(ip, indices.data(), data.data(), f.data(), 0, R, C, out.data());
        },
        nb::arg("indptr"), nb::arg("indices"), nb::arg("data"), nb::arg("f"), nb::arg("R"), nb::arg("V"), nb::arg("C"),
        nb::arg("out"),
        "A [R, V] (CSR: indptr int64, indices int32, data float32) times f [V, C] float32 into out [R, C], each "
        "sum in the order of A's entries (scipy's).");
    m.def(
        "depth_test",
        [](Array<const double> points, Array<const double> c2w, Array<const double> K, int64_t w, int64_t h,
           Array<const double> depth, double tol, int mode, Array<uint8_t> state) {
            const size_t n = state.size();
            checked(points, 3 * n, "points");
            checked(c2w, 16, "c2w");
            checked(K, 9, "K");
            if (w <= 0 || h <= 0) throw std::invalid_argument("psimap native: depth_test: empty image");
            checked(depth, static_cast<size_t>(w) * static_cast<size_t>(h), "depth");
            if (mode != 0 && mode != 1) throw std::invalid_argument("psimap native: depth_test: mode 0 or 1");
            nb::gil_scoped_release release;   // on the calling thread: export runs one thread by policy
            return depth_test(points.data(), static_cast<int64_t>(n), c2w.data(), K.data(), w, h, depth.data(),
                              tol, static_cast<DepthTestMode>(mode), state.data());
        },
        nb::arg("points"), nb::arg("c2w"), nb::arg("K"), nb::arg("w"), nb::arg("h"), nb::arg("depth"),
        nb::arg("tol"), nb::arg("mode"), nb::arg("state"),
        "Points [Q, 3] float64 a camera (c2w [4, 4], K [3, 3], depth [h, w] float64) sees in front of its depth "
        "by more than tol (mode 0) or within tol of it (mode 1): sets state [Q] uint8 to 1 where it was 0 and "
        "the test holds; returns the number set.");
    m.attr("MAX_TOPK") = kMaxTopK;
    m.attr("TILE") = kTile;
    bind_project<float>(m, "f32");
    bind_project<double>(m, "f64");

    m.def(
        "bin_tiles",
        [](Array<const int32_t> boxes, Array<const uint8_t> valid, Array<const float> depth_key,
           int width, int height) {
            const size_t n = valid.size();
            checked(boxes, 4 * n, "boxes");
            checked(depth_key, n, "depth_key");
            std::vector<int32_t> offsets, ids;
            {
                nb::gil_scoped_release release;
                bin_tiles(boxes.data(), valid.data(), depth_key.data(), static_cast<int64_t>(n),
                          width, height, offsets, ids);
            }
            return std::make_tuple(to_numpy(std::move(offsets)), to_numpy(std::move(ids)));
        },
        nb::arg("boxes"), nb::arg("valid"), nb::arg("depth_key"), nb::arg("width"),
        nb::arg("height"),
        "(tile offsets [tiles+1] int32, surfel ids [pairs] int32), each tile front to back.");

    m.def(
        "rasterize_forward",
        [](Array<const float> T, Array<const float> center, Array<const float> depth_key,
           Array<const float> normal, Array<const float> opacity, Array<const float> color,
           Array<const float> feature, int channels, Array<const int32_t> box,
           Array<const int32_t> offsets,
           Array<const int32_t> ids, int width, int height, int topk, bool exact_footprint, float near, float far,
           Array<const float> background, Array<float> out_rgb, Array<float> out_alpha,
           Array<float> out_depth, Array<float> out_median, Array<float> out_normal,
           Array<float> out_distortion, Array<float> out_feature, Array<float> t_final,
           Array<int32_t> n_last, Array<int32_t> median_pos, Array<double> dist_sums,
           Array<int32_t> topk_pos, Array<float> topk_w) {
            Common c = make_common(T, center, depth_key, normal, opacity, color, feature, channels,
                                   box, offsets, ids, width, height, topk, exact_footprint, near, far,
                                   background);
            ForwardBuffers b = make_buffers(c, out_rgb, out_alpha, out_depth, out_median,
                                            out_normal, out_distortion, out_feature, t_final,
                                            n_last, median_pos, dist_sums, topk_pos);
            // topk_w: empty = not wanted
            if (topk_w.size() > 0)
                b.topk_w = checked(topk_w, static_cast<size_t>(width) * height * topk, "topk_w");
            nb::gil_scoped_release release;
            return rasterize_forward(c.in, c.bins, c.cfg, b);
        },
        "Forward pass; writes every output pixel; returns the number of (pixel, surfel) evaluations.");

    m.def(
        "rasterize_backward",
        [](Array<const float> T, Array<const float> center, Array<const float> depth_key,
           Array<const float> normal, Array<const float> opacity, Array<const float> color,
           Array<const float> feature, int channels, Array<const int32_t> box,
           Array<const int32_t> offsets,
           Array<const int32_t> ids, int width, int height, int topk, bool exact_footprint, float near, float far,
           Array<const float> background, Array<float> depth, Array<float> t_final,
           Array<int32_t> n_last, Array<int32_t> median_pos, Array<double> dist_sums,
           Array<int32_t> topk_pos, Array<const float> g_rgb, Array<const float> g_alpha,
           Array<const float> g_depth, Array<const float> g_median, Array<const float> g_normal,
           Array<const float> g_distortion, Array<const float> g_feature, Array<float> gT,
           Array<float> g_center, Array<float> g_depth_key, Array<float> g_normal_c,
           Array<float> g_opacity, Array<float> g_color, Array<float> g_feat) {
            Common c = make_common(T, center, depth_key, normal, opacity, color, feature, channels,
                                   box, offsets, ids, width, height, topk, exact_footprint, near, far,
                                   background);
            const size_t px = static_cast<size_t>(width) * height;
            const size_t n = static_cast<size_t>(c.in.n);
            ForwardBuffers s{};
            s.depth = checked(depth, px, "depth");
            s.t_final = checked(t_final, px, "t_final");
            s.n_last = checked(n_last, px, "n_last");
            s.median_pos = checked(median_pos, px, "median_pos");
            s.dist_sums = checked(dist_sums, 3 * px, "dist_sums");
            s.topk_pos = checked(topk_pos, px * topk, "topk_pos");
            BackwardGrads g;
            g.rgb = checked(g_rgb, 3 * px, "grad rgb");
            g.alpha = checked(g_alpha, px, "grad alpha");
            g.depth = checked(g_depth, px, "grad depth");
            g.median = checked(g_median, px, "grad median_depth");
            g.normal = checked(g_normal, 3 * px, "grad normal");
            g.distortion = checked(g_distortion, px, "grad distortion");
            g.feature = checked(g_feature, px * channels, "grad features");
            g.T = checked(gT, 9 * n, "grad T");
            g.center = checked(g_center, 2 * n, "grad center");
            g.depth_key = checked(g_depth_key, n, "grad depth_key");
            g.normal_c = checked(g_normal_c, 3 * n, "grad normal_c");
            g.opacity = checked(g_opacity, n, "grad opacities");
            g.color = checked(g_color, 3 * n, "grad colors");
            g.feat = checked(g_feat, n * channels, "grad feature");
            nb::gil_scoped_release release;
            rasterize_backward(c.in, c.bins, c.cfg, s, g);
        },
        "Backward pass: writes dL/d(T, center, depth_key, normal_c, opacity, color, feature).");
}
