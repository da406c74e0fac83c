"""LiDAR in training (issue 18): virtual views of a sweep, the range term, the sweep's own noise
estimate, colouring returns, and training with and without depth images."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from psimap.geometry.depth_noise import estimate_lidar_noise
from psimap.train.lidar import (Sweep, colour_returns, lidar_views, range_l1, range_weight, sample_depth,
                                sweep_of)
from psimap.transforms import pixels_to_camera, transform_points


def box_sweep(origin=(0.3, -0.2, 0.1), noise=0.0, seed=0, beams=16, azimuths=720):
    """A spinning-LiDAR sweep inside the box [-4, 4] x [-3, 3] x [-1.2, 1.8] from `origin`."""
    el = np.radians(np.linspace(-25, 15, beams))
    az = np.linspace(0, 2 * np.pi, azimuths, endpoint=False)
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    o = np.asarray(origin, np.float64)
    lo, hi = np.array([-4.0, -3.0, -1.2]) - o, np.array([4.0, 3.0, 1.8]) - o
    with np.errstate(divide="ignore"):
        t = np.min(np.where(d > 0, hi / d, np.where(d < 0, lo / d, np.inf)), axis=1)
    t = t + np.random.default_rng(seed).normal(0, noise, t.shape)
    return Sweep(points=o + d * t[:, None], intensity=np.full(len(t), 0.4, np.float32), origin=o, name="s")


def test_views_reproject_every_return_exactly():
    sweep = box_sweep()
    views = lidar_views(sweep)
    # 16 rings from -25 to +15 degrees: the four side faces, none above or below
    assert len(views) == 4
    assert sum(v.z.numel() for v in views) == len(sweep.points)
    for v in views:
        assert float(v.z.min()) > 0.5                 # every return in front of its view's camera
        u, w = v.uv[:, 0].double().numpy(), v.uv[:, 1].double().numpy()
        assert u.min() >= -1e-3 and u.max() <= v.width - 1 + 1e-3 and w.min() >= -1e-3 and w.max() <= v.height - 1 + 1e-3
        world = transform_points(pixels_to_camera(u, w, v.z.double().numpy(), v.K.double().numpy()), v.c2w)
        d = np.linalg.norm(world[:, None] - sweep.points[None], axis=2).min(1)
        assert d.max() < 2e-4 * 5                     # float32 uv / z at ~5 m
        # the view's world-to-camera matrix is the inverse of its pose
        np.testing.assert_allclose(v.viewmat.double().numpy() @ v.c2w, np.eye(4), atol=1e-5)
    # a pixel is two of the sweep's angular steps (0.5 degrees -> ~115 pixels per 90 degrees)
    assert max(max(v.width, v.height) for v in views) in range(105, 125)


def test_sample_depth_is_bilinear_and_differentiable():
    H, W = 7, 9
    vv, uu = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    depth = (1.0 + 0.1 * uu + 0.05 * vv).requires_grad_(True)          # a plane: bilinear is exact
    uv = torch.tensor([[0.0, 0.0], [3.25, 2.5], [8.0, 6.0], [4.9, 0.1]])
    got = sample_depth(depth, uv)
    np.testing.assert_allclose(got.detach().numpy(), 1.0 + 0.1 * uv[:, 0] + 0.05 * uv[:, 1], atol=1e-6)
    got.sum().backward()
    assert abs(float(depth.grad.sum()) - 4.0) < 1e-5                  # each sample's weights sum to 1


def test_range_l1_and_weight():
    sweep = box_sweep()
    v = lidar_views(sweep)[0]
    # a rendered depth of 0 everywhere is off by each return's whole depth; 1 m further by that + 1
    zero = torch.zeros((v.height, v.width))
    assert abs(float(range_l1(zero, v)) - float(v.z.abs().mean())) < 1e-4
    far = torch.full((v.height, v.width), float(v.z.max()) + 1.0)
    assert abs(float(range_l1(far, v)) - float((v.z.max() + 1.0 - v.z).mean())) < 1e-4
    assert range_weight(None, 0.01) == 1.0
    assert range_weight(0.005, 0.01) == pytest.approx(0.5)
    assert range_weight(1.0, 0.001) == 1.0 and range_weight(1e-6, 0.1) == 0.1
    np.testing.assert_allclose(range_weight(np.array([0.0005, 0.002, 0.01, 0.05]), 0.01), [0.1, 0.2, 1.0, 1.0])
    # the weights apply per return; unweighted is the plain mean
    v.w = torch.linspace(0.0, 2.0, v.z.numel())
    assert abs(float(range_l1(zero, v)) - float((v.z * v.w).mean())) < 1e-4
    assert abs(float(range_l1(zero, v, weighted=False)) - float(v.z.mean())) < 1e-4


@pytest.mark.parametrize("sigma", [0.003, 0.01, 0.03])
def test_lidar_noise_estimated_from_the_sweep(sigma):
    sweep = box_sweep(noise=sigma, seed=1)
    est = estimate_lidar_noise(sweep.points, sweep.origin)
    assert est == pytest.approx(sigma, rel=0.15)
    # an origin a few cm off barely matters
    assert estimate_lidar_noise(sweep.points, sweep.origin + 0.05) == pytest.approx(sigma, rel=0.2)
    assert estimate_lidar_noise(sweep.points[:50], sweep.origin) is None        # too few samples


def test_colour_returns_visible_and_occluded():
    from psimap.train.trainer import to_train_frame

    K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    rgb = np.zeros((48, 64, 3), np.float32)
    rgb[..., 0] = 0.9
    depth = np.full((48, 64), 2.0, np.float32)                 # a wall 2 m in front of the camera
    fr = to_train_frame("f", rgb, depth, K, np.eye(4))
    pts = np.array([[0.0, 0.0, 2.0],                           # on the wall: red
                    [0.0, 0.0, 3.0],                           # behind the wall: not seen, intensity grey
                    [0.0, 0.0, -1.0]])                         # behind the camera
    sw = Sweep(points=pts, intensity=np.array([0.2, 0.3, 0.7], np.float32), origin=np.zeros(3))
    _, cols = colour_returns([sw], [fr])
    np.testing.assert_allclose(cols, [[0.9, 0, 0], [0.3, 0.3, 0.3], [0.7, 0.7, 0.7]], atol=1e-6)


@pytest.fixture(scope="module")
def lidar_scene(tmp_path_factory):
    from psimap.data.synthetic import generate

    out = tmp_path_factory.mktemp("lidar") / "scene"
    generate(out, seed=3, frames=12, width=64, height=48, lidar=True, lidar_every=4, progress=False)
    return out


def _train(seq, iters=60, **kw):
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import train

    return train(seq, TrainConfig(iters=iters, panoptic=False, **kw), log=lambda s: None)


def test_sweeps_are_read_and_origin_defaults_to_the_camera(lidar_scene):
    from psimap.data import load

    seq = load(lidar_scene)
    f = seq[0]
    sw = sweep_of(f)
    assert sw is not None and len(sw.points) > 1000
    np.testing.assert_allclose(sw.origin, f.c2w[:3, 3])
    assert sweep_of(seq[1]) is None                           # a sweep every 4th frame


def test_range_term_trains_the_map_towards_the_returns(lidar_scene):
    from psimap.data import load

    seq = load(lidar_scene)
    with_term = _train(seq)
    m = with_term.metrics
    assert m["lidar_sweeps"] == 3 and m["lidar_returns"] > 3000
    assert 0.005 < m["lidar_noise"] < 0.02                    # the generator's 1 cm range noise
    assert 0.1 <= m["range_weight"] < 1.0
    assert m["range_l1_end"] < 0.75 * m["range_l1_start"]
    without = _train(seq, lambda_range=0.0)
    assert m["range_l1_end"] < without.metrics["range_l1_end"]
    off = _train(seq, lidar=False)
    assert "lidar_sweeps" not in off.metrics


def test_colour_and_lidar_only_trains(lidar_scene):
    """No depth images at all: the frames' colour and the sweeps' geometry still make a map; without
    the sweeps, the same frames are refused."""
    from psimap import PsimapError
    from psimap.data import load

    seq = load(lidar_scene)
    nodepth = dataclasses.replace(seq, loader=lambda i: dataclasses.replace(seq[i], depth=np.zeros_like(seq[i].depth)))
    scene = _train(nodepth, iters=120)      # range error 6.4 -> 3.9 cm at 120 steps (5.7 without the term)
    assert scene.metrics["skipped_frames"] == [] and scene.cameras["c2w"].shape[0] == 12
    assert scene.metrics["range_l1_end"] < 0.75 * scene.metrics["range_l1_start"]
    assert scene.metrics["range_l1_end"] < 0.05
    assert torch.isfinite(scene.surfels["means"]).all()
    with pytest.raises(PsimapError, match="no frame has valid depth"):
        _train(nodepth, iters=5, lidar=False)


def test_scene_format_lidar_origin_and_no_depth_images(lidar_scene, tmp_path):
    """A capture may give each sweep's sensor position, and a LiDAR + colour capture has no depth
    images: frames with a lidar_file_path need no depth_file_path."""
    import json
    import shutil

    from psimap import PsimapError
    from psimap.data import load

    root = tmp_path / "scene"
    shutil.copytree(lidar_scene, root)
    meta = json.loads((root / "transforms.json").read_text())
    with_lidar = [fr for fr in meta["frames"] if fr.get("lidar_file_path")]
    with_lidar[0]["lidar_origin"] = [0.5, -1.0, 1.25]
    for fr in with_lidar:
        del fr["depth_file_path"]
    (root / "transforms.json").write_text(json.dumps(meta))
    seq = load(root)
    f = seq[0]
    assert not f.depth.any() and f.depth.shape == (48, 64)
    np.testing.assert_allclose(sweep_of(f).origin, [0.5, -1.0, 1.25])
    assert seq[1].depth.any()                                 # frames without a sweep keep theirs
    with_lidar[0]["lidar_origin"] = [0.5, "x"]
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(PsimapError, match="lidar_origin"):
        load(root)
    with_lidar[0]["lidar_origin"] = [0.5, float("nan"), 1.0]
    (root / "transforms.json").write_text(json.dumps(meta).replace("NaN", "NaN"))
    with pytest.raises(PsimapError, match="lidar_origin must be finite"):
        load(root)


KITTI = __import__("pathlib").Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti-velodyne" / "000000.bin"


@pytest.mark.skipif(not KITTI.exists(), reason="shared data absent")
def test_real_kitti_sweep_through_the_lidar_path():
    """The real HDL-64 sweep: its range noise is measurable and plausible (datasheet: < 2 cm), every
    return lands in a view, and the prior takes the coloured returns with that noise."""
    from psimap.geometry.points import lidar_points
    from psimap.geometry.sogmm import fit_sogmm

    p = lidar_points(np.fromfile(KITTI, dtype=np.float32).reshape(-1, 4))
    sweep = Sweep(points=p[:, :3].astype(np.float64), intensity=p[:, 3], origin=np.zeros(3), name="kitti")
    sigma = estimate_lidar_noise(sweep.points, sweep.origin)
    assert 0.004 < sigma < 0.03
    views = lidar_views(sweep)
    assert len(views) == 4 and sum(v.z.numel() for v in views) == len(p)
    assert all(v.width * v.height <= 256 * 256 for v in views)
    fit = fit_sogmm(p, noise=np.full(len(p), sigma), voxel=0.1)
    assert fit.K > 100 and np.isfinite(fit.means).all()
