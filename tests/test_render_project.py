"""Stage 1 (project_surfels) and stage 2 (bin_surfels) of the renderer against SPEC.md."""
from __future__ import annotations

import math

import pytest
import torch
from posed import random_c2w, to_world, viewmat as viewmat_of

from psimap.render import project_surfels
from psimap.render.binning import bin_surfels
from psimap.render.project import BOX_SLACK, R_LOWPASS

W, H = 64, 48
F = 40.0


def camera(dtype=torch.float64):
    K = torch.tensor([[F, 0, 30.0], [0, F, 20.0], [0, 0, 1]], dtype=dtype)
    return torch.eye(4, dtype=dtype), K


@pytest.mark.parametrize("pose_seed", [None, 0, 1, 2])
def test_facing_surfel_quantities_and_boxes(pose_seed):
    """The same camera-frame surfel seen by the identity camera and, moved into the world with the
    camera, by rigid cameras: every stage-1 quantity is a camera-frame one and must not change."""
    viewmat, K = camera()
    means = torch.tensor([[0.1, -0.05, 2.0]], dtype=torch.float64)
    quats = torch.tensor([[0.0, 1.0, 0.0, 0.0]], dtype=torch.float64)     # 180 deg about x: normal -z
    scales = torch.tensor([[0.1, 0.05]], dtype=torch.float64)
    m, q = means, quats
    if pose_seed is not None:
        c2w = random_c2w(pose_seed)
        m, q = to_world(c2w, means, quats)
        viewmat = viewmat_of(c2w)
    p = project_surfels(m, q, scales, torch.tensor([0.5], dtype=torch.float64), viewmat, K, W, H)
    cx, cy = 30 + F * 0.1 / 2, 20 - F * 0.05 / 2
    assert torch.allclose(p.center, torch.tensor([[cx, cy]], dtype=torch.float64))
    assert p.depth_key.item() == pytest.approx(2.0, abs=1e-12) and bool(p.valid.item())
    # T maps (u, v, 1) to (x z, y z, z): column 2 is K mu_c, columns 0/1 the scaled axes.
    assert torch.allclose(p.T[0, :, 2], K @ means[0])
    assert torch.allclose(p.T[0, :, 0], torch.tensor([F * 0.1, 0, 0], dtype=torch.float64))
    assert torch.allclose(p.T[0, :, 1], torch.tensor([0, -F * 0.05, 0], dtype=torch.float64))
    assert torch.allclose(p.normal_c, torch.tensor([[0, 0, -1.0]], dtype=torch.float64))
    # Ellipse half extents 3 s f / z: 6 px and 3 px; the low-pass disk (2.35 px) is inside in x only.
    hx, hy = 3 * 0.1 * F / 2, max(3 * 0.05 * F / 2, R_LOWPASS)
    want = [math.ceil(cx - hx - BOX_SLACK), math.ceil(cy - hy - BOX_SLACK),
            math.floor(cx + hx + BOX_SLACK) + 1, math.floor(cy + hy + BOX_SLACK) + 1]
    assert p.box_precise[0].tolist() == want
    r = 3 * 0.1 * F / 2 + BOX_SLACK                                    # circle: the semi-major axis
    assert p.box_circle[0].tolist() == [math.ceil(cx - r), math.ceil(cy - r), math.floor(cx + r) + 1,
                                        math.floor(cy + r) + 1]


def test_normal_is_flipped_towards_the_camera():
    viewmat, K = camera()
    means = torch.tensor([[0, 0, 2.0], [0, 0, 2.0]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0], [0.0, 1.0, 0, 0]], dtype=torch.float64)
    p = project_surfels(means, quats, torch.full((2, 2), 0.1, dtype=torch.float64),
                        torch.full((2,), 0.5, dtype=torch.float64), viewmat, K, W, H)
    assert torch.allclose(p.normal_c, torch.tensor([[0, 0, -1.0], [0, 0, -1.0]], dtype=torch.float64))


def test_culling_and_non_finite_surfels_never_leak_nan():
    viewmat, K = camera()
    means = torch.tensor([[0, 0, 2.0], [0, 0, -1.0], [0, 0, 0.2], [0, 0, 1e4], [float("nan"), 0, 2],
                          [0, 0, 2.0], [0, 0, 2.0], [0, 0, 2.0]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 8, dtype=torch.float64)
    quats[6] = 0.0                                                      # zero quaternion
    quats[7, 2] = float("inf")
    opac = torch.tensor([0.5, 0.5, 0.5, 0.5, 0.5, 0.0, 0.5, 0.5], dtype=torch.float64)
    leaves = [t.clone().requires_grad_(True) for t in (means, quats, torch.full((8, 2), 0.1, dtype=torch.float64))]
    p = project_surfels(*leaves, opac, viewmat, K, W, H, near=0.2, far=1000.0)
    assert p.valid.tolist() == [True] + [False] * 7
    for t in (p.T, p.center, p.depth_key, p.normal_c):
        assert bool(torch.isfinite(t).all())
    assert (p.box_precise[1:] == 0).all() and (p.box_circle[1:] == 0).all()
    loss = p.T.sum() + p.center.sum() + p.normal_c.sum()
    for g in torch.autograd.grad(loss, leaves):
        assert bool(torch.isfinite(g).all())


def test_disk_crossing_the_camera_plane_gets_the_whole_image():
    viewmat, K = camera()
    quat = torch.tensor([[math.cos(0.6), 0, math.sin(0.6), 0]], dtype=torch.float64)   # tilted 69 deg
    p = project_surfels(torch.tensor([[0, 0, 1.0]], dtype=torch.float64), quat,
                        torch.tensor([[2.0, 2.0]], dtype=torch.float64), torch.tensor([0.5], dtype=torch.float64),
                        viewmat, K, W, H)
    assert p.box_precise[0].tolist() == [0, 0, W, H] and p.box_circle[0].tolist() == [0, 0, W, H]


def brute_force_bins(box, depth, width, height, tile=16):
    tx_n, ty_n = (width + tile - 1) // tile, (height + tile - 1) // tile
    lists = [[] for _ in range(tx_n * ty_n)]
    for i, (x0, y0, x1, y1) in enumerate(box.tolist()):
        if x1 <= x0 or y1 <= y0:
            continue
        for ty in range(y0 // tile, (y1 - 1) // tile + 1):
            for tx in range(x0 // tile, (x1 - 1) // tile + 1):
                lists[ty * tx_n + tx].append(i)
    return [sorted(lst, key=lambda i: (float(depth[i]), i)) for lst in lists]


def test_binning_matches_brute_force_with_depth_ties():
    g = torch.Generator().manual_seed(0)
    n = 200
    x0 = torch.randint(-5, W, (n,), generator=g)
    y0 = torch.randint(-5, H, (n,), generator=g)
    box = torch.stack([x0, y0, x0 + torch.randint(0, 40, (n,), generator=g),
                       y0 + torch.randint(0, 30, (n,), generator=g)], -1).clamp(min=0)
    box[:, 2] = box[:, 2].clamp(max=W)
    box[:, 3] = box[:, 3].clamp(max=H)
    depth = torch.randint(0, 10, (n,), generator=g).double()           # many exact ties
    bins = bin_surfels(box.int(), depth, W, H)
    want = brute_force_bins(box, depth, W, H)
    got = [bins.surfel_ids[bins.offsets[t]:bins.offsets[t + 1]].tolist() for t in range(len(want))]
    assert got == want
    assert bins.counts.sum().item() == sum(map(len, want)) == bins.surfel_ids.numel()
    assert (bins.tile_ids[:-1] <= bins.tile_ids[1:]).all()


def test_binning_nothing():
    bins = bin_surfels(torch.zeros(3, 4, dtype=torch.int32), torch.ones(3), W, H)
    assert bins.surfel_ids.numel() == 0 and bins.offsets.tolist() == [0] * (bins.tiles_x * bins.tiles_y + 1)
