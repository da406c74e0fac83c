"""The panoptic field's fused per-surfel distribution (psimap/render/csrc/field_lanes.inl,
psimap.render.native.instance_distribution) against its torch form
(psimap.panoptic.queries.instance_distribution_reference).

Oracle: the reference in float64 on float32-representable inputs (the kernel computes in float32,
m2 rounded to float32 as the reference rounds it). Values of the distribution lie in [0, 1]: held
to 4e-6 absolute (measured <= 1.1e-6 over 5 seeds x 6 row lengths x 3 instruction sets); gradients
to 2e-5 of each gradient's largest magnitude (measured <= 5.5e-6: float32 sums over up to 93 queries). Row lengths cover a single lane, whole vectors and partial last vectors of every
instruction set (4, 8 and 16 lanes)."""
from __future__ import annotations

import pytest
import torch

from psimap.panoptic.queries import (MAX_MAHALANOBIS2, InstanceQueries, instance_distribution,
                                     instance_distribution_reference)
from psimap.render.api import native_available

pytestmark = pytest.mark.skipif(not native_available(), reason="native kernels not built")


@pytest.fixture(autouse=True)
def poison_outputs():
    """Every native output buffer starts as NaN, so a value the kernel leaves unwritten fails."""
    import psimap.render.native as native

    native.POISON_OUTPUTS = True
    yield
    native.POISON_OUTPUTS = False


def inputs(v: int, q: int, seed: int):
    """dot [V, Q] float32 (a few at +-60: saturated sigmoids), m2 [V, Q] float64 holding float32
    values in [0, 200] (the cap, 160, exactly in some), p_thing [V] float32, upstream w [V, Q]."""
    g = torch.Generator().manual_seed(seed)
    dot = torch.randn(v, q, generator=g) * 4
    dot[torch.rand(v, q, generator=g) < 0.03] = 60.0
    dot[torch.rand(v, q, generator=g) < 0.03] = -60.0
    m2 = torch.rand(v, q, generator=g) * 200
    m2[torch.rand(v, q, generator=g) < 0.05] = MAX_MAHALANOBIS2
    pt = torch.rand(v, generator=g)
    w = torch.randn(v, q, generator=g)
    return dot, m2.double(), pt, w


def evaluate(fn, dot, m2, pt, w, dtype):
    """(out, v_dot, v_m2, v_p_thing) of fn on leaves in `dtype` (m2 always float64)."""
    leaves = [dot.to(dtype).requires_grad_(True), m2.clone().requires_grad_(True)]
    if pt is not None:
        leaves.append(pt.to(dtype).requires_grad_(True))
    out = fn(leaves[0], leaves[1], leaves[2] if pt is not None else None, 0.1)
    grads = torch.autograd.grad((out * w.to(dtype)).sum(), leaves)
    return [out.detach().double(), *(g.double() for g in grads)]


@pytest.mark.parametrize("q", [1, 5, 16, 17, 33, 93])
@pytest.mark.parametrize("with_thing", [True, False])
def test_native_distribution_matches_the_reference_on_every_instruction_set(q, with_thing):
    from psimap.render import _native

    dot, m2, pt, w = inputs(150, q, seed=q + 100 * with_thing)
    pt = pt if with_thing else None
    ref = evaluate(instance_distribution_reference, dot, m2, pt, w, torch.float64)
    assert float(ref[0].sum(-1).max()) <= 1.0 + 1e-9
    try:
        for isa in _native.available_pixel_kernels():
            _native.use_pixel_kernels(isa)
            got = evaluate(lambda *a: instance_distribution(*a, backend="native"), dot, m2, pt, w, torch.float32)
            torch.testing.assert_close(got[0], ref[0], rtol=0.0, atol=4e-6, msg=f"{isa}: values")
            for name, a, b in zip(("dot", "m2", "p_thing"), got[1:], ref[1:]):
                torch.testing.assert_close(a, b, rtol=0.0, atol=2e-5 * float(b.abs().max()) + 1e-12,
                                           msg=f"{isa}: gradient of {name}")
            # beyond the cap the distance gets no gradient (the reference's clamp_max)
            assert float(got[2][m2 > MAX_MAHALANOBIS2].abs().max()) == 0.0
    finally:
        _native.use_pixel_kernels("")


def test_a_nan_row_stays_in_its_row():
    """A NaN input spoils its own surfel's row (as the reference's softmax does) and no other."""
    dot, m2, pt, w = inputs(40, 17, seed=3)
    clean = instance_distribution(dot, m2, pt, 0.1, backend="native")
    dot[5, 16] = float("nan")
    m2[9, 0] = float("nan")
    out = instance_distribution(dot, m2, pt, 0.1, backend="native")
    ref = instance_distribution_reference(dot, m2, pt, 0.1)
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

    dot, m2, pt, _ = inputs(8, 4, seed=1)
    with pytest.raises(ValueError, match="float64"):
        fused(dot, m2.float(), pt, 0.1)
    with pytest.raises(ValueError, match="p_thing"):
        fused(dot, m2, pt[:5], 0.1)
    with pytest.raises(ValueError, match="native kernel"):
        instance_distribution(dot.double(), m2, pt.double(), 0.1, backend="native")
