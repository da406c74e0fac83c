// Tile binning: (tile, surfel) pairs, each tile's list sorted front to back by depth_key (ties by
// surfel index). One global stable sort, then every thread fills the tiles of its own band of
// tile rows by scanning surfels in sorted order: lists come out sorted, without atomics.
#include <algorithm>
#include <numeric>

#include <omp.h>

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
#pragma omp parallel
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
#pragma omp parallel
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

void gather_tile(const SurfelInputs& in, const TileBins& bins, int t,
                 std::vector<SurfelParams>& params) {
    const int32_t begin = bins.offsets[t], end = bins.offsets[t + 1];
    params.resize(end - begin);
    for (int32_t k = begin; k < end; ++k) {
        const int64_t i = bins.ids[k];
        SurfelParams& s = params[k - begin];
        for (int j = 0; j < 9; ++j) s.T[j] = in.T[9 * i + j];
        s.x0 = in.box[4 * i];
        s.y0 = in.box[4 * i + 1];
        s.x1 = in.box[4 * i + 2];
        s.y1 = in.box[4 * i + 3];
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
}

void block_lists(const std::vector<SurfelParams>& params, int tile_x0, int tile_y0,
                 std::vector<int32_t>& pos, int32_t* starts) {
    pos.clear();
    const int n = static_cast<int>(params.size());
    for (int b = 0; b < kBlocks * kBlocks; ++b) {
        starts[b] = static_cast<int32_t>(pos.size());
        const int bx0 = tile_x0 + (b % kBlocks) * kBlockPx, by0 = tile_y0 + (b / kBlocks) * kBlockPx;
        const int bx1 = bx0 + kBlockPx, by1 = by0 + kBlockPx;
        for (int j = 0; j < n; ++j) {
            const SurfelParams& s = params[j];
            if (s.x0 < bx1 && s.x1 > bx0 && s.y0 < by1 && s.y1 > by0) pos.push_back(j);
        }
    }
    starts[kBlocks * kBlocks] = static_cast<int32_t>(pos.size());
}

}  // namespace psimap
