// The pixel kernels (raster_lanes.inl) for the compiler's baseline (4 lanes: SSE2 on x86-64, NEON on arm64).
// Built with this file's own instruction-set flags (CMakeLists.txt); raster_dispatch.cpp runs it only
// on a CPU that supports them.
#define PSIMAP_LANES 4
#define PSIMAP_ISA_NS isa_baseline
#define PSIMAP_ISA_NAME "baseline"
#include "raster_lanes.inl"
