"""Stage 1 in C++ (psimap.render.native.project_surfels) against its torch reference of the same
name (psimap.render.project.project_surfels): values, tile boxes, culling and gradients, on random
posed scenes with the degenerate rows mixed in (edge-on, zero scale, zero quaternion, behind the
camera, on the near plane, beyond far, zero opacity)."""
from __future__ import annotations

import pytest
import torch
from posed import random_c2w, viewmat as viewmat_of

from psimap.render import native, rasterize
from psimap.render.project import project_surfels as project_reference

project_native = native.project_surfels
W, H = 64, 48
NEAR, FAR = 0.2, 1000.0
DIFF = ("T", "center", "depth_key", "normal_c")


def posed_scene(n: int, seed: int, dtype=torch.float64):
    """n surfels in front of a random world camera plus one of each degenerate kind (first rows).
    Returns (means, quats, scales, opacities, viewmat, K)."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    cam = (r(n, 3) * 2 - 1) * torch.tensor([1.2, 0.9, 0.7], dtype=torch.float64)
    cam[:, 2] += 2.0
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = 0.02 + 0.3 * r(n, 2)
    opac = 0.05 + 0.9 * r(n)
    edge_on = torch.tensor([0.5 ** 0.5, 0.0, 0.5 ** 0.5, 0.0], dtype=torch.float64)  # normal along x
    degenerate = [
        (torch.tensor([0.0, 0.0, 2.0]), edge_on, [0.2, 0.2], 0.8),          # edge-on, on the axis
        (torch.tensor([0.1, 0.0, 2.0]), None, [0.0, 0.0], 0.8),             # zero scale
        (torch.tensor([0.0, 0.1, 2.0]), torch.zeros(4), [0.2, 0.2], 0.8),   # zero quaternion
        (torch.tensor([0.0, 0.0, -1.5]), None, [0.2, 0.2], 0.8),            # behind the camera
        (torch.tensor([0.0, 0.0, NEAR]), None, [0.2, 0.2], 0.8),            # on the near plane
        (torch.tensor([0.0, 0.0, 0.5]), None, [2.0, 2.0], 0.8),             # disk crosses z = 0
        (torch.tensor([0.0, 0.0, 2 * FAR]), None, [0.2, 0.2], 0.8),         # beyond far
        (torch.tensor([0.2, 0.2, 2.0]), None, [0.2, 0.2], 0.0),             # zero opacity
    ]
    for i, (m, q, s, o) in enumerate(degenerate):
        cam[i] = m.double()
        if q is not None:
            quats[i] = q
        scales[i] = torch.tensor(s, dtype=torch.float64)
        opac[i] = o
    c2w = random_c2w(seed)
    R, t = c2w[:3, :3], c2w[:3, 3]
    means = cam @ R.T + t
    # Quaternions are free parameters in the world: the camera rotation need not be applied to them.
    K = torch.tensor([[50.0, 0, W / 2 - 0.5], [0, 50.0, H / 2 - 0.5], [0, 0, 1]], dtype=torch.float64)
    out = [t.to(dtype) for t in (means, quats, scales, opac)]
    return (*out, viewmat_of(c2w).to(dtype), K.to(dtype))


def both(scene, weights_seed=0):
    """Project with both implementations; loss = sum of random weights * each differentiable
    output. Returns {name: (Projected, [grad means, grad quats, grad scales])}."""
    *surfels, viewmat, K = scene
    res = {}
    for name, fn in (("reference", project_reference), ("native", project_native)):
        leaves = [t.clone().requires_grad_(True) for t in surfels]
        p = fn(*leaves, viewmat, K, W, H, NEAR, FAR)
        g = torch.Generator().manual_seed(weights_seed)
        loss = sum((getattr(p, k) * torch.randn(getattr(p, k).shape, generator=g, dtype=torch.float64)
                    .to(p.T.dtype)).sum() for k in DIFF)
        grads = torch.autograd.grad(loss, leaves[:3])
        res[name] = (p, list(grads))
    return res


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_native_projection_equals_reference_in_float64(seed):
    scene = posed_scene(300, seed)
    res = both(scene, seed)
    (ref, gref), (nat, gnat) = res["reference"], res["native"]
    assert nat.valid.tolist() == ref.valid.tolist()
    # Edge-on, zero scale and a disk crossing z = 0 stay; the rest are culled (the near-plane row
    # is decided by the pose's rounding, the same way in both).
    assert bool(ref.valid[[0, 1, 5]].all()) and not bool(ref.valid[[2, 3, 6, 7]].any())
    assert nat.box_precise.tolist() == ref.box_precise.tolist()
    assert nat.box_circle.tolist() == ref.box_circle.tolist()
    for k in DIFF:
        a, b = getattr(ref, k).detach(), getattr(nat, k).detach()
        assert bool(torch.isfinite(b).all()), k
        assert float((a - b).abs().max()) <= 1e-12 * max(1.0, float(a.abs().max())), k
    for name, a, b in zip(("means", "quats", "scales"), gref, gnat):
        assert bool(torch.isfinite(b).all()), name
        assert float((a - b).abs().max()) <= 1e-10 * float(a.abs().max()), name
    # The zero quaternion's row is replaced by a harmless one: no gradient reaches it, as in torch.
    assert all(float(g[2].abs().max()) == 0.0 for g in gnat) and float(gref[0][2].abs().max()) == 0.0


@pytest.mark.parametrize("seed", [3, 4])
def test_native_projection_float32_rounds_like_the_reference(seed):
    """float32 in, float32 out: the forward is computed in float32 as torch does (same culling and
    facing decisions); gradients, computed in double, within float32 rounding of the reference."""
    scene = posed_scene(300, seed, torch.float32)
    res = both(scene, seed)
    (ref, gref), (nat, gnat) = res["reference"], res["native"]
    assert nat.T.dtype == torch.float32 and nat.valid.tolist() == ref.valid.tolist()
    assert nat.normal_c.detach().mul(ref.normal_c.detach()).sum(-1).min() > 0.99   # same facing sign
    # A box edge may move by one pixel where float32 rounding of T puts it on an integer.
    assert int((nat.box_precise - ref.box_precise).abs().max()) <= 1
    for k in DIFF:
        a, b = getattr(ref, k).detach(), getattr(nat, k).detach()
        assert float((a - b).abs().max()) <= 1e-5 * max(1.0, float(a.abs().max())), k
    for name, a, b in zip(("means", "quats", "scales"), gref, gnat):
        assert bool(torch.isfinite(b).all()), name
        rms = float(a.pow(2).mean().sqrt())
        assert float((a - b).abs().max()) <= 1e-3 * rms + 1e-4 * float(a.abs().max()), name


def test_native_projection_gradcheck():
    """The C++ backward against finite differences, independent of the torch reference."""
    *surfels, viewmat, K = posed_scene(12, 5)
    # The degenerate first rows have kinks (zero scale, zero quaternion, culling): the smooth rows.
    leaves = [t.detach()[8:].clone().requires_grad_(True) for t in surfels[:3]]
    opac = surfels[3][8:]

    def f(m, q, s):
        p = project_native(m, q, s, opac, viewmat, K, W, H, NEAR, FAR)
        return p.T, p.center, p.depth_key, p.normal_c

    assert torch.autograd.gradcheck(f, leaves, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_rasterize_uses_the_native_projection_unless_the_camera_needs_gradients(monkeypatch):
    """backend='native' projects in C++ (the torch projection is not called); a viewmat that
    requires grad goes through the torch projection so the pose still gets its gradient."""
    import psimap.render.project as project_module

    *surfels, viewmat, K = posed_scene(40, 6, torch.float32)
    colors = torch.rand(40, 3, generator=torch.Generator().manual_seed(0))
    calls = []
    real = project_module.project_surfels
    monkeypatch.setattr(project_module, "project_surfels", lambda *a, **k: calls.append(1) or real(*a, **k))
    out = rasterize(*surfels, colors, viewmat, K, W, H, backend="native")
    assert calls == [] and float(out.alpha.max()) > 0.5
    pose = viewmat.clone().requires_grad_(True)
    out = rasterize(*surfels, colors, pose, K, W, H, backend="native")
    out.rgb.sum().backward()
    assert calls == [1] and pose.grad is not None and float(pose.grad.abs().max()) > 0
    with pytest.raises(ValueError, match="camera gradients"):
        project_native(*surfels, pose, K, W, H)


def test_precise_tiles_skip_pixel_blocks_outside_the_footprint():
    """Precise tiles: a tilted, elongated splat's box is mostly empty corners; the native kernels
    only visit the 4x4 pixel blocks its footprint meets (same image as the reference, which
    tests/test_render_native.py checks), so they evaluate well under the box's pixel count.
    With circle tiles every pixel of the box is evaluated (no stop: faint surfels)."""
    n = 24
    g = torch.Generator().manual_seed(11)
    means = torch.cat([(torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * 1.2,
                       torch.full((n, 1), 2.5, dtype=torch.float64)], -1)
    ang = torch.full((n,), 0.6, dtype=torch.float64)        # about the optical axis: a diagonal splat
    quats = torch.stack([torch.cos(ang / 2), 0 * ang, 0 * ang, torch.sin(ang / 2)], -1)
    scales = torch.tensor([[0.5, 0.02]], dtype=torch.float64).expand(n, 2).contiguous()
    opac = torch.full((n,), 0.2, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    K = torch.tensor([[50.0, 0, W / 2 - 0.5], [0, 50.0, H / 2 - 0.5], [0, 0, 1]], dtype=torch.float64)
    args = [t.float() for t in (means, quats, scales, opac, colors)]
    V = torch.eye(4)
    proj = project_native(*args[:4], V, K.float(), W, H)
    evaluated, in_box = {}, {}
    for tiles in ("precise", "circle"):
        box = (proj.box_precise if tiles == "precise" else proj.box_circle).long()
        in_box[tiles] = int(((box[:, 2] - box[:, 0]) * (box[:, 3] - box[:, 1])).sum())
        out = rasterize(*args, V, K.float(), W, H, tiles=tiles, backend="native")
        evaluated[tiles] = out.stats["evaluated"]
    assert float(out.alpha.max()) > 0.3
    assert evaluated["circle"] == in_box["circle"]
    assert evaluated["precise"] < 0.75 * in_box["precise"], (evaluated, in_box)


def test_input_check_finds_one_bad_value_and_accepts_sums_that_overflow():
    """rasterize's finiteness check sums first (one pass); a sum that is not finite only sends it
    to the per-value check, so huge finite inputs still render and one inf is still named."""
    q = torch.tensor([[1.0, 0, 0, 0]] * 3)
    args = [torch.ones(3, 2), torch.full((3,), 0.5), torch.ones(3, 3), torch.eye(4), torch.eye(3), 8, 8]
    far = torch.full((3, 3), 3e38)                # finite, but their sum overflows float32
    out = rasterize(far, q, *args, backend="native")
    assert float(out.alpha.max()) == 0.0          # beyond the far plane: nothing drawn, no error
    bad = torch.zeros(3, 3)
    bad[1, 2] = float("inf")
    with pytest.raises(ValueError, match="means contains 1 NaN/inf"):
        rasterize(bad, q, *args, backend="native")
