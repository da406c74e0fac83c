// Tile binning: (tile, surfel) pairs, each tile's list sorted front to back by depth_key (ties by
// surfel index). One global stable sort, then every thread fills the tiles of its own band of
// tile rows by scanning surfels in sorted order: lists come out sorted, without atomics.
#include <algorithm>
#include <cmath>
#include <numeric>

#include <omp.h>

#include "threads.h"

#include "rasterize.h"

namespace psimap {

namespace {
struct TileRange {
    int tx0, ty0, tx1, ty1;  // inclusive tile range; empty when tx1 < tx0
};

TileRange tile_range(const int32_t* box, int width, int height) {
    // Box is (x0, y0, x1, y1), half-open in pixels; clip defensively.
    const int x0 = std::max(0, box[0]), y0 = std::max(0, box[1]);
    const int x1 = std::min(width, box[2]), y1 = std::min(height, box[3]);
    if (x1 <= x0 || y1 <= y0) return {0, 0, -1, -1};
    return {x0 / kTile, y0 / kTile, (x1 - 1) / kTile, (y1 - 1) / kTile};
}
}  // namespace

void bin_tiles(const int32_t* boxes, const uint8_t* valid, const float* depth_key, int64_t n,
               int width, int height, std::vector<int32_t>& offsets, std::vector<int32_t>& ids) {
    const int tiles_x = tiles_along(width), tiles_y = tiles_along(height);
    const int tiles = tiles_x * tiles_y;
    std::vector<int32_t> order;
    order.reserve(n);
    for (int64_t i = 0; i < n; ++i)
        if (valid[i]) order.push_back(static_cast<int32_t>(i));
    std::stable_sort(order.begin(), order.end(),
                     [depth_key](int32_t a, int32_t b) { return depth_key[a] < depth_key[b]; });
    std::vector<TileRange> ranges(order.size());
    for (size_t k = 0; k < order.size(); ++k) ranges[k] = tile_range(boxes + 4 * order[k], width, height);

    std::vector<int32_t> counts(tiles + 1, 0);
    // Pass 1: count per tile; pass 2: fill. Each thread owns a contiguous band of tile rows.
    auto band = [tiles_y](int thread, int threads, int& r0, int& r1) {
        r0 = static_cast<int>(static_cast<int64_t>(tiles_y) * thread / threads);
        r1 = static_cast<int>(static_cast<int64_t>(tiles_y) * (thread + 1) / threads);
    };
#pragma omp parallel num_threads(kernel_threads())
    {
        int r0, r1;
        band(omp_get_thread_num(), omp_get_num_threads(), r0, r1);
        for (const TileRange& r : ranges) {
            const int y0 = std::max(r.ty0, r0), y1 = std::min(r.ty1, r1 - 1);
            for (int ty = y0; ty <= y1; ++ty)
                for (int tx = r.tx0; tx <= r.tx1; ++tx) ++counts[ty * tiles_x + tx + 1];
        }
    }
    offsets.assign(tiles + 1, 0);
    std::partial_sum(counts.begin(), counts.end(), offsets.begin());
    ids.resize(offsets[tiles]);
#pragma omp parallel num_threads(kernel_threads())
    {
        int r0, r1;
        band(omp_get_thread_num(), omp_get_num_threads(), r0, r1);
        std::vector<int32_t> cursor(offsets.begin() + r0 * tiles_x,
                                    offsets.begin() + r1 * tiles_x);
        for (size_t k = 0; k < ranges.size(); ++k) {
            const TileRange& r = ranges[k];
            const int y0 = std::max(r.ty0, r0), y1 = std::min(r.ty1, r1 - 1);
            for (int ty = y0; ty <= y1; ++ty)
                for (int tx = r.tx0; tx <= r.tx1; ++tx)
                    ids[cursor[(ty - r0) * tiles_x + tx]++] = order[k];
        }
    }
}

namespace {

Footprint footprint_of(const SurfelParams& s) {
    Footprint f{};
    f.any = s.half_rho_cut >= 0.0f;
    // Low-pass: valid when rho2 <= ln 255, tried only when rho2 <= half_rho_cut.
    f.cx = s.cx;
    f.cy = s.cy;
    f.r2 = std::min(static_cast<double>(kLowPass2), static_cast<double>(s.half_rho_cut));
    // 3D branch: tried only when u^2 + v^2 <= min(chi^2, 2 half_rho_cut).
    const double r3 = std::min(static_cast<double>(kChi2), 2.0 * s.half_rho_cut);
    f.ellipse = false;
    if (!f.any || r3 <= 0.0) return f;
    double T[9];
    for (int k = 0; k < 9; ++k) T[k] = s.T[k];
    double Cs[9];  // dual conic T diag(1, 1, -1/r3) T^T
    for (int i = 0; i < 3; ++i)
        for (int k = 0; k < 3; ++k)
            Cs[3 * i + k] = T[3 * i] * T[3 * k] + T[3 * i + 1] * T[3 * k + 1] - T[3 * i + 2] * T[3 * k + 2] / r3;
    const double c22 = Cs[8];
    if (!(c22 < 0.0)) return f;  // the disk reaches the camera plane: unbounded in the image
    f.ex = Cs[2] / c22;
    f.ey = Cs[5] / c22;
    const double m00 = (Cs[2] * Cs[6] - Cs[0] * c22) / (c22 * c22);
    const double m01 = (Cs[2] * Cs[7] - Cs[1] * c22) / (c22 * c22);
    const double m11 = (Cs[5] * Cs[7] - Cs[4] * c22) / (c22 * c22);
    f.a = m11;
    f.b = -m01;
    f.c = m00;
    f.det = m00 * m11 - m01 * m01;
    // A nearly flat ellipse (an edge-on surfel) is a segment the test cannot resolve: box only.
    f.ellipse = std::isfinite(f.det) && std::isfinite(f.ex) && std::isfinite(f.ey) &&
                f.det > 1e-6 * m00 * m11 && m00 > 0.0 && m11 > 0.0;
    return f;
}

// Minimum over dy in [lo, hi] of a dx^2 + 2 b dx dy + c dy^2 (c > 0: convex in dy).
double edge_min(double a, double b, double c, double dx, double lo, double hi) {
    const double dy = std::min(std::max(-b * dx / c, lo), hi);
    return a * dx * dx + 2.0 * b * dx * dy + c * dy * dy;
}

// Whether the pixel centres x0 <= x <= x1, y0 <= y <= y1 may hold a pixel of the footprint. The
// rectangle is grown by a twentieth of a pixel and the ellipse by 0.1 % against rounding: a miss
// is then a pixel the per-pixel test (SPEC.md) would reject too.
bool meets(const Footprint& f, double x0, double y0, double x1, double y1) {
    if (!f.any) return false;
    constexpr double kGrow = 0.05, kRel = 1e-3;
    x0 -= kGrow;
    y0 -= kGrow;
    x1 += kGrow;
    y1 += kGrow;
    if (f.r2 >= 0.0) {
        const double dx = std::max({x0 - f.cx, 0.0, f.cx - x1}), dy = std::max({y0 - f.cy, 0.0, f.cy - y1});
        if (dx * dx + dy * dy <= f.r2 * (1.0 + kRel)) return true;
    }
    if (!f.ellipse) return true;  // the box alone decides
    if (f.ex >= x0 && f.ex <= x1 && f.ey >= y0 && f.ey <= y1) return true;
    // Minimum of q(d) = d^T adj(M) d over the rectangle's edges (d = x - e); inside when q <= det.
    const double lim = f.det * (1.0 + kRel);
    const double lx = x0 - f.ex, hx = x1 - f.ex, ly = y0 - f.ey, hy = y1 - f.ey;
    if (edge_min(f.a, f.b, f.c, lx, ly, hy) <= lim || edge_min(f.a, f.b, f.c, hx, ly, hy) <= lim) return true;
    // Horizontal edges: swap the roles of x and y (q = c dy^2 + 2 b dx dy + a dx^2).
    return edge_min(f.c, f.b, f.a, ly, lx, hx) <= lim || edge_min(f.c, f.b, f.a, hy, lx, hx) <= lim;
}

}  // namespace

void gather_tile(const SurfelInputs& in, const TileBins& bins, int t,
                 std::vector<SurfelParams>& params, std::vector<Footprint>* footprints) {
    const int32_t begin = bins.offsets[t], end = bins.offsets[t + 1];
    params.resize(end - begin);
    for (int32_t k = begin; k < end; ++k) {
        const int64_t i = bins.ids[k];
        SurfelParams& s = params[k - begin];
        for (int j = 0; j < 9; ++j) s.T[j] = in.T[9 * i + j];
        s.x0 = static_cast<float>(in.box[4 * i]);
        s.y0 = static_cast<float>(in.box[4 * i + 1]);
        s.x1 = static_cast<float>(in.box[4 * i + 2]);
        s.y1 = static_cast<float>(in.box[4 * i + 3]);
        s.cx = in.center[2 * i];
        s.cy = in.center[2 * i + 1];
        s.depth_key = in.depth_key[i];
        s.opacity = in.opacity[i];
        s.half_rho_cut = half_rho_cut(s.opacity);
        for (int j = 0; j < 3; ++j) {
            s.color[j] = in.color[3 * i + j];
            s.normal[j] = in.normal[3 * i + j];
        }
    }
    if (footprints) {
        footprints->resize(params.size());
        for (size_t j = 0; j < params.size(); ++j) (*footprints)[j] = footprint_of(params[j]);
    }
}

void block_lists(const std::vector<SurfelParams>& params, int tile_x0, int tile_y0,
                 std::vector<int32_t>& pos, int32_t* starts, const std::vector<Footprint>* footprints) {
    constexpr int kBlockCount = kBlocks * kBlocks;
    const int n = static_cast<int>(params.size());
    // Each surfel visits only the blocks its box overlaps (a range of block rows and columns),
    // appending itself to their lists in surfel order; the lists are then packed block by block.
    // Same lists as testing every (block, surfel) pair, without a hard-to-predict branch each.
    pos.resize(static_cast<size_t>(kBlockCount + 1) * n);
    int32_t* per_block = pos.data() + n;  // block b's list at per_block[b * n ...]
    int32_t count[kBlockCount] = {0};
    for (int j = 0; j < n; ++j) {
        const SurfelParams& s = params[j];
        // The box is integer-valued (half-open): block column bx overlaps it when
        // x0 < tile_x0 + 4 (bx + 1) and x1 > tile_x0 + 4 bx.
        const int x0 = static_cast<int>(s.x0) - tile_x0, x1 = static_cast<int>(s.x1) - tile_x0;
        const int y0 = static_cast<int>(s.y0) - tile_y0, y1 = static_cast<int>(s.y1) - tile_y0;
        const int bx0 = x0 < 0 ? 0 : x0 >> 2, bx1 = std::min(kBlocks - 1, ((x1 + kBlockPx - 1) >> 2) - 1);
        const int by0 = y0 < 0 ? 0 : y0 >> 2, by1 = std::min(kBlocks - 1, ((y1 + kBlockPx - 1) >> 2) - 1);
        for (int by = by0; by <= by1; ++by)
            for (int bx = bx0; bx <= bx1; ++bx) {
                // Pixel centres of the block: its first pixel .. + kBlockPx - 1 (x and y).
                const int px0 = tile_x0 + bx * kBlockPx, py0 = tile_y0 + by * kBlockPx;
                if (footprints && !meets((*footprints)[j], px0, py0, px0 + kBlockPx - 1, py0 + kBlockPx - 1))
                    continue;
                const int b = by * kBlocks + bx;
                per_block[static_cast<int64_t>(b) * n + count[b]++] = j;
            }
    }
    int32_t total = 0;
    for (int b = 0; b < kBlockCount; ++b) {
        starts[b] = total;
        // Packed in place: block b's list moves down to pos[total ...], never past its source.
        std::copy(per_block + static_cast<int64_t>(b) * n, per_block + static_cast<int64_t>(b) * n + count[b],
                  pos.data() + total);
        total += count[b];
    }
    starts[kBlockCount] = total;
}

}  // namespace psimap
