"""Scenes, oracles and tolerances shared by the renderer backends' parity tests
(tests/test_render_native.py, tests/test_render_cuda.py); the tolerance policy is described at the
top of tests/test_render_native.py."""
from __future__ import annotations

import math
import os

import torch

from psimap.render import project_surfels

OUTPUTS = ("rgb", "alpha", "depth", "median_depth", "normal", "distortion", "features")
W, H = 64, 48
NEAR, FAR = 0.2, 1000.0
BAND = 1e-4


def fresh_seed() -> int:
    """A new seed every run; PSIMAP_TEST_SEED=<seed> replays a failure."""
    if os.environ.get("PSIMAP_TEST_SEED"):
        return int(os.environ["PSIMAP_TEST_SEED"])
    return int.from_bytes(os.urandom(4), "little")


def camera(f=55.0):
    K = torch.tensor([[f, 0, W / 2 - 0.5], [0, f, H / 2 - 0.5], [0, 0, 1]], dtype=torch.float64)
    return torch.eye(4, dtype=torch.float64), K


def random_scene(n, seed, channels=6, opac=(0.05, 0.99), size=(0.02, 0.35), tilt=1.2):
    """n surfels in front of the camera, some large and opaque (the 1e-4 stop fires), some faint."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    means = (r(n, 3) * 2 - 1) * torch.tensor([1.1, 0.8, 0.6], dtype=torch.float64)
    means[:, 2] += 2.5
    axes = torch.randn(n, 3, generator=g, dtype=torch.float64)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    ang = r(n, 1) * tilt
    quats = torch.cat([torch.cos(ang / 2), axes * torch.sin(ang / 2)], -1)
    scales = size[0] + (size[1] - size[0]) * r(n, 2)
    opacities = opac[0] + (opac[1] - opac[0]) * r(n)
    colors = r(n, 3)
    feats = torch.randn(n, channels, generator=g, dtype=torch.float64)
    # Round to float32 once: both backends then see exactly the same numbers.
    return [t.float().double() for t in (means, quats, scales, opacities, colors, feats)]


def boundary_pixels(scene, viewmat, K, topk, band=BAND, geometric=True) -> torch.Tensor:
    """[H, W] bool: pixels where some surfel evaluation is within `band` of a cutoff (see top).
    geometric=False: only the cutoffs that depend on exp() (alpha, transmittance, G3-vs-G2, Top-K),
    for float32-vs-float32 comparisons where + - * / are bit-identical in both backends."""
    m, q, s, o, c, f = scene
    proj = project_surfels(m, q, s, o, viewmat, K, W, H, NEAR, FAR)
    order = [int(i) for i in torch.argsort(proj.depth_key, stable=True) if proj.valid[i]]
    flag = torch.zeros(H * W, dtype=torch.bool)
    if not order:
        return flag.reshape(H, W)
    idx = torch.tensor(order)
    T = proj.T[idx].detach()
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                            indexing="ij")
    x, y = xs.reshape(-1, 1), ys.reshape(-1, 1)
    hx = x[..., None] * T[None, :, 2, :] - T[None, :, 0, :]            # [P, N, 3]
    hy = y[..., None] * T[None, :, 2, :] - T[None, :, 1, :]
    p = torch.linalg.cross(hx, hy)
    sin = p[..., 2].abs() / (hx.norm(dim=-1) * hy.norm(dim=-1))
    hit = sin > 1e-10
    p2 = torch.where(hit, p[..., 2], torch.ones_like(sin))
    u, v = p[..., 0] / p2, p[..., 1] / p2
    rho3 = u * u + v * v
    z3 = T[None, :, 2, 0] * u + T[None, :, 2, 1] * v + T[None, :, 2, 2]
    valid3 = hit & (rho3 <= 9) & (z3 > NEAR)
    cen = proj.center[idx].detach()
    rho2 = (x - cen[None, :, 0]) ** 2 + (y - cen[None, :, 1]) ** 2
    lp = math.log(255.0)
    valid2 = rho2 <= lp
    g3 = torch.where(valid3, torch.exp(-0.5 * rho3), torch.zeros_like(rho3))
    g2 = torch.where(valid2, torch.exp(-rho2), torch.zeros_like(rho2))
    g = torch.maximum(g3, g2)
    oG = o[idx].detach()[None] * g
    alpha = oG.clamp(max=0.99)
    near_cut = (valid3 & valid2 & ((g3 - g2).abs() <= band * g)
                | ((oG - 1 / 255).abs() < band / 255)
                | ((oG - 0.99).abs() < band))
    if geometric:
        near_cut |= ((sin < 1e-5) & (rho2 < 4 * lp)
                     | hit & ((rho3 - 9).abs() < 9 * band) & (z3 > NEAR)
                     | hit & (rho3 <= 9) & ((z3 - NEAR).abs() < band * NEAR)
                     | ((rho2 - lp).abs() < band * lp))
    keep = alpha >= 1 / 255
    a = torch.where(keep, alpha, torch.zeros_like(alpha))
    t_incl = torch.cumprod(1 - a, -1)
    t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], -1)
    reached = t_excl >= 1e-4 * (1 - band)
    near_cut |= keep & ((t_incl - 1e-4).abs() < band * 1e-4)
    blended = keep & (t_incl >= 1e-4)
    near_cut |= blended & ((t_excl - 0.5).abs() < band)
    flag = (near_cut & reached).any(-1)
    if topk is not None and f.shape[1]:
        w = torch.where(blended, a * t_excl, torch.zeros_like(a))
        ws = torch.sort(w, -1, descending=True).values
        if ws.shape[1] > topk:
            kth, nxt = ws[:, topk - 1], ws[:, topk]
            flag |= (nxt > 0) & ((kth - nxt) <= band * kth)
    return flag.reshape(H, W)


def assert_forward_close(ref, nat, keep, msg, ref32=None):
    """Per element 1e-5 relative (floor 1e-5 of the output's scale), plus, against the float64
    oracle, 2x the float32 reference's own error: under a rotated camera the float32 stage 1 (shared
    by both float32 backends) already rounds the camera-frame surfels before native sees them."""
    # The one-pass distortion is a difference of O(1) NDC-depth moments: a float32 reference
    # resolves it only to a few ulps of 1 (native accumulates it in double).
    dist_floor = 5e-7 if ref.distortion.dtype == torch.float32 else 0.0
    for k in OUTPUTS:
        a, b = getattr(ref, k).detach(), getattr(nat, k).detach().double()
        assert b.shape == a.shape, (k, msg)
        assert bool(torch.isfinite(b).all()), f"{k}: non-finite / unwritten pixels ({msg})"
        if a.numel() == 0:
            continue
        m = keep if a.dim() == 2 else keep[..., None].expand_as(a)
        a32 = None if ref32 is None else getattr(ref32, k).detach().double()[m]
        a, b = a[m], b[m]
        scale = float(a.abs().max()) if a.numel() else 0.0
        tol = 1e-5 * a.abs() + 1e-5 * scale + (dist_floor if k == "distortion" else 0.0)
        if a32 is not None:
            tol = tol + 2 * (a32 - a).abs()
        bad = (a - b).abs() > tol
        assert not bool(bad.any()), (f"{k}: {int(bad.sum())} values differ, max |diff| "
                                     f"{float((a - b).abs().max()):.3g} (scale {scale:.3g}; {msg})")


def hard_scene(name):
    ang = math.pi / 2
    edge_on = [math.cos(ang / 2), 0.0, math.sin(ang / 2), 0.0]
    cases = {
        "edge_on": dict(means=[[0, 0, 2.0], [0.2, 0.1, 2.5]], quats=[edge_on, edge_on]),
        "tiny_scale": dict(means=[[0, 0, 2.0], [0.1, 0, 2.0]], scales=[[1e-8, 1e-8], [1e-8, 0.2]]),
        "huge_scale": dict(means=[[0, 0, 2.0], [0.1, 0, 3.0]], scales=[[1e3, 1e3], [1e3, 0.1]]),
        "opacity_0_and_1": dict(means=[[0, 0, 2.0], [0.1, 0, 2.5], [0, 0.1, 3.0]], opacities=[0.0, 1.0, 1.0]),
        "coincident": dict(means=[[0, 0, 2.0]] * 4),
        "near_plane": dict(means=[[0, 0, 0.2], [0, 0, 0.2000001], [0.1, 0, 0.25], [0, 0, 0.21]],
                           scales=[[0.3, 0.3], [0.3, 0.3], [0.5, 0.5], [0.01, 0.01]]),
        "all_culled": dict(means=[[0, 0, -1.0], [0, 0, 0.1], [0, 0, 2000.0], [50.0, 0, 2.0]]),
        "empty": dict(means=torch.zeros(0, 3)),
    }
    case = cases[name]
    m = torch.as_tensor(case["means"], dtype=torch.float64).reshape(-1, 3)
    n = m.shape[0]
    q = torch.as_tensor(case.get("quats", [[1.0, 0, 0, 0]] * n), dtype=torch.float64).reshape(n, 4)
    s = torch.as_tensor(case.get("scales", [[0.3, 0.3]] * n), dtype=torch.float64).reshape(n, 2)
    o = torch.as_tensor(case.get("opacities", [0.8] * n), dtype=torch.float64).reshape(n)
    g = torch.Generator().manual_seed(7)
    c = torch.rand(n, 3, generator=g, dtype=torch.float64)
    f = torch.randn(n, 5, generator=g, dtype=torch.float64)
    return [t.float().double() for t in (m, q, s, o, c, f)]
