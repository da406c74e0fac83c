// The native kernels' thread count, kept apart from OpenMP's global default: torch (same libgomp)
// reads that default as its own intra-op thread count, so setting it for the renderer would also
// split torch's reductions differently and change training's numbers with the core count.
#pragma once

#include <atomic>

#include <omp.h>

namespace psimap {

inline std::atomic<int>& kernel_threads_slot() {
    static std::atomic<int> n{omp_get_max_threads()};  // OMP_NUM_THREADS or the cores, at load
    return n;
}

// Every `#pragma omp parallel` of the kernels says num_threads(kernel_threads()).
inline int kernel_threads() { return kernel_threads_slot().load(std::memory_order_relaxed); }

inline void set_kernel_threads(int n) { kernel_threads_slot().store(n < 1 ? 1 : n); }

}  // namespace psimap
