"""The frozen blend's product on the native lanes (psimap/render/csrc/blend_lanes.inl,
psimap.render.native.blend_rows) against scipy's CSR product, which it must equal bit for bit
(each sum in the order of the row's entries, no FMA contraction): the panoptic field trained on
frozen geometry is then the same whichever computes it. Column counts cover one lane, whole
vectors and partial last vectors of every instruction set (4, 8 and 16 lanes)."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse
import torch

from psimap.render.api import native_available

# every native output buffer starts as NaN: a value a kernel forgets to write fails
pytestmark = [pytest.mark.skipif(not native_available(), reason="native kernels not built"),
              pytest.mark.usefixtures("poison_native_outputs")]


def blend(rows: int, cols: int, seed: int) -> scipy.sparse.csr_matrix:
    """A float32 CSR matrix shaped like a frozen blend: up to 8 entries a row in Top-K order (not
    sorted by column), some rows empty, weights in (0, 1)."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(0, 9, rows)
    counts[::7] = 0
    indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
    indices = np.concatenate([rng.choice(cols, c, replace=False) for c in counts]).astype(np.int32)
    data = rng.random(int(indptr[-1])).astype(np.float32)
    return scipy.sparse.csr_matrix((data, indices, indptr), shape=(rows, cols))


@pytest.mark.parametrize("c", [1, 5, 11, 16, 17, 33, 93])
def test_native_product_equals_scipys_bit_for_bit_on_every_instruction_set(c):
    from psimap.render import _native
    from psimap.render.native import blend_rows

    A = blend(400, 250, seed=c)
    f = torch.randn(250, c, generator=torch.Generator().manual_seed(c))
    want = torch.from_numpy(A @ f.numpy())
    sub = A[np.array([3, 7, 8, 100, 399])]                   # a step's sampled rows (at_pixels)
    try:
        for isa in _native.available_pixel_kernels():
            _native.use_pixel_kernels(isa)
            assert torch.equal(blend_rows(A, f), want), isa
            assert torch.equal(blend_rows(sub, f), torch.from_numpy(sub @ f.numpy())), isa
    finally:
        _native.use_pixel_kernels("")
    assert bool((want[::7] == 0).all())                      # empty rows are zeros, not poison


def test_a_nan_feature_reaches_only_the_rows_that_blend_its_surfel():
    from psimap.render.native import blend_rows

    A = blend(300, 120, seed=3)
    f = torch.randn(120, 17)
    f[42, 5] = float("nan")
    out = blend_rows(A, f)
    uses = torch.from_numpy((A[:, 42].toarray().ravel() != 0))
    assert bool(uses.any())
    assert bool(out[uses, 5].isnan().all())
    assert int(out.isnan().sum()) == int(uses.sum())


def test_the_row_blend_takes_the_kernel_and_keeps_scipys_gradient(monkeypatch):
    """fit._RowBlend (every frozen-blend step's render) runs the kernel forward; values and the
    gradient (scipy's transpose product) equal the scipy-only path's."""
    import psimap.panoptic.fit as fit
    import psimap.render.native as native

    A = blend(200, 90, seed=5)
    f = torch.randn(90, 21, requires_grad=True)
    w = torch.randn(200, 21)
    calls = []
    real = native.blend_rows
    monkeypatch.setattr(native, "blend_rows", lambda *a: calls.append(1) or real(*a))
    out = fit._RowBlend.apply(f, A)
    (g,) = torch.autograd.grad((out * w).sum(), f)
    assert calls == [1]
    monkeypatch.setattr("psimap.render.api.native_available", lambda: False)
    out_scipy = fit._RowBlend.apply(f, A)
    (g_scipy,) = torch.autograd.grad((out_scipy * w).sum(), f)
    assert calls == [1]                                       # the scipy path did not call it
    assert torch.equal(out, out_scipy) and torch.equal(g, g_scipy)


def test_bad_matrices_are_refused():
    from psimap.render import _native
    from psimap.render.native import blend_rows

    A = blend(20, 10, seed=1)
    f = torch.randn(10, 4)
    with pytest.raises(ValueError, match="float32"):
        blend_rows(A.astype(np.float64), f)
    with pytest.raises(ValueError, match="float32"):
        blend_rows(A, f[:9])
    indptr = A.indptr.astype(np.int64)
    indices = A.indices.copy()
    indices[3] = 10                                           # one column past V
    out = np.empty((20, 4), np.float32)
    with pytest.raises(ValueError, match="out of range"):
        _native.blend_rows(indptr, indices, A.data, f.numpy(), 20, 10, 4, out)
    bad = indptr.copy()
    bad[5], bad[6] = bad[6], bad[5] - 1
    with pytest.raises(ValueError, match="indptr"):
        _native.blend_rows(bad, A.indices, A.data, f.numpy(), 20, 10, 4, out)
