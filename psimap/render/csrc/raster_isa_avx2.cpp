// The pixel kernels (raster_lanes.inl) for AVX2 (8 lanes: half a 4x4 block per vector).
// Built with this file's own instruction-set flags (CMakeLists.txt); raster_dispatch.cpp runs it only
// on a CPU that supports them.
#define PSIMAP_LANES 8
#define PSIMAP_ISA_NS isa_avx2
#define PSIMAP_ISA_NAME "avx2"
#include "raster_lanes.inl"
