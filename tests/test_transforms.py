"""psimap.transforms: the one home of pixel, rotation and surface-sampling maths."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from psimap.camera import look_at, nearest_pixels
from psimap.transforms import (PIXEL_CENTER, camera_to_pixels, depth_to_world, pixels_to_camera,
                               pixels_to_camera_torch, quat_to_rotmat, quat_to_rotmat_torch, rotmat_to_quat,
                               sample_surface, transform_points)

K = np.array([[100.0, 0.0, 50.0], [0.0, 200.0, 40.0], [0.0, 0.0, 1.0]])


def random_quats(n, seed=0):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# ---- pixels <-> camera ------------------------------------------------------------------------

def test_opencv_pixel_centres_are_integers():
    assert PIXEL_CENTER == 0.0
    # the principal point's pixel looks straight ahead; 100 px right / 200 px down at 1 m is 1 m off
    pts = pixels_to_camera(np.array([50, 150, 0]), np.array([40, 240, 0]), np.array([2.0, 1.0, 4.0]), K)
    np.testing.assert_array_equal(pts, [[0.0, 0.0, 2.0], [1.0, 1.0, 1.0], [-2.0, -0.8, 4.0]])
    assert pts.dtype == np.float64


def test_pixels_camera_round_trip_and_batch_shape():
    v, u = np.mgrid[0:6, 0:7]
    z = 0.5 + np.random.default_rng(1).random((6, 7))
    pts = pixels_to_camera(u, v, z, K)
    assert pts.shape == (6, 7, 3)
    uu, vv = camera_to_pixels(pts[..., 0], pts[..., 1], pts[..., 2], K)
    np.testing.assert_allclose(uu, u, atol=1e-12)
    np.testing.assert_allclose(vv, v, atol=1e-12)


def test_torch_back_projection_matches_numpy_and_carries_depth_gradients():
    v, u = np.mgrid[0:4, 0:5]
    z = 1.0 + np.random.default_rng(2).random((4, 5))
    zt = torch.tensor(z, requires_grad=True)
    pts = pixels_to_camera_torch(torch.tensor(u, dtype=torch.float64), torch.tensor(v, dtype=torch.float64),
                                 zt, torch.tensor(K))
    np.testing.assert_array_equal(pts.detach().numpy(), pixels_to_camera(u, v, z, K))
    pts[..., 0].sum().backward()
    # x = (u - cx) / fx * z: dx/dz is the pixel's ray slope
    np.testing.assert_allclose(zt.grad.numpy(), (u - K[0, 2]) / K[0, 0], rtol=1e-12)


def test_transform_points_numpy_torch_and_inverse():
    c2w = look_at([1.0, -2.0, 1.5], [0.0, 0.5, 0.3])
    p = np.random.default_rng(3).normal(size=(10, 3))
    w = transform_points(p, c2w)
    np.testing.assert_allclose(w, (c2w @ np.c_[p, np.ones(10)].T).T[:, :3], atol=1e-12)
    np.testing.assert_allclose(transform_points(w, np.linalg.inv(c2w)), p, atol=1e-12)
    # torch's and numpy's matmul may round the last bit differently
    np.testing.assert_allclose(transform_points(torch.tensor(p), torch.tensor(c2w)).numpy(), w, atol=1e-14)


def test_depth_to_world_drops_invalid_depth_and_applies_pose():
    depth = np.full((4, 6), 2.0)
    depth[0, 0], depth[1, 2], depth[2, 3], depth[3, 5] = 0.0, np.nan, np.inf, -1.0
    c2w = np.eye(4)
    c2w[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]      # 90 degrees about z
    c2w[:3, 3] = [1.0, 2.0, 3.0]
    pts, v, u = depth_to_world(depth, K, c2w)
    assert len(pts) == 24 - 4
    assert not ((v == 0) & (u == 0)).any() and not ((v == 1) & (u == 2)).any()
    assert np.all(np.diff(v * 6 + u) > 0)                 # row-major pixel order
    cam = pixels_to_camera(u, v, depth[v, u], K)
    np.testing.assert_allclose(pts, cam @ c2w[:3, :3].T + c2w[:3, 3], atol=1e-12)
    np.testing.assert_allclose(pts[:, 2], 5.0)           # z-depth 2 along world z, camera at 3
    # stride keeps every 2nd row and column, in full-resolution pixel indices; max_depth cuts
    depth[::2, ::2] = np.where(np.isfinite(depth[::2, ::2]), depth[::2, ::2], 0)
    depth[2, 2] = 5.0
    pts2, v2, u2 = depth_to_world(depth, K, c2w, stride=2, max_depth=3.0)
    assert set(zip(v2.tolist(), u2.tolist())) == {(0, 2), (0, 4), (2, 0), (2, 4)}
    assert depth_to_world(np.zeros((3, 3)), K, c2w)[0].shape == (0, 3)


def test_nearest_pixels_inverts_back_projection():
    """camera.nearest_pixels (texture baking, carving) and depth_to_world share the pixel centres."""
    c2w = look_at([0.0, -3.0, 1.0], [0.0, 0.0, 0.5])
    depth = 2.0 + np.random.default_rng(4).random((8, 10))
    pts, v, u = depth_to_world(depth, K, c2w)
    pu, pv, z, inside = nearest_pixels(pts, K, c2w, 100, 80)
    np.testing.assert_array_equal(pu, u)
    np.testing.assert_array_equal(pv, v)
    np.testing.assert_allclose(z, depth[v, u], rtol=1e-12)
    assert inside.all()


# ---- quaternions <-> rotations ----------------------------------------------------------------

def test_quaternion_known_rotations():
    s = np.sqrt(0.5)
    R = quat_to_rotmat(np.array([[1.0, 0, 0, 0], [s, 0, 0, s], [0.0, 1, 0, 0]]))
    np.testing.assert_allclose(R[0], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(R[1], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)   # 90 deg about z
    np.testing.assert_allclose(R[2], np.diag([1.0, -1.0, -1.0]), atol=1e-15)          # 180 deg about x
    np.testing.assert_allclose(rotmat_to_quat(R), [[1, 0, 0, 0], [s, 0, 0, s], [0, 1, 0, 0]], atol=1e-15)


def test_quaternion_norm_zero_and_batch_shapes():
    q = random_quats(24).reshape(2, 3, 4, 4)
    R = quat_to_rotmat(q)
    assert R.shape == (2, 3, 4, 3, 3)
    np.testing.assert_allclose(quat_to_rotmat(3.5 * q), R, atol=1e-15)     # any non-zero norm
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    np.testing.assert_array_equal(quat_to_rotmat(np.zeros((2, 4))), np.broadcast_to(np.eye(3), (2, 3, 3)))
    assert rotmat_to_quat(R).shape == (2, 3, 4, 4)
    assert rotmat_to_quat(np.eye(3)).shape == (4,)


def test_quaternion_round_trip_picks_w_non_negative():
    q = random_quats(500, seed=5)
    back = rotmat_to_quat(quat_to_rotmat(q))
    assert (back[:, 0] >= 0).all()
    np.testing.assert_allclose(back, q * np.sign(q[:, :1]), atol=1e-12)     # q and -q: one rotation


def test_torch_rotation_matches_numpy_and_is_differentiable():
    q = random_quats(50, seed=6) * 1.7
    R = quat_to_rotmat(q)
    qt = torch.tensor(q, requires_grad=True)
    Rt = quat_to_rotmat_torch(qt)
    np.testing.assert_allclose(Rt.detach().numpy(), R, atol=1e-15)
    assert quat_to_rotmat_torch(torch.zeros(3, 4)).equal(torch.eye(3).expand(3, 3, 3))
    Rt[:, :, 2].sum().backward()
    assert torch.isfinite(qt.grad).all() and qt.grad.abs().sum() > 0
    # the rotation does not depend on the quaternion's length: no gradient along q itself
    np.testing.assert_allclose((qt.grad * qt).sum(1).detach().numpy(), 0.0, atol=1e-12)


# ---- surfaces ---------------------------------------------------------------------------------

def test_sample_surface_is_uniform_over_area_and_reproducible():
    import trimesh

    # two triangles in the plane z = 0 with areas 0.5 and 1.5: a quarter of the samples on the first
    mesh = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [2, 3, 0], [1, 0.0, 0]],
                           [[0, 1, 2], [5, 3, 4]], process=False)
    pts = sample_surface(mesh, 20_000, seed=3)
    assert pts.shape == (20_000, 3) and pts.dtype == np.float64
    np.testing.assert_array_equal(pts, sample_surface(mesh, 20_000, seed=3))
    assert not np.array_equal(pts, sample_surface(mesh, 20_000, seed=4))
    np.testing.assert_array_equal(pts[:, 2], 0.0)
    first = pts[:, 0] + pts[:, 1] <= 1.0 + 1e-12
    assert abs(first.mean() - 0.25) < 0.015
    # uniform inside a triangle: the centroid of the samples is the triangle's centroid
    np.testing.assert_allclose(pts[first, :2].mean(0), [1 / 3, 1 / 3], atol=0.01)
    closest, dist, _ = trimesh.proximity.closest_point(mesh, pts[:500])
    assert dist.max() < 1e-12


def test_sample_surface_vertices_and_degenerate_mesh():
    import trimesh

    box = trimesh.creation.box([0.2, 0.3, 0.4])
    pts = sample_surface(box, 100, seed=0, with_vertices=True)
    assert pts.shape == (108, 3)
    np.testing.assert_array_equal(pts[100:], box.vertices)
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], process=False)   # no area
    np.testing.assert_array_equal(sample_surface(flat, 10), flat.vertices)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_depth_to_world_ignores_non_finite_depth(bad):
    depth = np.full((2, 2), bad)
    depth[1, 1] = 1.0
    pts, v, u = depth_to_world(depth, K, np.eye(4))
    assert np.isfinite(pts).all() and (v.tolist(), u.tolist()) == ([1], [1])


def test_scale_intrinsics_keeps_the_view():
    """A camera point lands on the same spot of the image at any resolution: pixel u of the coarse
    image covers fine pixels s u .. s u + s - 1, whose mean index is the coarse pixel's centre."""
    from psimap.transforms import scale_intrinsics

    p = np.array([[0.3, -0.2, 2.0], [-1.0, 0.5, 4.0]])
    for s in (2, 3, 0.5, 1.7):
        K2 = scale_intrinsics(K, s)
        u, v = camera_to_pixels(p[:, 0], p[:, 1], p[:, 2], K)
        u2, v2 = camera_to_pixels(p[:, 0], p[:, 1], p[:, 2], K2)
        np.testing.assert_allclose(u2, (u + 0.5) * s - 0.5, atol=1e-12)
        np.testing.assert_allclose(v2, (v + 0.5) * s - 0.5, atol=1e-12)
    np.testing.assert_array_equal(scale_intrinsics(K, 1), K)
    assert scale_intrinsics(K, 2)[0, 2] == 100.5 and scale_intrinsics(K, 2)[1, 1] == 400.0
