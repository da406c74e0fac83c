// Which build of the pixel kernels runs: the widest instruction set the CPU supports among those
// the compiler could build (CMakeLists.txt defines PSIMAP_HAVE_AVX2 / PSIMAP_HAVE_AVX512).
// The choice is made once per process; every build gives the same forward bits.
#include "rasterize.h"

namespace psimap {

#define PSIMAP_DECLARE_KERNELS(ns) \
    namespace ns {                 \
    PixelKernels kernels();        \
    }
PSIMAP_DECLARE_KERNELS(isa_baseline)
#ifdef PSIMAP_HAVE_AVX2
PSIMAP_DECLARE_KERNELS(isa_avx2)
#endif
#ifdef PSIMAP_HAVE_AVX512
PSIMAP_DECLARE_KERNELS(isa_avx512)
#endif

namespace {

std::vector<PixelKernels> runnable() {
    std::vector<PixelKernels> k;
#if defined(__x86_64__) || defined(__i386__)
    __builtin_cpu_init();
#ifdef PSIMAP_HAVE_AVX512
    if (__builtin_cpu_supports("avx512f")) k.push_back(isa_avx512::kernels());
#endif
#ifdef PSIMAP_HAVE_AVX2
    if (__builtin_cpu_supports("avx2")) k.push_back(isa_avx2::kernels());
#endif
#endif
    k.push_back(isa_baseline::kernels());
    return k;
}

PixelKernels& current() {
    static PixelKernels chosen = runnable().front();
    return chosen;
}

}  // namespace

const PixelKernels& pixel_kernels() { return current(); }

std::vector<std::string> available_kernels() {
    std::vector<std::string> names;
    for (const PixelKernels& k : runnable()) names.push_back(k.isa);
    return names;
}

bool select_kernels(const std::string& isa) {
    for (const PixelKernels& k : runnable())
        if (isa.empty() || isa == k.isa) {
            current() = k;
            return true;
        }
    return false;
}

}  // namespace psimap
