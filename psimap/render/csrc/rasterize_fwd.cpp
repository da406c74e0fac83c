// Forward rasterization: OpenMP over 16x16 tiles (dynamic schedule); per tile the surfels are
// gathered and listed per 4x4 pixel block here, and the per-pixel front-to-back blending
// (SPEC.md stage 3, Top-K feature selection) runs in the SIMD pixel kernels (raster_lanes.inl).
#include <algorithm>
#include <memory>

#include <omp.h>

#include "threads.h"

#include "rasterize.h"

namespace psimap {

int64_t rasterize_forward(const SurfelInputs& in, const TileBins& bins, const RasterConfig& cfg,
                          const ForwardBuffers& out) {
    const int tiles = bins.tiles_x * bins.tiles_y;
    const PixelKernels& kernels = pixel_kernels();
    int64_t evaluated = 0;
#pragma omp parallel reduction(+ : evaluated) num_threads(kernel_threads())
    {
        std::vector<SurfelParams> params;
        std::vector<Footprint> footprints;
        std::vector<Footprint>* fp = cfg.exact_footprint ? &footprints : nullptr;
        std::vector<int32_t> block_pos;
        int32_t block_start[kBlocks * kBlocks + 1];
        std::vector<float> scratch(kernel_scratch_floats(in.channels));
#pragma omp for schedule(dynamic, 1)
        for (int t = 0; t < tiles; ++t) {
            gather_tile(in, bins, t, params, fp);
            const int tx = t % bins.tiles_x, ty = t / bins.tiles_x;
            block_lists(params, tx * kTile, ty * kTile, block_pos, block_start, fp);
            const TileWork work{tx * kTile, ty * kTile, params.data(), bins.ids + bins.offsets[t],
                                block_pos.data(), block_start, scratch.data()};
            evaluated += kernels.forward(in, cfg, out, work);
        }
    }
    return evaluated;
}

}  // namespace psimap
