"""The torch reference rasterizer (psimap/render/reference.py) against the math of SPEC.md."""
from __future__ import annotations

import math

import pytest
import torch
from posed import random_c2w, to_world, viewmat as viewmat_of

from psimap import PsimapError
from psimap.render import project_surfels, rasterize
from psimap.transforms import quat_to_rotmat_torch

W, H = 32, 24
OUTPUTS = ("rgb", "alpha", "depth", "median_depth", "normal", "distortion", "features")


def camera(f=30.0, dtype=torch.float64):
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]], dtype=dtype)
    return torch.eye(4, dtype=dtype), K


def quat_axis_angle(axis, angle):
    axis = torch.as_tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    return torch.cat([torch.tensor([math.cos(angle / 2)], dtype=torch.float64), axis * math.sin(angle / 2)])


def surfels(means, quats=None, scales=None, opacities=None, colors=None, dtype=torch.float64):
    means = torch.as_tensor(means, dtype=dtype).reshape(-1, 3)
    n = means.shape[0]
    quats = torch.tensor([[1.0, 0, 0, 0]] * n, dtype=dtype) if quats is None else torch.as_tensor(quats, dtype=dtype)
    scales = torch.full((n, 2), 0.3, dtype=dtype) if scales is None else torch.as_tensor(scales, dtype=dtype)
    opacities = torch.full((n,), 0.8, dtype=dtype) if opacities is None else torch.as_tensor(opacities, dtype=dtype)
    colors = torch.rand(n, 3, dtype=dtype) if colors is None else torch.as_tensor(colors, dtype=dtype)
    return means, quats.reshape(n, 4), scales.reshape(n, 2), opacities.reshape(n), colors.reshape(n, 3)


def random_scene(n, seed, dtype=torch.float64, depth=2.5, spread=0.6, size=(0.15, 0.3), opac=(0.3, 0.75)):
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1
    means = means * torch.tensor([spread, spread * 0.75, 0.3], dtype=dtype) + torch.tensor([0, 0, depth], dtype=dtype)
    # Mostly camera-facing, tilted up to ~40 degrees, so every surfel is in the smooth 3D regime.
    axes = torch.randn(n, 3, generator=g, dtype=dtype)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    ang = torch.rand(n, 1, generator=g, dtype=dtype) * 0.7
    quats = torch.cat([torch.cos(ang / 2), axes * torch.sin(ang / 2)], dim=-1)
    scales = size[0] + (size[1] - size[0]) * torch.rand(n, 2, generator=g, dtype=dtype)
    opacities = opac[0] + (opac[1] - opac[0]) * torch.rand(n, generator=g, dtype=dtype)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    feats = torch.randn(n, 4, generator=g, dtype=dtype)
    return means, quats, scales, opacities, colors, feats


def all_finite(out):
    return all(bool(torch.isfinite(getattr(out, k)).all()) for k in OUTPUTS)


# ---------------------------------------------------------------- analytic cases

def test_single_facing_surfel_centre_pixel():
    viewmat, K = camera()
    m, q, s, o, c = surfels([0.0, 0.0, 2.0], opacities=[0.7], colors=[[0.2, 0.4, 0.6]])
    out = rasterize(m, q, s, o, c, viewmat, K, W, H)
    cx, cy = W // 2, H // 2
    assert out.alpha[cy, cx].item() == pytest.approx(0.7, abs=1e-12)
    assert out.depth[cy, cx].item() == pytest.approx(2.0, abs=1e-12)
    assert out.median_depth[cy, cx].item() == pytest.approx(2.0, abs=1e-12)
    assert torch.allclose(out.rgb[cy, cx], 0.7 * torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64))
    # Normal faces the camera (-view direction = -z), weighted by the blending weight.
    assert torch.allclose(out.normal[cy, cx], torch.tensor([0, 0, -0.7], dtype=torch.float64), atol=1e-12)
    assert out.distortion.abs().max().item() < 1e-15          # one surfel per ray: no distortion
    # Gaussian falloff: one pixel right is 2 cm on the plane at depth 2 (f = 30): rho = (x z / f / s)^2.
    u = 1 * 2.0 / 30.0 / 0.3
    assert out.alpha[cy, cx + 1].item() == pytest.approx(0.7 * math.exp(-0.5 * u * u), rel=1e-9)


def test_tilted_surfel_hit_depth_and_falloff_are_exact():
    """Per-pixel depth is the ray-plane hit (not the centre depth), alpha the Gaussian at (u, v)."""
    viewmat, K = camera()
    quat = quat_axis_angle([0.3, 1.0, 0.2], 0.9)
    mean = torch.tensor([0.05, -0.03, 2.2], dtype=torch.float64)
    scale = torch.tensor([0.5, 0.35], dtype=torch.float64)
    m, q, s, o, c = surfels(mean, quats=quat, scales=scale, opacities=[0.6])
    out = rasterize(m, q, s, o, c, viewmat, K, W, H)
    R = quat_to_rotmat_torch(quat[None])[0]
    tu, tv, n = R[:, 0], R[:, 1], R[:, 2]
    checked = 0
    for py in range(0, H, 3):
        for px in range(0, W, 3):
            ray = torch.linalg.solve(K, torch.tensor([px, py, 1.0], dtype=torch.float64))
            t = (n @ mean) / (n @ ray)
            hit = t * ray
            u, v = (hit - mean) @ tu / scale[0], (hit - mean) @ tv / scale[1]
            rho = (u * u + v * v).item()
            alpha = 0.6 * math.exp(-0.5 * rho)
            if rho < 8.0 and alpha > 2 / 255:
                assert out.depth[py, px].item() == pytest.approx(hit[2].item(), rel=1e-9)
                assert out.alpha[py, px].item() == pytest.approx(alpha, rel=1e-9)
                checked += 1
    assert checked > 20


def test_wall_of_surfels_gives_planar_depth():
    viewmat, K = camera()
    # A dense grid on the tilted plane z = 2 + 0.4 x, surfels lying in it.
    normal = torch.tensor([-0.4, 0.0, 1.0], dtype=torch.float64)
    normal = normal / normal.norm()
    axis = torch.linalg.cross(torch.tensor([0, 0, 1.0], dtype=torch.float64), normal)
    quat = quat_axis_angle(axis, math.acos(normal[2].item()))
    xs, ys = torch.meshgrid(torch.linspace(-1.6, 1.6, 17, dtype=torch.float64),
                            torch.linspace(-1.2, 1.2, 13, dtype=torch.float64), indexing="ij")
    means = torch.stack([xs.flatten(), ys.flatten(), 2 + 0.4 * xs.flatten()], -1)
    n = means.shape[0]
    m, q, s, o, c = surfels(means, quats=quat.expand(n, 4), scales=torch.full((n, 2), 0.2),
                            opacities=torch.full((n,), 0.9))
    out = rasterize(m, q, s, o, c, viewmat, K, W, H)
    pys, pxs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    dx = (pxs - W / 2) / 30.0
    # Ray (dx, dy, 1) t meets z = 2 + 0.4 x at t = 2 / (1 - 0.4 dx).
    plane = 2.0 / (1 - 0.4 * dx)
    assert out.alpha.min().item() > 0.99
    assert (out.depth - plane).abs().max().item() < 1e-9
    assert (out.median_depth - plane).abs().max().item() < 1e-9
    assert out.distortion.max().item() < 1e-12               # all hits on one plane


@pytest.mark.parametrize("o_front", [0.6, 0.3])
def test_two_surfels_blend_in_depth_order(o_front):
    viewmat, K = camera()
    near, far = 0.2, 1000.0
    cf, cb = [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]
    # The back surfel comes first in the arrays: order must come from depth, not index.
    m, q, s, o, c = surfels([[0, 0, 3.0], [0, 0, 2.0]], opacities=[0.8, o_front], colors=[cb, cf])
    feats = torch.tensor([[0.0, 1.0], [1.0, 0.0]], dtype=torch.float64)
    out = rasterize(m, q, s, o, c, viewmat, K, W, H, features=feats, near=near, far=far)
    y, x = H // 2, W // 2
    w1, w2 = o_front, (1 - o_front) * 0.8
    expect_rgb = torch.tensor([w1, 0, w2], dtype=torch.float64)
    assert torch.allclose(out.rgb[y, x], expect_rgb, atol=1e-12)
    assert out.alpha[y, x].item() == pytest.approx(w1 + w2, abs=1e-12)
    assert out.depth[y, x].item() == pytest.approx((2 * w1 + 3 * w2) / (w1 + w2), abs=1e-12)
    # Median: transmittance before the back surfel is 1 - o_front; it is the median iff > 0.5.
    assert out.median_depth[y, x].item() == pytest.approx(2.0 if o_front >= 0.5 else 3.0, abs=1e-12)
    ndc = lambda d: far * (d - near) / ((far - near) * d)  # noqa: E731
    assert out.distortion[y, x].item() == pytest.approx(w1 * w2 * (ndc(3.0) - ndc(2.0)) ** 2, rel=1e-9)
    assert torch.allclose(out.features[y, x], torch.tensor([w1, w2], dtype=torch.float64), atol=1e-12)


@pytest.mark.parametrize("z", [-2.0, 0.1, 1500.0])
def test_behind_camera_near_or_beyond_far_contributes_nothing(z):
    viewmat, K = camera()
    m, q, s, o, c = surfels([[0, 0, z], [0.3, 0, 2.0]], scales=[[0.5, 0.5], [0.05, 0.05]])
    both = rasterize(m, q, s, o, c, viewmat, K, W, H)
    alone = rasterize(m[1:], q[1:], s[1:], o[1:], c[1:], viewmat, K, W, H)
    assert both.stats["culled"] == 1
    for k in OUTPUTS:
        assert torch.equal(getattr(both, k), getattr(alone, k)), k


def test_background_fills_transmittance():
    viewmat, K = camera()
    m, q, s, o, c = surfels([0, 0, 2.0], opacities=[0.5], colors=[[1.0, 1.0, 1.0]])
    bg = torch.tensor([0.0, 1.0, 0.25], dtype=torch.float64)
    out = rasterize(m, q, s, o, c, viewmat, K, W, H, background=bg)
    assert torch.allclose(out.rgb[H // 2, W // 2], torch.tensor([0.5, 1.0, 0.625], dtype=torch.float64))
    assert torch.allclose(out.rgb[0, 0], bg)                 # untouched pixel
    assert out.depth[0, 0].item() == 0.0 and out.median_depth[0, 0].item() == 0.0


# ---------------------------------------------------------------- the sequential rule

def sequential_pixel(proj, order, opac, colors, feats, x, y, near, far, topk):
    """SPEC.md stage 3 written as the literal sequential loop, for one pixel (float64)."""
    T_acc, rgb, dnum, med = 1.0, torch.zeros(3, dtype=torch.float64), 0.0, 0.0
    A = D = D2 = dist = 0.0
    weights = []
    r_lp2 = math.log(255.0)
    for i in order:
        T = proj.T[i]
        hx = x * T[2] - T[0]
        hy = y * T[2] - T[1]
        p = torch.linalg.cross(hx, hy)
        g3 = 0.0
        z3 = None
        if abs(p[2]) > 1e-10 * hx.norm() * hy.norm():
            u, v = p[0] / p[2], p[1] / p[2]
            rho3 = float(u * u + v * v)
            z3 = float(T[2] @ torch.stack([u, v, torch.ones_like(u)]))
            if rho3 <= 9 and z3 > near:
                g3 = math.exp(-rho3 / 2)
            else:
                z3 = None
        rho2 = float((x - proj.center[i, 0]) ** 2 + (y - proj.center[i, 1]) ** 2)
        g2 = math.exp(-rho2) if rho2 <= r_lp2 else 0.0
        if z3 is not None and g3 >= g2:
            g, d = g3, z3
        else:
            g, d = g2, float(proj.depth_key[i])
        alpha = min(0.99, float(opac[i]) * g)
        if alpha < 1 / 255:
            continue
        if T_acc * (1 - alpha) < 1e-4:
            break
        w = alpha * T_acc
        if T_acc > 0.5:
            med = d
        rgb += w * colors[i]
        dnum += w * d
        m = far * (d - near) / ((far - near) * d)
        dist += w * (m * m * A + D2 - 2 * m * D)
        A, D, D2 = A + w, D + w * m, D2 + w * m * m
        weights.append((w, i))
        T_acc *= 1 - alpha
    top = sorted(weights, key=lambda t: -t[0])[: (topk or len(weights))]   # stable: earlier wins ties
    feat = sum((w * feats[i] for w, i in top), torch.zeros(feats.shape[1], dtype=torch.float64))
    return rgb, 1 - T_acc, dnum, med, dist, feat


@pytest.mark.parametrize("topk", [None, 2])
def test_vectorised_compositing_equals_the_sequential_loop(topk):
    """Many overlapping, some opaque (the 1e-4 stop fires), some faint (the 1/255 skip fires)."""
    viewmat, K = camera()
    near, far = 0.2, 1000.0
    m, q, s, o, c, f = random_scene(60, seed=3, opac=(0.002, 0.99), size=(0.1, 0.5))
    o[:10] = 0.99
    proj = project_surfels(m, q, s, o, viewmat, K, W, H, near, far)
    order = [int(i) for i in torch.argsort(proj.depth_key, stable=True) if proj.valid[i]]
    out = rasterize(m, q, s, o, c, viewmat, K, W, H, features=f, topk=topk, near=near, far=far)
    g = torch.Generator().manual_seed(0)
    stopped = 0
    for _ in range(40):
        x, y = int(torch.randint(0, W, (1,), generator=g)), int(torch.randint(0, H, (1,), generator=g))
        rgb, alpha, dnum, med, dist, feat = sequential_pixel(proj, order, o, c, f, x, y, near, far, topk)
        stopped += alpha > 0.999
        assert torch.allclose(out.rgb[y, x], rgb, atol=1e-10)
        assert out.alpha[y, x].item() == pytest.approx(alpha, abs=1e-10)
        assert (out.depth[y, x] * out.alpha[y, x]).item() == pytest.approx(dnum, abs=1e-9)
        assert out.median_depth[y, x].item() == pytest.approx(med, abs=1e-10)
        assert out.distortion[y, x].item() == pytest.approx(dist, abs=1e-10)
        assert torch.allclose(out.features[y, x], feat, atol=1e-10)
    assert stopped > 5                                        # the stop rule was exercised


@pytest.mark.parametrize("pose_seed", [0, 1, 2])
def test_moving_scene_and_camera_together_changes_no_pixel(pose_seed):
    """Surfels given in the camera frame, rendered by the identity camera, and the same surfels
    moved into the world with a random rigid camera: every output (normals are camera-frame) is the
    same. The analytic tests above all use the identity camera, where R and R^T cannot be told apart."""
    _, K = camera()
    m, q, s, o, c, f = random_scene(60, seed=20 + pose_seed, size=(0.05, 0.4))
    q = q / q.norm(dim=-1, keepdim=True)
    ident = rasterize(m, q, s, o, c, torch.eye(4, dtype=torch.float64), K, W, H, features=f, topk=3)
    c2w = random_c2w(pose_seed)
    mw, qw = to_world(c2w, m, q)
    posed = rasterize(mw, qw, s, o, c, viewmat_of(c2w), K, W, H, features=f, topk=3)
    assert float(ident.alpha.max()) > 0.9 and float(ident.normal[..., 0].abs().max()) > 0.1
    for k in OUTPUTS:
        assert torch.allclose(getattr(posed, k), getattr(ident, k), atol=1e-9, rtol=0), k
    assert posed.stats["tile_pairs"] == ident.stats["tile_pairs"]


# ---------------------------------------------------------------- gradients

GRAD_INPUTS = ["means", "quats", "scales", "opacities", "colors", "features"]


@pytest.mark.parametrize("wrt", GRAD_INPUTS)
@pytest.mark.parametrize("topk", [None, 2])
def test_gradcheck(wrt, topk):
    _, K = camera()
    m, q, s, o, c, f = random_scene(5, seed=11)
    c2w = random_c2w(11)                      # a rigid camera: gradients through the rotation too
    m, q = to_world(c2w, m, q)
    viewmat = viewmat_of(c2w)
    inputs = dict(means=m, quats=q, scales=s, opacities=o, colors=c, features=f)

    def fn(x):
        kw = dict(inputs)
        kw[wrt] = x
        out = rasterize(kw["means"], kw["quats"], kw["scales"], kw["opacities"], kw["colors"], viewmat, K,
                        W, H, features=kw["features"], topk=topk)
        return torch.cat([getattr(out, k).reshape(-1) for k in OUTPUTS])

    x = inputs[wrt].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(fn, (x,), eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)


def test_topk_gradient_reaches_unselected_front_surfel():
    """Top-K keeps only the back surfel's features, but the front opacity still gets a gradient via T."""
    viewmat, K = camera()
    m, q, s, o, c = surfels([[0, 0, 2.0], [0, 0, 3.0]], opacities=[0.3, 0.9])
    o.requires_grad_(True)
    f = torch.tensor([[1.0], [2.0]], dtype=torch.float64)
    out = rasterize(m, q, s, o, c, viewmat, K, W, H, features=f, topk=1)
    y, x = H // 2, W // 2
    assert out.features[y, x, 0].item() == pytest.approx(0.7 * 0.9 * 2.0, abs=1e-12)   # w_back > w_front
    (g,) = torch.autograd.grad(out.features[y, x, 0], o)
    assert g[0].item() == pytest.approx(-0.9 * 2.0, abs=1e-12)
    assert g[1].item() == pytest.approx(0.7 * 2.0, abs=1e-12)


def test_precise_and_circle_tiles_give_identical_images_and_gradients():
    viewmat, K = camera()
    m, q, s, o, c, f = random_scene(40, seed=5, size=(0.02, 0.4))
    leaves = [t.clone().requires_grad_(True) for t in (m, q, s, o, c, f)]
    res = {}
    for tiles in ("precise", "circle"):
        out = rasterize(*leaves[:5], viewmat, K, W, H, features=leaves[5], topk=3, tiles=tiles)
        loss = sum((getattr(out, k) * (i + 1)).sum() for i, k in enumerate(OUTPUTS))
        res[tiles] = (out, torch.autograd.grad(loss, leaves))
    (a, ga), (b, gb) = res["precise"], res["circle"]
    for k in OUTPUTS:
        assert torch.allclose(getattr(a, k), getattr(b, k), atol=1e-12, rtol=0), k
    for x, y in zip(ga, gb):
        assert torch.allclose(x, y, atol=1e-9, rtol=1e-9)
    assert a.stats["tile_pairs"] < b.stats["tile_pairs"]
    assert a.stats["evaluated"] < b.stats["evaluated"]


def test_boxes_are_nested_and_cover_every_contributing_pixel():
    viewmat, K = camera()
    m, q, s, o, c, _ = random_scene(30, seed=8, size=(0.01, 0.6))
    o = torch.full_like(o, 0.99)
    proj = project_surfels(m, q, s, o, viewmat, K, W, H)
    bp, bc = proj.box_precise, proj.box_circle
    ne = (bp[:, 2] > bp[:, 0]) & (bp[:, 3] > bp[:, 1])
    assert bool((bc[ne, :2] <= bp[ne, :2]).all() and (bc[ne, 2:] >= bp[ne, 2:]).all())
    assert bool(((bc[:, 2] - bc[:, 0]) * (bc[:, 3] - bc[:, 1]) >= (bp[:, 2] - bp[:, 0]) * (bp[:, 3] - bp[:, 1])).all())
    for i in range(m.shape[0]):
        out = rasterize(m[i:i + 1], q[i:i + 1], s[i:i + 1], o[i:i + 1], c[i:i + 1], viewmat, K, W, H,
                        tiles="circle")
        ys, xs = torch.nonzero(out.alpha > 0, as_tuple=True)
        x0, y0, x1, y1 = bp[i].tolist()
        assert bool(((xs >= x0) & (xs < x1) & (ys >= y0) & (ys < y1)).all()), i


def test_chunked_and_checkpointed_equals_single_chunk():
    from psimap.render.reference import rasterize_reference

    viewmat, K = camera()
    m, q, s, o, c, f = random_scene(30, seed=2)
    leaves = [t.clone().requires_grad_(True) for t in (m, q, s, o, c, f)]
    res = []
    for chunk in (1 << 24, 1 << 14, 2500):        # one chunk; several tiles per chunk; tiles split by pixels
        proj = project_surfels(*leaves[:4], viewmat, K, W, H)
        out = rasterize_reference(proj, leaves[3], leaves[4], leaves[5], W, H, topk=2, chunk_evals=chunk)
        loss = sum((getattr(out, k) ** 2).sum() for k in OUTPUTS)
        res.append((out, torch.autograd.grad(loss, leaves)))
    n_tiles = (W + 15) // 16 * ((H + 15) // 16)
    assert res[0][0].stats["chunks"] == 1 and 1 < res[1][0].stats["chunks"] < n_tiles < res[2][0].stats["chunks"]
    for other in res[1:]:
        for k in OUTPUTS:
            assert torch.allclose(getattr(res[0][0], k), getattr(other[0], k), atol=1e-12), k
        for x, y in zip(res[0][1], other[1]):
            assert torch.allclose(x, y, atol=1e-10)


# ---------------------------------------------------------------- Top-K

def test_topk_at_least_surfels_per_ray_equals_full_blending_exactly():
    viewmat, K = camera()
    m, q, s, o, c, f = random_scene(25, seed=4, spread=1.2, size=(0.05, 0.12))
    full = rasterize(m, q, s, o, c, viewmat, K, W, H, features=f)
    # Surfels contributing to each pixel, counted by rendering each one alone.
    per_ray = sum((rasterize(m[i:i + 1], q[i:i + 1], s[i:i + 1], o[i:i + 1], c[i:i + 1], viewmat, K, W, H).alpha
                   > 0).long() for i in range(m.shape[0]))
    k_max = int(per_ray.max())
    assert 1 < k_max < full.stats["max_pairs_per_tile"]      # the selection path really runs
    for k in (k_max, k_max + 3, 1000):
        top = rasterize(m, q, s, o, c, viewmat, K, W, H, features=f, topk=k)
        assert torch.equal(top.features, full.features), k
    fewer = rasterize(m, q, s, o, c, viewmat, K, W, H, features=f, topk=1)
    assert not torch.equal(fewer.features, full.features)
    assert torch.equal(fewer.rgb, full.rgb) and torch.equal(fewer.depth, full.depth)  # only features change


def test_topk_ties_keep_the_front_surfel():
    viewmat, K = camera()
    # o_front = 0.5, o_back = 1 (clamped to 0.99): w = 0.5 and 0.495, the front surfel is kept.
    m, q, s, o, c = surfels([[0, 0, 2.0], [0, 0, 3.0]], opacities=[0.5, 1.0])
    f = torch.tensor([[1.0], [10.0]], dtype=torch.float64)
    out = rasterize(m, q, s, o, c, viewmat, K, W, H, features=f, topk=1)
    assert out.features[H // 2, W // 2, 0].item() == pytest.approx(0.5, abs=1e-12)
    # Equal weights (0.25 = 0.25 * 1, 0.75 * 1/3): the earlier surfel wins the tie.
    m, q, s, o, c = surfels([[0, 0, 2.0], [0, 0, 3.0]], opacities=[0.25, 1.0 / 3.0])
    out = rasterize(m, q, s, o, c, viewmat, K, W, H, features=f, topk=1)
    assert out.features[H // 2, W // 2, 0].item() == pytest.approx(0.25, abs=1e-12)


# ---------------------------------------------------------------- hard cases

def hard_case(name):
    edge_on = quat_axis_angle([0, 1.0, 0], math.pi / 2)     # normal along x: tangent plane holds the ray
    cases = {
        "edge_on": dict(means=[[0, 0, 2.0], [0.2, 0.1, 2.5]], quats=torch.stack([edge_on, edge_on])),
        "tiny_scale": dict(means=[[0, 0, 2.0], [0.1, 0, 2.0]], scales=[[1e-8, 1e-8], [1e-8, 0.2]]),
        "huge_scale": dict(means=[[0, 0, 2.0], [0.1, 0, 3.0]], scales=[[1e3, 1e3], [1e3, 0.1]]),
        "opacity_0_and_1": dict(means=[[0, 0, 2.0], [0.3, 0, 2.5], [-0.3, 0, 3.0]], opacities=[0.0, 1.0, 1.0],
                                scales=[[0.3, 0.3], [0.05, 0.05], [0.05, 0.05]]),
        "coincident": dict(means=[[0, 0, 2.0]] * 4),
        "near_plane": dict(means=[[0, 0, 0.2], [0, 0, 0.2000001], [0.1, 0, 0.25], [0, 0, 0.21]],
                           scales=[[0.3, 0.3], [0.3, 0.3], [0.5, 0.5], [0.01, 0.01]]),
        "all_culled": dict(means=[[0, 0, -1.0], [0, 0, 0.1], [0, 0, 2000.0], [50.0, 0, 2.0]]),
        "empty": dict(means=torch.zeros(0, 3)),
    }
    return cases[name]


@pytest.mark.parametrize("name", ["edge_on", "tiny_scale", "huge_scale", "opacity_0_and_1", "coincident",
                                  "near_plane", "all_culled", "empty"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_hard_cases_are_finite_in_outputs_and_gradients(name, dtype):
    viewmat, K = camera(dtype=dtype)
    case = hard_case(name)
    m, q, s, o, c = surfels(case["means"], quats=case.get("quats"), scales=case.get("scales"),
                            opacities=case.get("opacities"), dtype=dtype)
    f = torch.randn(m.shape[0], 5, dtype=dtype)
    leaves = [t.clone().requires_grad_(True) for t in (m, q, s, o, c, f)]
    out = rasterize(*leaves[:5], viewmat, K, W, H, features=leaves[5], topk=2)
    assert all_finite(out), name
    assert out.rgb.shape == (H, W, 3) and out.features.shape == (H, W, 5)
    # composited alpha = 1 - T, and blending stops before T falls below 1e-4
    assert float(out.alpha.detach().max()) <= 1 - 1e-4 + 1e-7 and float(out.alpha.detach().min()) >= 0
    loss = sum((getattr(out, k) * (i + 1)).sum() for i, k in enumerate(OUTPUTS))
    grads = torch.autograd.grad(loss, leaves, allow_unused=True)
    for g in grads:
        assert g is None or bool(torch.isfinite(g).all()), name
    if name == "edge_on":
        assert float(out.alpha.detach().max()) > 0.3                 # the low-pass keeps it visible...
        assert int((out.alpha > 0).sum()) < 200              # ...as a thin line, not a blow-up
    if name == "tiny_scale":
        assert float(out.alpha.detach()[H // 2, W // 2]) > 0.3       # sub-pixel surfel still covers its pixel
    if name == "opacity_0_and_1":
        assert out.stats["culled"] == 1
        assert float(out.alpha.detach().max()) == pytest.approx(0.99, abs=1e-6)  # alpha is clamped at 0.99
    if name == "coincident":
        assert float(out.alpha.detach()[H // 2, W // 2]) == pytest.approx(1 - 0.2 ** 4, abs=1e-5)
    if name in ("all_culled", "empty"):
        assert float(out.alpha.detach().abs().max()) == 0 and out.stats["tile_pairs"] == 0
    if name == "near_plane":
        assert out.stats["culled"] == 1                     # depth_key == near is culled
        assert float(out.depth.detach()[out.alpha > 0.01].min()) > 0.2   # nothing closer than near is blended


# ---------------------------------------------------------------- input validation

@pytest.mark.parametrize("field", ["means", "quats", "scales", "opacities", "colors", "features", "viewmat", "K"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_input_is_a_clear_error(field, bad):
    viewmat, K = camera()
    m, q, s, o, c, f = random_scene(3, seed=0)
    args = dict(means=m, quats=q, scales=s, opacities=o, colors=c, features=f, viewmat=viewmat, K=K)
    args[field] = args[field].clone()
    args[field].view(-1)[1] = bad
    with pytest.raises(ValueError, match=f"{field} contains 1 NaN/inf"):
        rasterize(args["means"], args["quats"], args["scales"], args["opacities"], args["colors"],
                  args["viewmat"], args["K"], W, H, features=args["features"])


def test_bad_shapes_and_options_are_clear_errors():
    viewmat, K = camera()
    m, q, s, o, c, f = random_scene(3, seed=0)
    with pytest.raises(ValueError, match=r"scales must have shape \[N, 2\]"):
        rasterize(m, q, s[:, :1], o, c, viewmat, K, W, H)
    with pytest.raises(ValueError, match=r"colors must have shape"):
        rasterize(m, q, s, o, c[:2], viewmat, K, W, H)
    with pytest.raises(ValueError, match="topk"):
        rasterize(m, q, s, o, c, viewmat, K, W, H, features=f, topk=0)
    with pytest.raises(ValueError, match="tiles"):
        rasterize(m, q, s, o, c, viewmat, K, W, H, tiles="square")
    with pytest.raises(ValueError, match="near"):
        rasterize(m, q, s, o, c, viewmat, K, W, H, near=0.0)
    with pytest.raises(ValueError, match="float32"):
        rasterize(m, q.float(), s, o, c, viewmat, K, W, H)


# ---------------------------------------------------------------- dtype / device / backend

def test_float32_matches_float64():
    viewmat, K = camera()
    scene = random_scene(40, seed=6)
    a = rasterize(*scene[:5], viewmat, K, W, H, features=scene[5])
    b = rasterize(*[t.float() for t in scene[:5]], viewmat.float(), K.float(), W, H, features=scene[5].float())
    for k in ("rgb", "alpha", "normal", "features"):
        assert torch.allclose(getattr(a, k).float(), getattr(b, k), atol=2e-4), k
    mask = a.alpha > 0.05
    assert torch.allclose(a.depth[mask].float(), b.depth[mask], rtol=1e-4)


def test_auto_backend_renders_and_native_missing_is_a_clear_error(monkeypatch):
    import sys

    viewmat, K = camera()
    scene = random_scene(10, seed=1)
    ref = rasterize(*scene[:5], viewmat, K, W, H)
    auto = rasterize(*scene[:5], viewmat, K, W, H, backend="auto")
    assert torch.allclose(ref.rgb, auto.rgb, atol=1e-5)
    # an install whose native module was never built: `import psimap.render.native` fails
    monkeypatch.setitem(sys.modules, "psimap.render.native", None)
    with pytest.raises(ImportError):
        import psimap.render.native  # noqa: F401
    auto = rasterize(*scene[:5], viewmat, K, W, H, backend="auto")      # falls back to torch
    assert auto.stats["backend"] == "reference"
    for k in OUTPUTS:
        assert torch.equal(getattr(auto, k), getattr(ref, k)), k
    with pytest.raises(PsimapError, match="native renderer backend is not available"):
        rasterize(*scene[:5], viewmat, K, W, H, backend="native")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    viewmat, K = camera()
    scene = random_scene(40, seed=6)
    a = rasterize(*scene[:5], viewmat, K, W, H, features=scene[5], topk=2)
    b = rasterize(*[t.cuda() for t in scene[:5]], viewmat.cuda(), K.cuda(), W, H, features=scene[5].cuda(), topk=2)
    for k in OUTPUTS:
        assert torch.allclose(getattr(a, k), getattr(b, k).cpu(), atol=1e-9), k


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_gradients_match_cpu():
    """Backward on the device equals backward on the CPU (float64: only summation order differs)."""
    viewmat, K = camera()
    grads = {}
    for dev in ("cpu", "cuda"):
        scene = [t.to(dev).requires_grad_(True) for t in random_scene(60, seed=7)]
        out = rasterize(*scene[:5], viewmat.to(dev), K.to(dev), W, H, features=scene[5], topk=4)
        loss = sum((getattr(out, k) * (i + 1)).sum() for i, k in enumerate(OUTPUTS))
        loss.backward()
        grads[dev] = [t.grad.cpu() for t in scene]
    for a, b in zip(grads["cpu"], grads["cuda"]):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-11)
