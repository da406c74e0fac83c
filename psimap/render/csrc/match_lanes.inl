// The sums the panoptic field's Hungarian matching reads (psimap.panoptic.matching,
// `match_sums_reference` is the readable torch form the tests hold this to), in one pass over a
// view's rendered query probabilities x [P, Q] (pixel-major), for each of M masks:
//   on the mask (target):     sum x,  sum log x,  sum log(1 - x)
//   on its window (mask + ring): sum x,  sum log(1 - x)
// with x clamped to [lo, hi] first. In torch these were a clamped copy, two logarithms and a
// negation of every window pixel's row, each a [P, Q] temporary written and read back by three
// matrix products: ~10 ms a step at 85 queries, ~2 ms at 21. Here each row is read once, its
// logarithms stay in a row-sized scratch, and the sums run in float32 over blocks of pixels, then
// in float64 (no temporary of [P, Q]).
// Included by raster_lanes.inl after field_lanes.inl, inside namespace psimap::PSIMAP_ISA_NS
// (simd_lanes.h and field_lanes.inl's load_f are already there).

namespace {

// log(x) for positive normal floats: x = 2^e m with m in [sqrt(1/2), sqrt(2)), log m =
// 2 atanh(s) with s = (m - 1) / (m + 1), |s| <= 0.172, by its series to s^11 (the next term is
// below 1e-10). Within ~2 ulp of glibc's logf on [1e-6, 1] (tests/test_panoptic_match_native.py).
PSIMAP_LANE_FN vf log_positive(vf x) {
    const vi bits = reinterpret_cast<vi>(x);
    vi e = ((bits >> 23) & 0xff) - 127;
    vf m = reinterpret_cast<vf>((bits & 0x007fffff) | 0x3f800000);   // [1, 2)
    const vi big = m > 1.41421356f;
    m = select(big, m * 0.5f, m);
    e = e - big;                                                       // big lanes are -1
    const vf f = m - 1.0f;
    const vf s = f / (f + 2.0f);
    const vf z = s * s;
    vf p = splat(1.0f / 11.0f);
    p = p * z + 1.0f / 9.0f;
    p = p * z + 1.0f / 7.0f;
    p = p * z + 1.0f / 5.0f;
    p = p * z + 1.0f / 3.0f;
    p = p * z + 1.0f;
    const vf ef = __builtin_convertvector(e, vf);
    // ln 2 = 0.693359375 (9 bits: e * it is exact) - 2.12194440e-4; a NaN stays NaN (its bits
    // would read as some mantissa)
    const vf out = ef * 0.693359375f + ((s + s) * p + ef * -2.12194440e-4f);
    return select(x != x, x, out);
}

// log(1 - x) for x in [0, 1): u = 1 - x rounded, then log(u) + ((1 - u) - x). (1 - u) - x is
// exact (u lies within a factor 2 of 1 or is itself exact) and is u's rounding error d; log(u + d)
// = log(u) + d / u + ..., and d instead of d / u is off by d x / u, < 6e-8 of |log(1 - x)|. No
// division: Kahan's log(u) x / (1 - u) took one more per vector.
PSIMAP_LANE_FN vf log1m(vf x) {
    const vf u = 1.0f - x;
    return log_positive(u) + ((1.0f - u) - x);
}

}  // namespace

// Pixels [p0, p1) of x [P, Q] float32 and codes [M, P] uint8 (0: pixel outside mask m's window,
// 1: in the window only, 2: on the mask, which lies in its window) add into sums [5, M, Q] float64:
// x on the mask, log x on the mask, log(1 - x) on the mask, x on the window, log(1 - x) on the
// window, x clamped to [lo, hi] (0 < lo, hi < 1). A pixel in no window is not read. The sums run
// in float32 over blocks of kSumBlock pixels, then into float64 (only the masks a block touched).
// scratch: match_scratch_floats(Q, M) floats (rasterize.h).
constexpr int64_t kSumBlock = 64;

void match_sums_rows(const float* x, const uint8_t* codes, int64_t P, int64_t p0, int64_t p1, int64_t Q,
                     int64_t M, float lo, float hi, double* sums, float* scratch) {
    const int64_t MQ = M * Q;
    const int64_t W = (Q + kLanes - 1) / kLanes * kLanes;
    float* cx = scratch;               // the row clamped, its log and log(1 - x): [W] each
    float* lx = scratch + W;
    float* l1 = scratch + 2 * W;
    float* acc = scratch + 3 * W;      // [5, M, W] this block's sums
    uint8_t* dirty = reinterpret_cast<uint8_t*>(acc + 5 * M * W);       // [M]
    memset(acc, 0, sizeof(float) * 5 * M * W);
    memset(dirty, 0, M);
    auto add = [W](float* a, const float* v) {
        for (int64_t q0 = 0; q0 < W; q0 += kLanes) {
            vf s, t;
            memcpy(&s, a + q0, sizeof s);
            memcpy(&t, v + q0, sizeof t);
            s += t;
            memcpy(a + q0, &s, sizeof s);
        }
    };
    auto flush = [&]() {
        for (int64_t m = 0; m < M; ++m) {
            if (!dirty[m]) continue;
            dirty[m] = 0;
            for (int k = 0; k < 5; ++k) {
                float* a = acc + (k * M + m) * W;
                double* out = sums + k * MQ + m * Q;
                for (int64_t q = 0; q < Q; ++q) out[q] += a[q];
                memset(a, 0, sizeof(float) * W);
            }
        }
    };
    int64_t in_block = 0;
    for (int64_t p = p0; p < p1; ++p) {
        // mask m's code at codes[m * P + p]: M sequential streams as p goes on
        const uint8_t* c = codes + p;
        bool any_window = false;
        for (int64_t m = 0; m < M; ++m) any_window |= c[m * P] != 0;
        if (!any_window) continue;
        const float* row = x + p * Q;
        for (int64_t q0 = 0; q0 < Q; q0 += kLanes) {
            vf v = load_f(row, q0, Q);
            // NaN stays NaN (both comparisons false), as torch's clamp keeps it
            v = select(v < lo, splat(lo), v);
            v = select(v > hi, splat(hi), v);
            const vf a = log_positive(v), b = log1m(v);
            memcpy(cx + q0, &v, sizeof v);
            memcpy(lx + q0, &a, sizeof a);
            memcpy(l1 + q0, &b, sizeof b);
        }
        for (int64_t m = 0; m < M; ++m) {
            const uint8_t code = c[m * P];
            if (code == 0) continue;
            dirty[m] = 1;
            add(acc + (3 * M + m) * W, cx);
            add(acc + (4 * M + m) * W, l1);
            if (code != 2) continue;
            add(acc + m * W, cx);
            add(acc + (M + m) * W, lx);
            add(acc + (2 * M + m) * W, l1);
        }
        if (++in_block == kSumBlock) {
            flush();
            in_block = 0;
        }
    }
    flush();
}
