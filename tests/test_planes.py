"""psimap.geometry.planes.ransac_plane: seeded RANSAC plane fits (segment's stuff planes, gravity's
levelling) that find the plane, refit it, stop early, skip degenerate draws and answer the same on
every run and every thread."""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from psimap.geometry.planes import ransac_plane


def _plane_points(rng, n_pts, normal, offset, size=1.0, noise=0.001):
    """n_pts points on the plane normal.x + offset = 0 (a size x size patch about its foot point),
    with Gaussian noise along the normal."""
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    a = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    uv = rng.uniform(-size / 2, size / 2, (n_pts, 2))
    return (-offset * normal + uv[:, :1] * a + uv[:, 1:] * b
            + rng.normal(0, noise, (n_pts, 1)) * normal)


def _angle_deg(n, m):
    return float(np.degrees(np.arccos(min(1.0, abs(float(n @ m)) / np.linalg.norm(n) / np.linalg.norm(m)))))


def _scene(seed=0):
    """A tilted floor (2000 points, 1 mm noise), a wall (800) and 1200 points scattered in the box
    around them: the floor is the answer."""
    rng = np.random.default_rng(seed)
    normal = np.array([0.1, -0.2, 1.0])
    floor = _plane_points(rng, 2000, normal, 0.3)
    wall = _plane_points(rng, 800, [1.0, 0.0, 0.0], -0.4)
    clutter = rng.uniform(-0.6, 0.6, (1200, 3))
    return np.concatenate([floor, wall, clutter]), normal / np.linalg.norm(normal), 0.3


def test_the_largest_plane_is_found_among_a_smaller_one_and_clutter():
    pts, normal, offset = _scene()
    plane, inliers = ransac_plane(pts, 0.005, np.random.default_rng(1))
    n, d = plane[:3], plane[3]
    assert abs(np.linalg.norm(n) - 1) < 1e-9
    if n @ normal < 0:
        n, d = -n, -d
    # refitted by least squares to ~2000 points with 1 mm noise: far better than any 3-point plane
    assert _angle_deg(n, normal) < 0.05
    assert abs(d - offset) < 5e-4
    on_floor = inliers < 2000
    assert on_floor.sum() >= 0.99 * 2000
    # the clutter inside the 5 mm band (about 1 % of the box's height): a handful, not the wall
    assert (~on_floor).sum() < 30
    assert np.all(np.diff(inliers) > 0)                  # sorted indices, each once


def test_the_same_answer_for_a_seed_on_every_thread():
    pts, _, _ = _scene(seed=3)

    def fit(seed):
        plane, inl = ransac_plane(pts, 0.005, np.random.default_rng(seed), iterations=200)
        return plane, inl

    ref = [fit(s) for s in (5, 6)]
    with ThreadPoolExecutor(4) as ex:
        again = list(ex.map(fit, [5, 6, 5, 6, 5, 6, 5, 6]))
    for k, (plane, inl) in enumerate(again):
        assert np.array_equal(plane, ref[k % 2][0]) and np.array_equal(inl, ref[k % 2][1])


class _CountingRng:
    """A Generator that counts the hypotheses drawn (ransac_plane draws (b, 3) integer arrays)."""

    def __init__(self, seed):
        self.rng, self.drawn = np.random.default_rng(seed), 0

    def integers(self, low, high, size):
        self.drawn += size[0]
        return self.rng.integers(low, high, size)


def test_draws_stop_once_a_clean_sample_is_all_but_certain():
    rng = np.random.default_rng(0)
    clean = _plane_points(rng, 1000, [0, 0, 1], 0.0)
    counter = _CountingRng(0)
    plane, inl = ransac_plane(clean, 0.005, counter, iterations=100000)
    assert len(inl) == 1000 and _angle_deg(plane[:3], [0, 0, 1]) < 0.05
    assert counter.drawn <= 64                            # one batch: every point an inlier
    # half the points inliers: (1 - 0.5^3)^k <= 1e-8 needs k = 138 draws, so three batches of 64
    pts, _, _ = _scene()
    half = np.concatenate([pts[:2000], np.random.default_rng(1).uniform(-0.6, 0.6, (2000, 3))])
    counter = _CountingRng(0)
    ransac_plane(half, 0.005, counter, iterations=100000)
    assert 128 < counter.drawn <= 192


def test_too_few_collinear_and_repeated_points_give_no_plane():
    rng = np.random.default_rng(0)
    for pts in (np.zeros((0, 3)), np.ones((2, 3)),
                np.outer(np.linspace(0, 1, 50), [1.0, 2.0, 3.0]),        # one line
                np.repeat([[0.1, 0.2, 0.3]], 40, axis=0)):               # one point, repeated
        plane, inl = ransac_plane(pts, 0.01, rng, iterations=300)
        assert not plane.any() and len(inl) == 0 and inl.dtype == np.int64
    # a plane one of whose points is repeated 600 times (most draws hold it twice or thrice): those
    # draws make no plane, and every other plane through the repeated point holds fewer points
    plane_pts = _plane_points(rng, 300, [0, 0, 1], 0.0, noise=0.0)
    off = rng.uniform(-0.5, 0.5, (20, 3)) + [0.0, 0.0, 1.0]
    pts = np.concatenate([plane_pts, np.repeat(plane_pts[:1], 600, axis=0), off])
    plane, inl = ransac_plane(pts, 0.01, np.random.default_rng(2), iterations=2000)
    assert _angle_deg(plane[:3], [0, 0, 1]) < 1e-6 and np.array_equal(inl, np.arange(900))


def test_a_scene_in_geographic_coordinates_fits_as_well_as_at_the_origin():
    """UTM-like coordinates (hundreds of kilometres): hypotheses are scored in float32 about the
    centroid, so the plane and its inliers are those of the same scene at the origin."""
    pts, normal, _ = _scene()
    offset = np.array([412345.0, 5412345.0, 230.0])
    ref_plane, ref_inl = ransac_plane(pts, 0.005, np.random.default_rng(1))
    plane, inl = ransac_plane(pts + offset, 0.005, np.random.default_rng(1))
    assert _angle_deg(plane[:3], normal) < 0.05
    assert len(np.setxor1d(inl, ref_inl)) <= 5
    assert abs(abs(plane[:3] @ (pts[0] + offset) + plane[3])) < 0.005
