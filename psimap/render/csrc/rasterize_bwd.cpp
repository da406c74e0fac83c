// Backward rasterization: per pixel, back to front from the last blended surfel, reconstructing
// the transmittance T_i = T_{i+1} / (1 - alpha_i) from the saved final one (the SIMD pixel kernels,
// raster_lanes.inl). Gradients are summed
// per (tile, surfel) bin entry, each tile by whichever thread takes it (no atomics), then reduced
// per surfel in tile order: the sum is the same bits for any thread count and schedule, so
// training stays reproducible on every core.
#include <algorithm>
#include <cstring>
#include <memory>

#include <omp.h>

#include "threads.h"

#include "rasterize.h"

namespace psimap {

namespace {
constexpr int kGT = kGradT, kGCenter = kGradCenter, kGDepthKey = kGradDepthKey, kGNormal = kGradNormal,
              kGOpacity = kGradOpacity, kGColor = kGradColor, kGSlots = kGradSlots;
}  // namespace

void rasterize_backward(const SurfelInputs& in, const TileBins& bins, const RasterConfig& cfg,
                        const ForwardBuffers& saved, const BackwardGrads& g) {
    const int C = in.channels;
    const int64_t N = in.n;
    const int tiles = bins.tiles_x * bins.tiles_y;
    const int64_t pairs = bins.offsets[tiles];
    // One gradient row per bin entry (tile, surfel): written by the tile's thread only.
    // (uninitialised: every tile writes all its rows)
    std::unique_ptr<float[]> entry_geo(new float[static_cast<size_t>(pairs) * kGSlots]);
    std::unique_ptr<float[]> entry_feat(new float[static_cast<size_t>(pairs) * C + 1]);

    const PixelKernels& kernels = pixel_kernels();
#pragma omp parallel num_threads(kernel_threads())
    {
        std::vector<SurfelParams> params;
        std::vector<Footprint> footprints;
        std::vector<Footprint>* fp = cfg.exact_footprint ? &footprints : nullptr;
        std::vector<int32_t> block_pos;
        int32_t block_start[kBlocks * kBlocks + 1];
        std::vector<float> scratch(kernel_scratch_floats(C));
        std::vector<float> lane_acc;   // the kernels' per-lane partial sums, vector-aligned below
        std::vector<uint8_t> touched;
#pragma omp for schedule(dynamic, 1)
        for (int t = 0; t < tiles; ++t) {
            const int n = bins.offsets[t + 1] - bins.offsets[t];
            if (n == 0) continue;
            gather_tile(in, bins, t, params, fp);
            float* tile_geo = entry_geo.get() + static_cast<size_t>(bins.offsets[t]) * kGSlots;
            float* tile_feat = entry_feat.get() + static_cast<size_t>(bins.offsets[t]) * C;
            std::fill(tile_feat, tile_feat + static_cast<size_t>(n) * C, 0.0f);
            const int tx = t % bins.tiles_x, ty = t / bins.tiles_x;
            block_lists(params, tx * kTile, ty * kTile, block_pos, block_start, fp);
            const size_t acc_floats = static_cast<size_t>(n) * kGradSlots * kMaxLanes;
            if (lane_acc.size() < acc_floats + kMaxLanes) lane_acc.resize(acc_floats + kMaxLanes);
            if (touched.size() < static_cast<size_t>(n)) touched.resize(n);
            const uintptr_t raw = reinterpret_cast<uintptr_t>(lane_acc.data());
            const uintptr_t align = sizeof(float) * kMaxLanes;
            float* acc = reinterpret_cast<float*>((raw + align - 1) / align * align);
            TileWork work{tx * kTile, ty * kTile, params.data(), bins.ids + bins.offsets[t], block_pos.data(),
                          block_start, scratch.data()};
            work.n = n;
            work.grad_rows = tile_geo;
            work.grad_feat = tile_feat;
            work.lane_acc = acc;
            work.touched = touched.data();
            kernels.backward(in, cfg, saved, g, work);
        }
    }

    // Reduce per surfel in tile order. Each thread owns a contiguous range of surfel ids and walks
    // every entry (ids only: 4 bytes each), adding the rows of its own surfels.
    std::unique_ptr<float[]> acc_geo(new float[static_cast<size_t>(N) * kGSlots + 1]);
#pragma omp parallel num_threads(kernel_threads())
    {
        const int th = omp_get_thread_num(), nth = omp_get_num_threads();
        const int64_t lo = N * th / nth, hi = N * (th + 1) / nth;
        std::fill(acc_geo.get() + lo * kGSlots, acc_geo.get() + hi * kGSlots, 0.0f);
        if (C > 0) std::fill(g.feat + lo * C, g.feat + hi * C, 0.0f);
        for (int64_t e = 0; e < pairs; ++e) {
            const int64_t i = bins.ids[e];
            if (i < lo || i >= hi) continue;
            float* dst = acc_geo.get() + i * kGSlots;
            const float* src = entry_geo.get() + e * kGSlots;
            for (int k = 0; k < kGSlots; ++k) dst[k] += src[k];
            float* dstf = g.feat + i * C;
            const float* srcf = entry_feat.get() + e * C;
            for (int c = 0; c < C; ++c) dstf[c] += srcf[c];
        }
        for (int64_t i = lo; i < hi; ++i) {
            const float* acc = acc_geo.get() + i * kGSlots;
            for (int k = 0; k < 9; ++k) g.T[9 * i + k] = acc[kGT + k];
            g.center[2 * i] = acc[kGCenter];
            g.center[2 * i + 1] = acc[kGCenter + 1];
            g.depth_key[i] = acc[kGDepthKey];
            for (int k = 0; k < 3; ++k) {
                g.normal_c[3 * i + k] = acc[kGNormal + k];
                g.color[3 * i + k] = acc[kGColor + k];
            }
            g.opacity[i] = acc[kGOpacity];
        }
    }
}

}  // namespace psimap
