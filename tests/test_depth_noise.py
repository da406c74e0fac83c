"""Depth-noise estimation from the depth images (psimap.geometry.depth_noise) and the trainer's
noise-weighted depth loss."""
from __future__ import annotations

import numpy as np
import torch

from psimap.geometry.depth_noise import estimate_depth_noise, noise_at, second_difference_samples


def _plane_views(sigma_of_z, n=6, h=60, w=80, seed=0, edge=False):
    """Depth images of tilted planes spanning 1-4 m, with i.i.d. noise of std sigma_of_z(z)."""
    rng = np.random.default_rng(seed)
    out = []
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    for i in range(n):
        # inverse depth affine in the pixel coordinates = a plane in the camera frame
        inv = 1.0 / 1.0 - (1.0 / 1.0 - 1.0 / 4.0) * (v / (h - 1)) * (0.8 + 0.05 * i) - 0.001 * u
        z = 1.0 / inv
        if edge:   # a box in front: a depth step on a fifth of the image
            z = np.where((u > 30) & (u < 46), z * 0.6, z)
        out.append((z + rng.standard_normal(z.shape) * sigma_of_z(z)).astype(np.float32))
    return out


def test_estimator_recovers_a_range_dependent_noise_model():
    def sigma(z):
        return 0.002 + 0.004 * (z - 0.5) ** 2

    for edge in (False, True):        # depth edges must not inflate the robust estimate
        zc, sc = estimate_depth_noise(_plane_views(sigma, edge=edge))
        assert len(zc) >= 6
        err = np.abs(sc / sigma(zc) - 1.0)
        assert err.max() < 0.15, (edge, np.c_[zc, sc, sigma(zc)])
        assert np.all(np.diff(sc) >= 0)


def test_estimator_scales_with_the_noise():
    base = estimate_depth_noise(_plane_views(lambda z: 0.003 * z**2, seed=1))
    triple = estimate_depth_noise(_plane_views(lambda z: 0.009 * z**2, seed=1))
    ratio = np.median(triple[1] / base[1])
    assert 2.7 < ratio < 3.3


def test_estimator_degenerate_inputs():
    # no valid triple: empty model, noise_at falls back to its floor
    empty = estimate_depth_noise([np.zeros((10, 10), np.float32), np.full((4, 4), np.nan, np.float32)])
    assert len(empty[0]) == 0
    assert np.all(noise_at(np.array([1.0, 3.0]), empty, floor=1e-3) == 1e-3)
    assert len(estimate_depth_noise([])[0]) == 0
    # noiseless plane: sigma ~ 0, clamped by the floor; no NaN from inf / NaN pixels
    z = _plane_views(lambda z: 0.0 * z, n=2)
    z[0][5, 5] = np.inf
    z[1][7, 7] = np.nan
    zc, sc = estimate_depth_noise(z)
    assert np.isfinite(sc).all() and sc.max() < 1e-5
    assert np.all(noise_at(zc, (zc, sc), floor=1e-4) >= 1e-4)
    zs, ss = second_difference_samples(np.array([[1.0, 0.0, 1.0]]))
    assert len(zs) == 0


def test_prior_points_carry_the_noise_of_their_range():
    """The trainer's SOGMM input: one noise value per back-projected point, sigma(z) of its depth."""
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import TrainFrame, prior_points

    def sigma(z):
        return 0.001 + 0.004 * (z - 0.5) ** 2

    K = torch.tensor([[50.0, 0, 40], [0, 50.0, 30], [0, 0, 1]])
    frames = []
    for d in _plane_views(sigma, n=4):
        d[0, :5] = 0.0
        frames.append(TrainFrame(name="f", rgb=torch.zeros(*d.shape, 3), depth=torch.from_numpy(d), K=K,
                                 c2w=np.eye(4), viewmat=torch.eye(4)))
    pts, noise, stride, _ = prior_points(frames, TrainConfig(), log=lambda s: None)
    assert noise is not None and noise.shape == (len(pts),) and np.isfinite(noise).all()
    # the point's camera-frame z is its depth (identity pose): noise follows sigma(z)
    inner = (pts[:, 2] > 1.2) & (pts[:, 2] < 3.0)
    assert np.allclose(noise[inner], sigma(pts[inner, 2]), rtol=0.2)
    pts2, none, _, _ = prior_points(frames, TrainConfig(prior_noise=False), log=lambda s: None)
    assert none is None and np.array_equal(pts, pts2)
