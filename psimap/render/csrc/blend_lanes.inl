// The panoptic field's frozen-blend product (psimap.panoptic.fit `_RowBlend`; scipy's CSR product
// is the form the tests hold this to, bit for bit): a view's Top-K feature render of frozen
// geometry is a sparse matrix A [R, V] (CSR, ~K entries a row) times per-surfel features f [V, C].
// Features lie on the lanes; each output is summed over a row's entries in order, multiplications
// and additions as scipy makes them (no FMA contraction), so the product equals scipy's:
// 0 + a_0 f_0 + a_1 f_1 + ... The backward (A^T times the render's gradient, a scatter into random
// surfel rows) stays scipy's: on these lanes it took as long. Included by raster_lanes.inl after
// field_lanes.inl (its load_f / store_f), inside namespace psimap::PSIMAP_ISA_NS.

// out [r, :] = sum_j data[j] f[indices[j], :] over the entries j of rows [r0, r1) (indptr [R + 1]).
void blend_rows_forward(const int64_t* indptr, const int32_t* indices, const float* data, const float* f,
                        int64_t r0, int64_t r1, int64_t C, float* out) {
    for (int64_t r = r0; r < r1; ++r) {
        const int64_t j0 = indptr[r], j1 = indptr[r + 1];
        float* o = out + r * C;
        for (int64_t q0 = 0; q0 < C; q0 += kLanes) {
            vf acc = vf{};
            for (int64_t j = j0; j < j1; ++j)
                acc += splat(data[j]) * load_f(f + static_cast<int64_t>(indices[j]) * C, q0, C);
            store_f(o, q0, C, acc);
        }
    }
}
