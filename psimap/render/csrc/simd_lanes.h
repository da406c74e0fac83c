// Vectors of PSIMAP_LANES floats (GCC / Clang vector extensions) for the pixel kernels: one lane
// per pixel of a 4x4 block (16 lanes: AVX-512), of half a block (8: AVX2) or of a block row (4:
// SSE2 / NEON). Included only by raster_lanes.inl, inside an ISA-specific namespace (after
// <stdint.h>, <string.h> and, on x86, <immintrin.h>): every function here is compiled for that
// ISA and must never be shared with (linked into) another.
#pragma once

#ifndef PSIMAP_LANES
#error "define PSIMAP_LANES (4, 8 or 16) before including simd_lanes.h"
#endif

#define PSIMAP_LANE_FN static inline __attribute__((always_inline))

constexpr int kLanes = PSIMAP_LANES;
constexpr int kHalf = kLanes / 2;  // doubles per half vector
typedef float vf __attribute__((vector_size(4 * kLanes)));
typedef int32_t vi __attribute__((vector_size(4 * kLanes)));   // masks: -1 (true) / 0
typedef int32_t vi_half __attribute__((vector_size(2 * kLanes)));
typedef float vf_half __attribute__((vector_size(2 * kLanes)));
typedef double vd __attribute__((vector_size(4 * kLanes)));    // kHalf doubles
typedef int64_t vl __attribute__((vector_size(4 * kLanes)));

PSIMAP_LANE_FN vf splat(float x) { return vf{} + x; }
PSIMAP_LANE_FN vi splat_i(int32_t x) { return vi{} + x; }

// Bit l set when lane l of the mask is true.
PSIMAP_LANE_FN unsigned lane_bits(vi m) {
#if PSIMAP_LANES == 16 && defined(__AVX512F__)
    return _mm512_cmplt_epi32_mask(reinterpret_cast<__m512i>(m), _mm512_setzero_si512());
#elif PSIMAP_LANES == 8 && defined(__AVX2__)
    return static_cast<unsigned>(_mm256_movemask_ps(reinterpret_cast<__m256>(m)));
#elif PSIMAP_LANES == 4 && defined(__SSE2__)
    return static_cast<unsigned>(_mm_movemask_ps(reinterpret_cast<__m128>(m)));
#else
    unsigned b = 0;
    for (int l = 0; l < kLanes; ++l) b |= (m[l] != 0 ? 1u : 0u) << l;
    return b;
#endif
}
PSIMAP_LANE_FN bool any(vi m) { return lane_bits(m) != 0; }

PSIMAP_LANE_FN vf select(vi m, vf a, vf b) { return m ? a : b; }
PSIMAP_LANE_FN vi select(vi m, vi a, vi b) { return m ? a : b; }
PSIMAP_LANE_FN vd select(vl m, vd a, vd b) { return m ? a : b; }

// Half `upper` of a lane vector (0: lanes 0 .. kHalf-1, 1: the rest), converted lane by lane:
// floats to doubles, 32-bit masks to 64-bit masks.
template <typename Out, typename Half, typename In>
PSIMAP_LANE_FN Out half_of(In v, int upper) {
    Half h;
    memcpy(&h, reinterpret_cast<const char*>(&v) + upper * sizeof h, sizeof h);
    return __builtin_convertvector(h, Out);
}
PSIMAP_LANE_FN vd lo_d(vf v) { return half_of<vd, vf_half>(v, 0); }
PSIMAP_LANE_FN vd hi_d(vf v) { return half_of<vd, vf_half>(v, 1); }
PSIMAP_LANE_FN vl lo_mask(vi m) { return half_of<vl, vi_half>(m, 0); }
PSIMAP_LANE_FN vl hi_mask(vi m) { return half_of<vl, vi_half>(m, 1); }

// Two halves of doubles back to one lane vector of floats (each rounded as static_cast<float>).
PSIMAP_LANE_FN vf to_float(vd lo, vd hi) {
    const vf_half l = __builtin_convertvector(lo, vf_half), h = __builtin_convertvector(hi, vf_half);
    vf v;
    memcpy(&v, &l, sizeof l);
    memcpy(reinterpret_cast<char*>(&v) + sizeof l, &h, sizeof h);
    return v;
}

// std::min(a, b) lane by lane: (b < a) ? b : a (the same float decisions as the scalar kernels).
PSIMAP_LANE_FN vf min_of(vf a, vf b) { return select(b < a, b, a); }

// exp(x) for -6 <= x <= 0 (the kernels' range), within 1 ulp of glibc's expf (max relative error
// 1.02e-7, measured over every float in the range): x = n ln2 + r, |r| <= ln2/2, exp(r) by its
// degree-7 Taylor polynomial, times 2^n through the exponent bits. Plain + - * (no FMA: the build
// turns contraction off), so every lane count gives the same bits and the backward re-evaluates
// the forward's alphas exactly. Callers pass 0 in the lanes they do not need.
PSIMAP_LANE_FN vf exp_nonpositive(vf x) {
    const float round_magic = 12582912.0f;  // 1.5 * 2^23: adding it rounds to an integer
    const vf t = x * 1.44269504088896341f + round_magic;
    const vf n = t - round_magic;
    const vi n_int = reinterpret_cast<vi>(t) - reinterpret_cast<vi>(splat(round_magic));
    // ln 2 = 0.693359375 (9 bits: n * it is exact) - 2.12194440e-4
    const vf r = (x - n * 0.693359375f) - n * -2.12194440e-4f;
    vf p = splat(1.0f / 5040.0f);
    p = p * r + 1.0f / 720.0f;
    p = p * r + 1.0f / 120.0f;
    p = p * r + 1.0f / 24.0f;
    p = p * r + 1.0f / 6.0f;
    p = p * r + 0.5f;
    p = p * r + 1.0f;
    p = p * r + 1.0f;
    return p * reinterpret_cast<vf>((n_int + 127) << 23);
}

// Sum of the lanes, halving pairwise (the same tree for a given lane count).
PSIMAP_LANE_FN float lane_sum(vf v) {
    float a[kLanes];
    memcpy(a, &v, sizeof a);
    for (int w = kLanes / 2; w >= 1; w /= 2)
        for (int l = 0; l < w; ++l) a[l] = a[l] + a[l + w];
    return a[0];
}
