// The pixel kernels (raster_lanes.inl) for AVX-512 (16 lanes: a whole 4x4 block per vector).
// Built with this file's own instruction-set flags (CMakeLists.txt); raster_dispatch.cpp runs it only
// on a CPU that supports them.
#define PSIMAP_LANES 16
#define PSIMAP_ISA_NS isa_avx512
#define PSIMAP_ISA_NAME "avx512"
#include "raster_lanes.inl"
