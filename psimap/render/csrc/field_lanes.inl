// The panoptic field's per-surfel instance distribution (psimap.panoptic.queries,
// `instance_distribution_reference` is the readable torch form the tests hold this to), fused:
//   m2 = sum_k terms[v, k] coef[q, k] (float64, rounded to float32),
//   s = sigmoid(dot), e = exp(-min(m2, kMaxM2) / 2), l = s e / T,
//   out = softmax_q(l) * p_thing
// over rows of Q queries, kLanes queries per vector. In torch it was ~9 passes over [V, Q]
// forward and ~13 backward with their temporaries (two of them casts of m2 between float64 and
// float32): 24 ms forward and backward at 17k surfels x 93 queries, 8 ms here. The squared
// Mahalanobis distances m2 are summed here from the surfels' quadratic monomials and the queries'
// coefficients (InstanceQueries.mahalanobis_terms), and their gradient goes straight into the
// coefficients': the [V, Q] float64 distances, their gradient and the two float64 products that
// made and reduced them (~10 ms of a 93-query room step) are never built. Included by
// raster_isa_*.cpp after raster_lanes.inl, inside namespace psimap::PSIMAP_ISA_NS (simd_lanes.h is
// already there): the rows [v0, v1) of a call, each computed alone (no OpenMP nor any shared inline
// function here; the bindings call it on all rows).

namespace {

constexpr float kMaxM2 = 160.0f;       // psimap.panoptic.queries.MAX_MAHALANOBIS2
constexpr float kMinExpArg = -87.0f;   // exp_nonpositive stays a normal float down to here

// exp(x) for x <= 0: exp_nonpositive's reduction holds while 2^n is a normal float
// (n >= -126); below -87 the result (< 1.7e-38) is returned for -87.
PSIMAP_LANE_FN vf exp_le0(vf x) { return exp_nonpositive(select(x < kMinExpArg, splat(kMinExpArg), x)); }

// sigmoid(x) = 1 / (1 + exp(-x)) from exp(-|x|) <= 1 (no overflow for large |x|).
PSIMAP_LANE_FN vf sigmoid_of(vf x) {
    const vi neg = x < 0.0f;
    const vf e = exp_le0(select(neg, x, -x));
    return select(neg, e, splat(1.0f)) / (1.0f + e);
}

// Lanes [q0, q0 + kLanes) of a row: a full vector is one unaligned load or store; the row's last,
// partial one a masked load / store on AVX-512 and AVX2 (the lanes past the row read as 0 and are
// not written), value by value through memory on the baseline set.
PSIMAP_LANE_FN int tail_of(int64_t q0, int64_t Q) { return Q - q0 < kLanes ? static_cast<int>(Q - q0) : kLanes; }

#if PSIMAP_LANES == 8 && defined(__AVX2__)
PSIMAP_LANE_FN __m256i first_lanes(int n) {
    return _mm256_cmpgt_epi32(_mm256_set1_epi32(n), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
}
PSIMAP_LANE_FN __m256i first_lanes_d(int n) {  // 4 doubles
    return _mm256_cmpgt_epi64(_mm256_set1_epi64x(n), _mm256_setr_epi64x(0, 1, 2, 3));
}
#endif

PSIMAP_LANE_FN vf load_f(const float* row, int64_t q0, int64_t Q) {
    vf v;
    const int n = tail_of(q0, Q);
    if (n == kLanes) {
        memcpy(&v, row + q0, sizeof v);
        return v;
    }
#if PSIMAP_LANES == 16 && defined(__AVX512F__)
    return reinterpret_cast<vf>(_mm512_maskz_loadu_ps(static_cast<__mmask16>((1u << n) - 1u), row + q0));
#elif PSIMAP_LANES == 8 && defined(__AVX2__)
    return reinterpret_cast<vf>(_mm256_maskload_ps(row + q0, first_lanes(n)));
#else
    float a[kLanes] = {};
    for (int l = 0; l < n; ++l) a[l] = row[q0 + l];
    memcpy(&v, a, sizeof v);
    return v;
#endif
}
// The float64 values of lanes [q0, q0 + kLanes) of a row as two halves (lanes past the row: 0).
PSIMAP_LANE_FN void load_d_halves(const double* row, int64_t q0, int64_t Q, vd* lo, vd* hi) {
    const int n = tail_of(q0, Q);
    if (n == kLanes) {
        memcpy(lo, row + q0, sizeof *lo);
        memcpy(hi, row + q0 + kHalf, sizeof *hi);
        return;
    }
#if PSIMAP_LANES == 16 && defined(__AVX512F__)
    const unsigned m = (1u << n) - 1u;
    *lo = reinterpret_cast<vd>(_mm512_maskz_loadu_pd(static_cast<__mmask8>(m & 0xffu), row + q0));
    *hi = reinterpret_cast<vd>(_mm512_maskz_loadu_pd(static_cast<__mmask8>(m >> 8), row + q0 + 8));
#elif PSIMAP_LANES == 8 && defined(__AVX2__)
    *lo = reinterpret_cast<vd>(_mm256_maskload_pd(row + q0, first_lanes_d(n)));
    *hi = reinterpret_cast<vd>(_mm256_maskload_pd(row + q0 + 4, first_lanes_d(n - 4)));
#else
    double a[kLanes] = {};
    for (int l = 0; l < n; ++l) a[l] = row[q0 + l];
    memcpy(lo, a, sizeof *lo);
    memcpy(hi, a + kHalf, sizeof *hi);
#endif
}
// Adds lanes [q0, q0 + kLanes) of a float64 row, lanes past the row left alone.
PSIMAP_LANE_FN void add_d_halves(double* row, int64_t q0, int64_t Q, vd lo, vd hi) {
    vd a, b;
    load_d_halves(row, q0, Q, &a, &b);
    a += lo;
    b += hi;
    const int n = tail_of(q0, Q);
    if (n == kLanes) {
        memcpy(row + q0, &a, sizeof a);
        memcpy(row + q0 + kHalf, &b, sizeof b);
        return;
    }
    double t[kLanes];
    memcpy(t, &a, sizeof a);
    memcpy(t + kHalf, &b, sizeof b);
    for (int l = 0; l < n; ++l) row[q0 + l] = t[l];
}
PSIMAP_LANE_FN void store_f(float* row, int64_t q0, int64_t Q, vf v) {
    const int n = tail_of(q0, Q);
    if (n == kLanes) {
        memcpy(row + q0, &v, sizeof v);
        return;
    }
#if PSIMAP_LANES == 16 && defined(__AVX512F__)
    _mm512_mask_storeu_ps(row + q0, static_cast<__mmask16>((1u << n) - 1u), reinterpret_cast<__m512>(v));
#elif PSIMAP_LANES == 8 && defined(__AVX2__)
    _mm256_maskstore_ps(row + q0, first_lanes(n), reinterpret_cast<__m256>(v));
#else
    float a[kLanes];
    memcpy(a, &v, sizeof a);
    for (int l = 0; l < n; ++l) row[q0 + l] = a[l];
#endif
}
PSIMAP_LANE_FN vi real_lanes(int64_t q0, int64_t Q) {
    vi idx;
    for (int l = 0; l < kLanes; ++l) idx[l] = l;
    return idx < static_cast<int32_t>(Q - q0 < kLanes ? Q - q0 : kLanes);
}
// Horizontal max / sum of a row's lanes: intrinsics on AVX-512 and x86 baselines, a halving tree
// through memory elsewhere (a row of 16-20 queries is one or two vectors, so these reductions and
// not the arithmetic set the cost of a row).
PSIMAP_LANE_FN float row_max(vf v) {
#if PSIMAP_LANES == 16 && defined(__AVX512F__)
    return _mm512_reduce_max_ps(reinterpret_cast<__m512>(v));
#elif PSIMAP_LANES == 8 && defined(__AVX2__)
    __m128 m = _mm_max_ps(_mm256_castps256_ps128(reinterpret_cast<__m256>(v)),
                          _mm256_extractf128_ps(reinterpret_cast<__m256>(v), 1));
    m = _mm_max_ps(m, _mm_movehl_ps(m, m));
    return _mm_cvtss_f32(_mm_max_ss(m, _mm_shuffle_ps(m, m, 1)));
#elif PSIMAP_LANES == 4 && defined(__SSE2__)
    __m128 m = reinterpret_cast<__m128>(v);
    m = _mm_max_ps(m, _mm_movehl_ps(m, m));
    return _mm_cvtss_f32(_mm_max_ss(m, _mm_shuffle_ps(m, m, 1)));
#else
    float a[kLanes];
    memcpy(a, &v, sizeof a);
    for (int w = kLanes / 2; w >= 1; w /= 2)
        for (int l = 0; l < w; ++l) a[l] = a[l + w] > a[l] ? a[l + w] : a[l];
    return a[0];
#endif
}
PSIMAP_LANE_FN float row_sum(vf v) {
#if PSIMAP_LANES == 16 && defined(__AVX512F__)
    return _mm512_reduce_add_ps(reinterpret_cast<__m512>(v));
#elif PSIMAP_LANES == 8 && defined(__AVX2__)
    __m128 s = _mm_add_ps(_mm256_castps256_ps128(reinterpret_cast<__m256>(v)),
                          _mm256_extractf128_ps(reinterpret_cast<__m256>(v), 1));
    s = _mm_add_ps(s, _mm_movehl_ps(s, s));
    return _mm_cvtss_f32(_mm_add_ss(s, _mm_shuffle_ps(s, s, 1)));
#elif PSIMAP_LANES == 4 && defined(__SSE2__)
    __m128 s = reinterpret_cast<__m128>(v);
    s = _mm_add_ps(s, _mm_movehl_ps(s, s));
    return _mm_cvtss_f32(_mm_add_ss(s, _mm_shuffle_ps(s, s, 1)));
#else
    return lane_sum(v);
#endif
}

// The affinity term of one lane vector: s = sigmoid(dot), e = exp(-min(m2, kMaxM2) / 2).
PSIMAP_LANE_FN void affinity_terms(vf dot, vf m2, vf* s, vf* e) {
    *s = sigmoid_of(dot);
    *e = exp_le0(-0.5f * min_of(m2, splat(kMaxM2)));
}

// m2 of a row's lanes: sum_k terms[k] coef_t[k, q] in float64 (k = 0 .. K-1, in order), rounded
// to float32 as torch's cast of the float64 product rounds it.
PSIMAP_LANE_FN vf m2_lanes(const double* terms, const double* coef_t, int64_t K, int64_t q0, int64_t Q) {
    vd lo = vd{}, hi = vd{};
    for (int64_t k = 0; k < K; ++k) {
        vd c_lo, c_hi;
        load_d_halves(coef_t + k * Q, q0, Q, &c_lo, &c_hi);
        lo += terms[k] * c_lo;
        hi += terms[k] * c_hi;
    }
    return to_float(lo, hi);
}

}  // namespace

// Rows [v0, v1) of dot [V, Q] float32 (surfel . query features), the squared Mahalanobis distances
// m2 = terms [V, K] x coef_t [K, Q] (float64: each surfel's quadratic monomials, each query's
// coefficients, psimap.panoptic.queries.InstanceQueries.mahalanobis_terms), p_thing [V] or null
// (factor 1): out [V, Q] the distribution, soft [V, Q] the softmax (saved for the backward).
void field_forward_rows(const float* dot, const double* terms, const double* coef_t, int64_t K,
                        const float* p_thing, int64_t v0, int64_t v1, int64_t Q, float temperature, float* out,
                        float* soft) {
    const float inv_t = 1.0f / temperature;
    for (int64_t v = v0; v < v1; ++v) {
        const float* d_row = dot + v * Q;
        const double* t_row = terms + v * K;
        float* o_row = out + v * Q;
        float* s_row = soft + v * Q;
        vf mx = splat(-__builtin_inff());
        for (int64_t q0 = 0; q0 < Q; q0 += kLanes) {
            vf s, e;
            affinity_terms(load_f(d_row, q0, Q), m2_lanes(t_row, coef_t, K, q0, Q), &s, &e);
            const vf l = (s * e) * inv_t;
            store_f(o_row, q0, Q, l);
            mx = select(real_lanes(q0, Q) & (l > mx), l, mx);
        }
        const float m = row_max(mx);
        vf sum = vf{};
        for (int64_t q0 = 0; q0 < Q; q0 += kLanes) {
            const vf p = select(real_lanes(q0, Q), exp_le0(load_f(o_row, q0, Q) - m), vf{});
            store_f(s_row, q0, Q, p);
            sum += p;
        }
        const float inv_total = 1.0f / row_sum(sum);
        const float pt = p_thing ? p_thing[v] : 1.0f;
        for (int64_t q0 = 0; q0 < Q; q0 += kLanes) {
            const vf p = load_f(s_row, q0, Q) * inv_total;
            store_f(s_row, q0, Q, p);
            store_f(o_row, q0, Q, p * pt);
        }
    }
}

// Rows [v0, v1) of the affinity alone, out [V, Q] = sigmoid(dot) exp(-min(m2, kMaxM2) / 2) (the
// same lanes as field_forward_rows before its softmax): the adjustments' and the labels' scene-wide
// affinity (psimap.panoptic.queries.InstanceQueries.affinity), where torch built the [V, Q] float64
// distances by a product with 10 columns, cast them and ran four more passes (~130 ms for 65k
// surfels x 93 queries).
void field_affinity_rows(const float* dot, const double* terms, const double* coef_t, int64_t K, int64_t v0,
                         int64_t v1, int64_t Q, float* out) {
    for (int64_t v = v0; v < v1; ++v) {
        const float* d_row = dot + v * Q;
        const double* t_row = terms + v * K;
        float* o_row = out + v * Q;
        for (int64_t q0 = 0; q0 < Q; q0 += kLanes) {
            vf s, e;
            affinity_terms(load_f(d_row, q0, Q), m2_lanes(t_row, coef_t, K, q0, Q), &s, &e);
            store_f(o_row, q0, Q, s * e);
        }
    }
}

// The backward of field_distribution_forward for v_out [V, Q]: v_dot [V, Q] float32, v_coef_t [K, Q]
// float64 added to (the terms are constants; m2's gradient is 0 where m2 > kMaxM2, the cap's),
// v_p_thing [V] (written when p_thing is given).
void field_backward_rows(const float* dot, const double* terms, const double* coef_t, int64_t K,
                         const float* p_thing, const float* soft, const float* v_out, int64_t v0, int64_t v1,
                         int64_t Q, float temperature, float* v_dot, double* v_coef_t, float* v_p_thing) {
    const float inv_t = 1.0f / temperature;
    for (int64_t v = v0; v < v1; ++v) {
        const float* s_row = soft + v * Q;
        const float* g_row = v_out + v * Q;
        const float pt = p_thing ? p_thing[v] : 1.0f;
        vf gp = vf{}, us = vf{};
        for (int64_t q0 = 0; q0 < Q; q0 += kLanes) {
            const vf sm = load_f(s_row, q0, Q), g = load_f(g_row, q0, Q);
            gp += g * sm;
            us += (g * pt) * sm;
        }
        if (p_thing) v_p_thing[v] = row_sum(gp);
        const float c = row_sum(us);
        const float* d_row = dot + v * Q;
        const double* t_row = terms + v * K;
        float* vd_row = v_dot + v * Q;
        for (int64_t q0 = 0; q0 < Q; q0 += kLanes) {
            const vf sm = load_f(s_row, q0, Q), g = load_f(g_row, q0, Q);
            const vf v_a = (sm * (g * pt - c)) * inv_t;        // through the softmax and 1/T
            const vf m = m2_lanes(t_row, coef_t, K, q0, Q);
            vf s, e;
            affinity_terms(load_f(d_row, q0, Q), m, &s, &e);
            store_f(vd_row, q0, Q, (v_a * e) * ((1.0f - s) * s));
            // m2's gradient (0 past the cap) into the coefficients': v_coef_t[k, q] += terms[k] v_m2[q]
            const vf v_m = select(m <= kMaxM2, ((v_a * s) * e) * -0.5f, vf{});
            const vd lo = lo_d(v_m), hi = hi_d(v_m);
            for (int64_t k = 0; k < K; ++k) add_d_halves(v_coef_t + k * Q, q0, Q, t_row[k] * lo, t_row[k] * hi);
        }
    }
}
