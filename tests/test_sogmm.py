"""SOGMM prior (psimap.geometry): fit quality on known shapes, adaptivity, degenerate inputs,
determinism, surfel sampling, training-time queries, and the 4D point helpers."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from psimap import PsimapError
from psimap.geometry import (SOGMMIndex, backproject_frame, fit_sogmm, frames_to_points, geo_loss,
                             lidar_points, normal_alignment, point_to_plane, sample_surfels,
                             voxel_downsample)

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
COS10 = np.cos(np.radians(10.0))


def plane_points(n=8000, noise=0.002, seed=0, side=1.0):
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-side / 2, side / 2, (n, 2)), rng.normal(0.0, noise, n)]


def box_points(lo, hi, n, seed=0, noise=0.0):
    """Points on the 6 faces of an axis-aligned box and the face normal of each."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    ext = hi - lo
    areas = np.array([ext[1] * ext[2]] * 2 + [ext[0] * ext[2]] * 2 + [ext[0] * ext[1]] * 2)
    face = rng.choice(6, n, p=areas / areas.sum())
    axis = face // 2
    p = lo + rng.random((n, 3)) * ext
    p[np.arange(n), axis] = np.where(face % 2 == 1, hi[axis], lo[axis])
    nrm = np.zeros((n, 3))
    nrm[np.arange(n), axis] = 1.0
    return p + rng.normal(0.0, noise, (n, 1)) * nrm, nrm


def sphere_points(n=20000, seed=0):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def check_valid(g, min_points=8):
    assert np.isfinite(g.means).all() and np.isfinite(g.covs).all() and np.isfinite(g.eigvals).all()
    np.testing.assert_allclose(np.linalg.norm(g.normals, axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(g.weights.sum(), 1.0, atol=1e-9)
    assert (np.linalg.eigvalsh(g.covs) > 0).all()
    # [t0, t1, n] is a proper rotation
    R = np.concatenate([g.tangents, g.normals[:, None]], axis=1)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    assert (np.diff(g.eigvals, axis=1) <= 1e-15).all()      # descending


# ---------------------------------------------------------------------------------------------- fits


def test_plane_few_components_normals_z_residual_at_noise():
    noise = 0.002
    pts = plane_points(noise=noise)
    g = fit_sogmm(pts, max_extent=10.0, voxel=0.0)
    check_valid(g)
    assert g.K <= 4
    assert (np.abs(g.normals[:, 2]) > 0.9999).all()
    # mean |N(0, s)| = s sqrt(2/pi): the fit residual is the noise, not the model
    expected = noise * np.sqrt(2 / np.pi)
    assert 0.85 * expected < g.fit_stats["residual_mean"] < 1.15 * expected
    # default settings: more, smaller patches, all still flat
    d = fit_sogmm(pts)
    check_valid(d)
    cells = (1.0 / d.fit_stats["max_extent"]) ** 2
    assert d.K <= 4 * cells + 4
    assert (np.abs(d.normals[:, 2]) > 0.95).all()
    assert d.fit_stats["residual_mean"] <= d.fit_stats["residual_budget"]


def test_box_normals_follow_faces():
    pts, nrm = box_points([0, 0, 0], [1.0, 0.6, 0.4], 20000, noise=0.001)
    g = fit_sogmm(pts)
    check_valid(g)
    lab = g.assign(pts)
    cos = np.abs((g.normals[lab] * nrm).sum(1))
    assert (cos > COS10).mean() > 0.95
    assert g.fit_stats["residual_mean"] < g.fit_stats["residual_budget"]
    # the nearest-mean lookup used in training is right away from edges (within half a patch of
    # an edge the nearest mean may belong to the other face)
    idx = SOGMMIndex(g).nearest(torch.as_tensor(pts, dtype=torch.float32)).numpy()
    assert (np.abs((g.normals[idx] * nrm).sum(1)) > COS10).mean() > 0.85
    # choosing among 6 candidates by likelihood repairs the creases, as `assign` does
    idx6 = SOGMMIndex(g).nearest(torch.as_tensor(pts, dtype=torch.float32), candidates=6).numpy()
    assert (np.abs((g.normals[idx6] * nrm).sum(1)) > COS10).mean() > 0.95
    assert (idx6 == g.assign(pts.astype(np.float32).astype(np.float64))).mean() > 0.999


def test_sphere_components_grow_as_budget_shrinks():
    pts = sphere_points()
    ks, res = [], []
    for budget in (0.02, 0.005, 0.0015):
        g = fit_sogmm(pts, residual=budget, max_extent=10.0)
        check_valid(g)
        ks.append(g.K)
        res.append(g.fit_stats["residual_mean"])
        assert g.fit_stats["residual_mean"] <= budget
    assert ks[0] < ks[1] < ks[2] and ks[2] > 3 * ks[0]
    assert res[0] > res[1] > res[2]


def test_huge_coordinates_keep_precision():
    # UTM-like offsets: a flat patch 1e6 m from the origin is still flat
    pts = plane_points(noise=0.0005) + np.array([5.0e5, 4.0e6, 100.0])
    g = fit_sogmm(pts, max_extent=10.0, voxel=0.0)
    assert (np.abs(g.normals[:, 2]) > 0.9999).all()
    assert g.fit_stats["residual_mean"] < 0.001


@pytest.mark.skipif(not (DATA / "kitti-velodyne" / "000000.bin").exists(), reason="shared data absent")
def test_kitti_sweep():
    raw = np.fromfile(DATA / "kitti-velodyne" / "000000.bin", dtype=np.float32).reshape(-1, 4)
    pts = lidar_points(raw)
    assert pts.shape[1] == 4 and 0.0 <= pts[:, 3].min() and pts[:, 3].max() <= 1.0
    g = fit_sogmm(pts, residual=0.05)
    check_valid(g)
    assert 50 < g.K < len(pts) / 8
    assert g.fit_stats["residual_mean"] < 0.05
    # the road under the car (z ~ -1.7 m in the sensor frame, within 10 m) is horizontal
    near_ground = (np.linalg.norm(g.means[:, :2], axis=1) < 10) & (np.abs(g.means[:, 2] + 1.73) < 0.1)
    assert near_ground.sum() >= 5
    assert np.median(np.abs(g.normals[near_ground, 2])) > 0.98


# ---------------------------------------------------------------------------------- degenerate input


def test_empty_and_all_nan_inputs_raise():
    with pytest.raises(PsimapError, match="empty"):
        fit_sogmm(np.zeros((0, 3)))
    with pytest.raises(PsimapError, match="NaN"):
        fit_sogmm(np.full((10, 3), np.nan))
    with pytest.raises(PsimapError, match="shape"):
        fit_sogmm(np.zeros((10, 5)))
    with pytest.raises(PsimapError, match="intensity"):
        fit_sogmm(np.zeros((10, 3)), intensity=np.zeros(3))
    with pytest.raises(PsimapError, match="numeric"):
        fit_sogmm([["a", "b", "c"]])


def test_nan_points_dropped_with_count():
    pts = plane_points(n=2000)
    pts[::100] = np.nan
    pts[1, 2] = np.inf
    g = fit_sogmm(pts, max_extent=10.0)
    assert g.fit_stats["n_dropped_nonfinite"] == 21
    check_valid(g)
    assert (np.abs(g.normals[:, 2]) > 0.999).all()


def test_duplicates_single_point_and_two_points():
    same = np.tile([[1.0, 2.0, 3.0]], (500, 1))
    g = fit_sogmm(same)
    check_valid(g)
    assert g.K == 1 and g.counts[0] >= 1
    np.testing.assert_allclose(g.means[0, :3], [1, 2, 3])
    g1 = fit_sogmm(np.array([[0.0, 0.0, 0.0]]))
    check_valid(g1)
    assert g1.K == 1
    g2 = fit_sogmm(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), voxel=0.0)
    check_valid(g2)
    assert g2.K == 1
    assert abs(g2.normals[0, 0]) < 1e-9                      # normal perpendicular to the segment
    # duplicates inside a real cloud: each point 20 times changes nothing but the counts
    pts = plane_points(n=3000)
    a = fit_sogmm(pts, voxel=0.01)
    b = fit_sogmm(np.repeat(pts, 20, axis=0), voxel=0.01)
    assert a.fit_stats["n_points"] == b.fit_stats["n_points"] and a.K == b.K
    np.testing.assert_allclose(a.normals, b.normals, atol=1e-6)
    # without downsampling, duplicates weigh in but the planes found are the same
    a = fit_sogmm(pts, voxel=0.0, residual=0.01, max_extent=10.0)
    b = fit_sogmm(np.repeat(pts, 20, axis=0), voxel=0.0, residual=0.01, max_extent=10.0)
    assert a.K == b.K <= 4
    assert (np.abs(b.normals[:, 2]) > 0.999).all()


def test_collinear_cluster_gives_finite_unit_normal():
    t = np.linspace(0.0, 2.0, 3000)
    direction = np.array([1.0, 2.0, 2.0]) / 3.0
    g = fit_sogmm(t[:, None] * direction)
    check_valid(g)
    assert (np.abs(g.normals @ direction) < 1e-6).all()
    assert (np.abs(g.tangents[:, 0] @ direction) > 0.999999).all()


def test_tiny_clusters_never_below_min_points():
    pts = np.concatenate([plane_points(n=4000), [[3.0, 3.0, 3.0], [3.01, 3.0, 3.0], [3.0, 3.01, 3.0]]])
    g = fit_sogmm(pts, min_points=8)
    check_valid(g)
    assert (g.counts >= 8).all()
    assert g.counts.sum() == g.fit_stats["n_points"]


def test_deterministic():
    pts, _ = box_points([0, 0, 0], [0.5, 0.5, 0.5], 5000, seed=3, noise=0.001)
    a, b = fit_sogmm(pts, seed=0), fit_sogmm(pts, seed=0)
    for f in ("means", "covs", "weights", "normals", "tangents", "eigvals", "counts"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    c = type(a).from_arrays(a.as_arrays())
    for f in ("means", "covs", "normals", "counts"):
        np.testing.assert_array_equal(getattr(a, f), getattr(c, f))
    s1, s2 = sample_surfels(a, 500, seed=1), sample_surfels(a, 500, seed=1)
    s3 = sample_surfels(a, 500, seed=2)
    for x, y in zip(s1, s2):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(s1[0], s3[0])


# ---------------------------------------------------------------------------------------- sampling


def test_sample_surfels_frames_counts_and_positions():
    pts, _ = box_points([0, 0, 0], [1.0, 0.6, 0.4], 10000, noise=0.0)
    g = fit_sogmm(pts)
    means, quats, scales, grey = sample_surfels(g, 3000, seed=0)
    assert means.shape == (3000, 3) and quats.shape == (3000, 4) and scales.shape == (3000, 2)
    assert grey.shape == (3000,)
    np.testing.assert_allclose(np.linalg.norm(quats, axis=1), 1.0, atol=1e-6)
    assert (scales > 0).all() and np.isfinite(scales).all()
    # the quaternion's z axis (surfel normal) is the sampled component's normal
    w, x, y, z = quats.astype(np.float64).T
    n_q = np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=1)
    side = g.extents()
    areas = side[:, 0] * side[:, 1]
    # positions sampled in order of component: recover each surfel's component from the allocation
    counts = _alloc_counts(areas, 3000)
    comp = np.repeat(np.arange(g.K), counts)
    assert np.abs(counts - areas / areas.sum() * 3000).max() < 1.0   # proportional to tangent area
    np.testing.assert_allclose(n_q, g.normals[comp], atol=1e-5)
    # surfels lie on their component's plane, inside its tangent rectangle
    d = np.abs(((means - g.means[comp, :3]) * g.normals[comp]).sum(1))
    assert d.max() < 1e-5
    uv = np.einsum("sij,sj->si", g.tangents[comp], means - g.means[comp, :3])
    assert (np.abs(uv) <= side[comp] / 2 + 1e-5).all()
    # all surfels are near the sampled box surface
    from scipy.spatial import cKDTree

    assert np.quantile(cKDTree(pts).query(means)[0], 0.99) < 0.02


def _alloc_counts(areas, n):
    from psimap.geometry.sogmm import _allocate

    return _allocate(areas, n)


def test_sample_surfels_density_and_grey_gradient():
    # grey ramps with x: the conditional grey of a sample follows its position
    pts = plane_points(n=6000, noise=0.0)
    grey = 0.5 + 0.4 * pts[:, 0]
    g = fit_sogmm(pts, intensity=grey, max_extent=10.0, voxel=0.0)
    means, quats, scales, inten = sample_surfels(g, density=2000.0, seed=0)
    area = float((g.extents()[:, 0] * g.extents()[:, 1]).sum())
    assert abs(len(means) - 2000.0 * area) <= 1
    np.testing.assert_allclose(inten, np.clip(0.5 + 0.4 * means[:, 0], 0, 1), atol=0.02)
    # scales split each component's rectangle among its surfels: the covered area matches
    assert abs(float((4 * scales[:, 0] * scales[:, 1]).sum()) - area) < 0.05 * area


# ---------------------------------------------------------------------------------- training terms


def test_point_to_plane_and_normal_alignment_analytic():
    mu = torch.tensor([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0], [1.0, 2.0, 3.0]], requires_grad=True)
    m = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    s = 2 ** -0.5
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [s, s, 0.0]])
    d = point_to_plane(mu, m, n)
    torch.testing.assert_close(d, torch.tensor([2.0, 2.0, 3.0 * s]))
    d.sum().backward()
    # d/dmu |(mu - m).n| = sign((mu - m).n) n
    torch.testing.assert_close(mu.grad, torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [s, s, 0.0]]))
    a = torch.tensor([[0.0, 0.0, 1.0]] * 4)
    b = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.6, 0.8]])
    torch.testing.assert_close(normal_alignment(a, b), torch.tensor([0.0, 0.0, 1.0, 0.2]))


def test_index_nearest_matches_brute_force():
    pts, _ = box_points([0, 0, 0], [1.0, 0.6, 0.4], 8000, noise=0.002)
    g = fit_sogmm(pts)
    index = SOGMMIndex(g)
    q = torch.as_tensor(np.random.default_rng(1).uniform(-0.2, 1.2, (3000, 3)), dtype=torch.float32)
    idx = index.nearest(q)
    assert idx.dtype == torch.long and idx.shape == (3000,)
    brute = torch.cdist(q.double(), torch.as_tensor(g.means[:, :3])).argmin(1)
    dq = torch.cdist(q.double(), torch.as_tensor(g.means[:, :3]))
    # equal, or a tie at float precision
    assert torch.all((idx == brute) | ((dq[torch.arange(3000), idx] - dq[torch.arange(3000), brute]) < 1e-9))
    with pytest.raises(PsimapError, match="NaN"):
        index.nearest(torch.tensor([[float("nan"), 0.0, 0.0]]))


def test_geo_loss_zero_on_prior_and_equals_offset():
    pts, _ = box_points([0, 0, 0], [1.0, 0.6, 0.4], 8000, noise=0.0)
    g = fit_sogmm(pts)
    index = SOGMMIndex(g)
    means = torch.as_tensor(g.means[:, :3], dtype=torch.float32)
    normals = torch.as_tensor(g.normals, dtype=torch.float32)
    assert geo_loss(means, normals, index, lambda_n=0.5).item() < 1e-6
    # push every surfel 1 mm along its component normal: the loss is exactly that offset
    shifted = (means + 0.001 * normals).requires_grad_(True)
    t0 = torch.as_tensor(g.tangents[:, 0], dtype=torch.float32)
    tilted = torch.nn.functional.normalize(normals + 0.3 * t0, dim=1)
    loss = geo_loss(shifted, tilted, index, lambda_n=0.5)
    expected = 0.001 + 0.5 * (1 - 1 / np.sqrt(1 + 0.09))
    assert abs(loss.item() - expected) < 1e-5
    loss.backward()
    assert torch.isfinite(shifted.grad).all() and shifted.grad.abs().sum() > 0
    s = geo_loss(shifted.detach(), tilted, index, lambda_n=0.5, reduction="sum")
    assert abs(s.item() - expected * g.K) < 1e-3 * g.K
    assert geo_loss(torch.zeros((0, 3)), torch.zeros((0, 3)), index).item() == 0.0
    # surfels on the prior stay (nearly) loss-free with the likelihood lookup too
    assert geo_loss(means, normals, index, lambda_n=0.5, candidates=6).item() < 1e-6


# ------------------------------------------------------------------------------------- point helpers


def test_backproject_plane_and_pose():
    H, W = 48, 64
    K = np.array([[50.0, 0, 32.0], [0, 50.0, 24.0], [0, 0, 1]])
    depth = np.full((H, W), 2.0, np.float32)
    depth[:5] = 0.0                                     # invalid rows
    depth[5, 5] = np.nan
    rgb = np.zeros((H, W, 3), np.float32)
    rgb[..., 1] = 1.0                                    # pure green -> grey 0.587
    c2w = np.eye(4)
    # camera 3 m up looking straight down (OpenCV z forward = world -z)
    c2w[:3, :3] = np.diag([1.0, -1.0, -1.0])
    c2w[:3, 3] = [0.5, 0.0, 3.0]
    p = backproject_frame(rgb, depth, K, c2w)
    assert p.shape == ((H - 5) * W - 1, 4)
    np.testing.assert_allclose(p[:, 2], 1.0, atol=1e-6)          # world plane z = 3 - 2
    np.testing.assert_allclose(p[:, 3], 0.587, atol=1e-6)
    # the principal pixel lands right below the camera
    assert np.min(np.linalg.norm(p[:, :2] - [0.5, 0.0], axis=1)) < 1e-6
    assert len(backproject_frame(rgb, depth, K, c2w, max_depth=1.5)) == 0
    frame_ok = SimpleNamespace(rgb=rgb, depth=depth, K=K, c2w=c2w, lidar=None)
    frame_empty = SimpleNamespace(rgb=rgb, depth=np.zeros((H, W), np.float32), K=K, c2w=c2w,
                                  lidar=np.array([[0, 0, 0, 200.0], [1, 0, 0, 100.0]], np.float32))
    allp = frames_to_points([frame_ok, frame_empty])
    assert len(allp) == len(p) + 2
    # incremental per-frame voxel averaging equals downsampling the union at once
    frame_2 = SimpleNamespace(rgb=rgb * 0.5, depth=depth * 1.1, K=K, c2w=c2w, lidar=None)
    union = frames_to_points([frame_ok, frame_2, frame_empty])
    inc = frames_to_points([frame_ok, frame_2, frame_empty], voxel=0.2)
    np.testing.assert_allclose(inc, voxel_downsample(union, 0.2), atol=1e-6)
    assert len(inc) < len(union) / 4
    with pytest.raises(PsimapError):
        backproject_frame(rgb[:10], depth, K, c2w)


def test_voxel_downsample_averages_and_lidar_intensity():
    pts = np.array([[0.01, 0.01, 0.01, 0.0], [0.03, 0.02, 0.01, 1.0], [0.5, 0.5, 0.5, 0.4]])
    out = voxel_downsample(pts, 0.1)
    assert out.shape == (2, 4)
    np.testing.assert_allclose(out[0], [0.02, 0.015, 0.01, 0.5])
    np.testing.assert_allclose(out[1], [0.5, 0.5, 0.5, 0.4])
    with pytest.raises(PsimapError):
        voxel_downsample(pts, -1.0)
    raw = np.c_[np.random.default_rng(0).normal(size=(1000, 3)), np.linspace(0, 255, 1000)]
    raw[3, 0] = np.nan
    li = lidar_points(raw)
    assert len(li) == 999 and li[:, 3].min() >= 0 and li[:, 3].max() <= 1.0
    assert li[:, 3].max() == 1.0 and 0.45 < np.median(li[:, 3]) < 0.55
    kitti_like = np.c_[np.zeros((5, 3)), [0.0, 0.2, 0.4, 0.6, 0.99]]
    np.testing.assert_allclose(lidar_points(kitti_like)[:, 3], [0.0, 0.2, 0.4, 0.6, 0.99], atol=1e-6)


@pytest.mark.skipif(not (DATA / "7scenes-chess").exists(), reason="shared data absent")
def test_7scenes_prior_explains_held_out_frame():
    from PIL import Image

    root = DATA / "7scenes-chess"
    K = np.loadtxt(root / "camera-intrinsics.txt")

    def frame(i):
        stem = root / f"frame-{i:06d}"
        raw = np.asarray(Image.open(f"{stem}.depth.png")).astype(np.float32)
        raw[raw >= 65535] = 0.0                              # Kinect "no reading"
        return SimpleNamespace(rgb=np.asarray(Image.open(f"{stem}.color.jpg"), np.float32) / 255.0,
                               depth=raw / 1000.0, K=K, c2w=np.loadtxt(f"{stem}.pose.txt"), lidar=None)

    pts = frames_to_points([frame(i) for i in range(0, 50, 10)], stride=4, voxel=0.01, max_depth=4.0)
    assert pts.shape[1] == 4 and 0.0 <= pts[:, 3].min() and pts[:, 3].max() <= 1.0
    g = fit_sogmm(pts, residual=0.01)
    check_valid(g)
    assert g.fit_stats["residual_mean"] < 0.01
    # a frame the prior never saw lies on its planes (real Kinect noise: ~1 cm)
    held = frame(80)
    q = backproject_frame(held.rgb, held.depth, K, held.c2w, stride=4, max_depth=4.0)
    lab = g.assign(q)
    d = np.abs(((q[:, :3] - g.means[lab, :3]) * g.normals[lab]).sum(1))
    assert np.median(d) < 0.012


def test_noise_aware_fit_keeps_noisy_planes_whole_and_still_splits_bends():
    """Per-point depth noise: a plane whose residual the noise explains stops splitting (fewer,
    larger patches, closer to the true plane than the noise-blind fit); a bend of the surface
    larger than the noise still splits; points at the noise level of 0 behave as without."""
    rng = np.random.default_rng(3)
    n, sigma = 20000, 0.02
    xy = rng.uniform(-1.0, 1.0, (n, 2))
    pts = np.c_[xy, rng.normal(0.0, sigma, n)]                 # 2 x 2 m plane, 2 cm noise
    blind = fit_sogmm(pts, voxel=0.0, max_extent=1.0, residual=0.005)
    aware = fit_sogmm(pts, voxel=0.0, max_extent=1.0, residual=0.005, noise=np.full(n, sigma))
    check_valid(aware)
    assert aware.K <= 9 < blind.K                  # seed cells of max_extent / sqrt 2: 3 x 3
    truth = np.c_[rng.uniform(-0.9, 0.9, (4000, 2)), np.zeros(4000)]

    def plane_error(g):
        lab = g.assign(truth)
        return np.abs(((truth - g.means[lab, :3]) * g.normals[lab]).sum(1)).mean()

    assert plane_error(aware) < 0.5 * plane_error(blind), (plane_error(aware), plane_error(blind))
    assert (np.abs(aware.normals[:, 2]) > COS10).all()
    # a 90-degree fold (floor + wall) with 2 mm noise: the fold is far above the noise, so it splits
    fold = np.r_[np.c_[rng.uniform(0, 1, (4000, 2)), rng.normal(0, 0.002, 4000)],
                 np.c_[rng.normal(0, 0.002, 4000), rng.uniform(0, 1, (4000, 2))]]
    g = fit_sogmm(fold, voxel=0.0, max_extent=2.0, residual=0.005, noise=np.full(len(fold), 0.002))
    lab = g.assign(fold)
    d = np.abs(((fold - g.means[lab, :3]) * g.normals[lab]).sum(1))
    assert d.mean() < 0.006 and g.K >= 2
    # zero noise: the same fit as without noise
    z = fit_sogmm(pts, voxel=0.0, max_extent=1.0, residual=0.005, noise=np.zeros(n))
    assert z.K == blind.K and np.allclose(z.means, blind.means)
    with pytest.raises(PsimapError, match="noise has"):
        fit_sogmm(pts, noise=np.ones(3))


def test_noise_aware_fit_counts_voxel_averaging():
    """Voxel averaging of m readings lowers their noise by sqrt(m): with many readings per voxel
    the same per-reading noise no longer explains a coarse misfit (the fit splits more)."""
    rng = np.random.default_rng(4)
    xy = rng.uniform(-1.0, 1.0, (40000, 2))
    pts = np.c_[xy, 0.05 * np.sin(3 * xy[:, 0]) + rng.normal(0.0, 0.01, len(xy))]   # a gentle wave
    few = fit_sogmm(pts[:4000], voxel=0.0, max_extent=1.0, residual=0.002, noise=np.full(4000, 0.01))
    many = fit_sogmm(pts, voxel=0.02, max_extent=1.0, residual=0.002, noise=np.full(len(pts), 0.01))
    assert many.K > few.K
