"""The panoptic field's fused per-surfel distribution (psimap/render/csrc/field_lanes.inl,
psimap.render.native.instance_distribution) against its torch form
(psimap.panoptic.queries.instance_distribution_reference).

Oracle: the reference in float64 on float32-representable inputs (the kernel computes in float32;
m2 = terms x coef is summed in float64 and rounded to float32, as the oracle rounds it). Values of the distribution lie in [0, 1]: held
to 4e-6 absolute (measured <= 1.1e-6 over 5 seeds x 6 row lengths x 3 instruction sets); gradients
to 2e-5 of each gradient's largest magnitude (measured <= 5.5e-6: float32 sums over up to 93 queries). Row lengths cover a single lane, whole vectors and partial last vectors of every
instruction set (4, 8 and 16 lanes)."""
from __future__ import annotations

import pytest
import torch

from psimap.panoptic.queries import (MAX_MAHALANOBIS2, InstanceQueries, instance_distribution,
                                     instance_distribution_reference)
from psimap.render.api import native_available

# every native output buffer starts as NaN: a value a kernel forgets to write fails
pytestmark = [pytest.mark.skipif(not native_available(), reason="native kernels not built"),
              pytest.mark.usefixtures("poison_native_outputs")]


def inputs(v: int, q: int, seed: int, k: int = 10):
    """dot [V, Q] float32 (a few at +-60: saturated sigmoids), terms [V, K] and coef [Q, K] float64
    with m2 = terms coef^T in [0, ~300] (query 0 past the cap, 160, on every surfel; surfel 1 at
    m2 = 0 from every query), p_thing [V] float32, upstream w [V, Q]."""
    g = torch.Generator().manual_seed(seed)
    dot = torch.randn(v, q, generator=g) * 4
    dot[torch.rand(v, q, generator=g) < 0.03] = 60.0
    dot[torch.rand(v, q, generator=g) < 0.03] = -60.0
    terms = (0.5 + 0.5 * torch.rand(v, k, generator=g)).double()
    terms[1] = 0.0
    coef = (torch.rand(q, k, generator=g) * 30.0 / k).double()
    coef[0] = 400.0 / k                                    # m2 >= 200 > the cap
    pt = torch.rand(v, generator=g)
    w = torch.randn(v, q, generator=g)
    return dot, terms, coef, pt, w


def reference(dot, terms, coef, pt, temperature):
    """The torch form on m2 rounded to float32 (as the kernel rounds its float64 sums)."""
    m2 = (terms @ coef.T).float().to(torch.float64)
    return instance_distribution_reference(dot, m2, pt, temperature)


def evaluate(fn, dot, terms, coef, pt, w, dtype):
    """(out, v_dot, v_coef, v_p_thing) of fn on leaves in `dtype` (terms and coef always float64)."""
    leaves = [dot.to(dtype).requires_grad_(True), coef.clone().requires_grad_(True)]
    if pt is not None:
        leaves.append(pt.to(dtype).requires_grad_(True))
    out = fn(leaves[0], terms, leaves[1], leaves[2] if pt is not None else None, 0.1)
    grads = torch.autograd.grad((out * w.to(dtype)).sum(), leaves)
    return [out.detach().double(), *(g.double() for g in grads)]


@pytest.mark.parametrize("q", [1, 5, 16, 17, 33, 93])
@pytest.mark.parametrize("with_thing", [True, False])
def test_native_distribution_matches_the_reference_on_every_instruction_set(q, with_thing):
    from psimap.render import _native

    dot, terms, coef, pt, w = inputs(150, q, seed=q + 100 * with_thing)
    pt = pt if with_thing else None
    m2 = terms @ coef.T
    far = torch.ones(150, dtype=torch.bool)
    far[1] = False                                         # surfel 1: m2 = 0 (and no coefficient gradient)
    assert float(m2[far, 0].min()) > MAX_MAHALANOBIS2 and (q == 1 or float(m2[:, 1:].max()) < MAX_MAHALANOBIS2)
    ref = evaluate(reference, dot, terms, coef, pt, w, torch.float64)
    assert float(ref[0].sum(-1).max()) <= 1.0 + 1e-9
    try:
        for isa in _native.available_pixel_kernels():
            _native.use_pixel_kernels(isa)
            got = evaluate(lambda *a: instance_distribution(*a, backend="native"), dot, terms, coef, pt, w,
                           torch.float32)
            torch.testing.assert_close(got[0], ref[0], rtol=0.0, atol=4e-6, msg=f"{isa}: values")
            for name, a, b in zip(("dot", "coef", "p_thing"), got[1:], ref[1:]):
                torch.testing.assert_close(a, b, rtol=0.0, atol=2e-5 * float(b.abs().max()) + 1e-12,
                                           msg=f"{isa}: gradient of {name}")
            # beyond the cap the distance gets no gradient (the reference's clamp_max): query 0's
            # coefficients, past it on every surfel
            assert float(got[2][0].abs().max()) == 0.0
            if q > 1:
                assert float(got[2][1:].abs().max()) > 0.0
    finally:
        _native.use_pixel_kernels("")


def test_a_nan_row_stays_in_its_row():
    """A NaN input spoils its own surfel's row (as the reference's softmax does) and no other."""
    dot, terms, coef, pt, w = inputs(40, 17, seed=3)
    clean = instance_distribution(dot, terms, coef, pt, 0.1, backend="native")
    dot[5, 16] = float("nan")
    terms[9, 0] = float("nan")
    out = instance_distribution(dot, terms, coef, pt, 0.1, backend="native")
    ref = reference(dot, terms, coef, pt, 0.1)
    for r in (5, 9):
        assert bool(out[r].isnan().all()) and bool(ref[r].isnan().all())
    rest = torch.ones(40, dtype=torch.bool)
    rest[[5, 9]] = False
    assert torch.equal(out[rest], clean[rest])


def test_queries_distribution_runs_the_kernel_and_keeps_the_reference_value():
    """InstanceQueries.distribution (what every panoptic step calls) takes the fused kernel for float32
    CPU tensors and gives the torch form's values and gradients (backend="torch")."""
    g = torch.Generator().manual_seed(4)
    q = 21
    queries = InstanceQueries(torch.randn(q, 16, generator=g), torch.randn(q, 3, generator=g),
                              torch.eye(3).expand(q, 3, 3) * 0.2, generator=g)
    feat = torch.randn(300, 16, generator=g, requires_grad=True)
    pos = torch.randn(300, 3, generator=g)
    pt = torch.rand(300, generator=g, requires_grad=True)
    w = torch.randn(300, q, generator=g)
    params = [feat, pt, queries.feature, queries.mean, queries.log_diag, queries.offdiag]
    outs = {}
    for backend in ("auto", "torch"):
        d = queries.distribution(feat, pos, p_thing=pt, backend=backend)
        outs[backend] = (d.detach(), torch.autograd.grad((d * w).sum(), params), type(d.grad_fn).__name__)
    assert outs["auto"][2] == "_FieldDistributionBackward" and outs["torch"][2] != outs["auto"][2]
    torch.testing.assert_close(outs["auto"][0], outs["torch"][0], rtol=0.0, atol=4e-6)
    for a, b in zip(outs["auto"][1], outs["torch"][1]):
        torch.testing.assert_close(a, b, rtol=0.0, atol=1e-4 * float(b.abs().max()))


def test_bad_shapes_and_dtypes_are_refused():
    from psimap.render.native import instance_distribution as fused

    dot, terms, coef, pt, _ = inputs(8, 4, seed=1)
    with pytest.raises(ValueError, match="float64"):
        fused(dot, terms.float(), coef, pt, 0.1)
    with pytest.raises(ValueError, match="float64"):
        fused(dot, terms, coef[:, :3], pt, 0.1)
    with pytest.raises(ValueError, match="p_thing"):
        fused(dot, terms, coef, pt[:5], 0.1)
    with pytest.raises(ValueError, match="native kernel"):
        instance_distribution(dot.double(), terms, coef, pt.double(), 0.1, backend="native")


@pytest.mark.parametrize("q", [1, 5, 16, 17, 33, 93])
def test_native_affinity_matches_the_reference_on_every_instruction_set(q):
    """instance_affinity (the distribution kernel's affinity before its softmax) against
    sigmoid(dot) exp(-min(m2, cap) / 2) in float64 on m2 rounded to float32: within 2e-6 (values in
    [0, 1]) on every instruction set, past the cap and at m2 = 0 included; InstanceQueries.affinity
    dispatches to it and equals affinity_reference to float rounding."""
    from psimap.render import _native
    from psimap.render.native import instance_affinity

    dot, terms, coef, _, _ = inputs(150, q, seed=q + 7)
    m2 = (terms @ coef.T).float().double().clamp_max(MAX_MAHALANOBIS2)
    ref = torch.sigmoid(dot.double()) * torch.exp(-0.5 * m2)
    # surfel 1 at m2 = 0 from every query; query 0 past the cap on every other surfel
    assert float(ref[1].min()) > 0.0 and float(ref[torch.arange(150) != 1, 0].max()) < 1e-30
    try:
        for isa in _native.available_pixel_kernels():
            _native.use_pixel_kernels(isa)
            got = instance_affinity(dot, terms, coef)
            assert got.dtype == torch.float32 and got.shape == (150, q)
            torch.testing.assert_close(got.double(), ref, rtol=0.0, atol=2e-6, msg=f"{isa}: affinity")
    finally:
        _native.use_pixel_kernels("")
    g = torch.Generator().manual_seed(q)
    queries = InstanceQueries(torch.randn(q, 16, generator=g), torch.randn(q, 3, generator=g),
                              0.5 * torch.eye(3).expand(q, 3, 3), generator=g)
    feat, pos = torch.randn(300, 16, generator=g), torch.randn(300, 3, generator=g)
    a, b = queries.affinity(feat, pos), queries.affinity_reference(feat, pos).detach()
    torch.testing.assert_close(a, b, rtol=0.0, atol=2e-6)
    assert float(b.max()) > 0.1
    with pytest.raises(ValueError, match="instance_affinity"):
        instance_affinity(dot.double(), terms, coef)
