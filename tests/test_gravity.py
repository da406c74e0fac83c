"""Gravity from a capture's surfaces and cameras, in whatever frame the capture came (issue #16 §2).

Scenes that break the Z-up assumption: the same room in Y-up (phones), Z-down (a robot's hand-eye
frame) and arbitrary (COLMAP) frames; a tabletop seen by a wrist camera looking straight down with a
fixed yaw (the upright-camera cue points sideways there); a corridor whose walls outweigh its floor.
"""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from psimap import PsimapError
from psimap.camera import camera_rig, look_at
from psimap.geometry.gravity import (estimate_up, parse_up, resolve_up, rotation_to_z_up, snap_to_axis,
                                     up_scores)


def _samples(meshes, n=20000, seed=0):
    """points, normals, weights of an even surface sampling of the meshes (weights: equal area)."""
    m = trimesh.util.concatenate(meshes)
    pts, face = trimesh.sample.sample_surface(m, n, seed=seed)
    return pts, m.face_normals[face], np.full(len(pts), 1.0 / len(pts))


def _room(w=6.0, d=3.0, h=2.8, ceiling=True, furniture=True):
    """An open box room (inward-facing walls), a table and two boxes on it."""
    parts = [trimesh.creation.box(extents=[w, d, 0.02]).apply_translation([0, 0, -0.01])]
    for sx in (-1, 1):
        parts.append(trimesh.creation.box(extents=[0.02, d, h]).apply_translation([sx * w / 2, 0, h / 2]))
    for sy in (-1, 1):
        parts.append(trimesh.creation.box(extents=[w, 0.02, h]).apply_translation([0, sy * d / 2, h / 2]))
    if ceiling:
        parts.append(trimesh.creation.box(extents=[w, d, 0.02]).apply_translation([0, 0, h]))
    if furniture:
        parts.append(trimesh.creation.box(extents=[1.2, 0.8, 0.04]).apply_translation([0.5, 0.2, 0.74]))
        parts.append(trimesh.creation.box(extents=[0.2, 0.15, 0.1]).apply_translation([0.4, 0.1, 0.81]))
        parts.append(trimesh.creation.cylinder(radius=0.04, height=0.12).apply_translation([0.7, 0.3, 0.82]))
    return parts


def _handheld(n=24, seed=0, w=6.0, d=3.0):
    rng = np.random.default_rng(seed)
    c2w = []
    for _ in range(n):
        eye = np.array([rng.uniform(-w / 3, w / 3), rng.uniform(-d / 4, d / 4), rng.uniform(1.2, 1.7)])
        target = np.array([rng.uniform(-w / 2, w / 2), rng.uniform(-d / 2, d / 2), rng.uniform(0.2, 1.4)])
        up = np.array([rng.normal(0, 0.1), rng.normal(0, 0.1), 1.0])          # a little roll
        c2w.append(look_at(eye, target, up))
    return np.stack(c2w)


def _wrist_top_down(n=16, seed=0):
    """A robot wrist camera over a table looking straight down, always with the same yaw."""
    rng = np.random.default_rng(seed)
    c2w = []
    for _ in range(n):
        eye = np.array([0.5 + rng.uniform(-0.2, 0.2), 0.2 + rng.uniform(-0.15, 0.15), 1.25])
        c2w.append(look_at(eye, eye - [0, 0, 1.0], up=(1.0, 0.0, 0.0)))
    return np.stack(c2w)


def _rotated(R, pts, nrm, c2w):
    T = np.eye(4)
    T[:3, :3] = R
    return pts @ R.T, nrm @ R.T, T @ c2w


FRAMES = {"z-up": np.eye(3), "y-up": Rotation.from_euler("x", -90, degrees=True).as_matrix(),
          "z-down": Rotation.from_euler("x", 180, degrees=True).as_matrix(),
          "colmap": Rotation.from_euler("zyx", [37, -71, 112], degrees=True).as_matrix()}


def _angle(a, b):
    return np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


@pytest.mark.parametrize("frame", list(FRAMES))
@pytest.mark.parametrize("ceiling", [True, False])
def test_room_up_in_any_frame(frame, ceiling):
    pts, nrm, w = _samples(_room(ceiling=ceiling))
    R = FRAMES[frame]
    P, N, C = _rotated(R, pts, nrm, _handheld())
    est = estimate_up(P, N, w, C)
    true_up = R @ [0, 0, 1]
    assert _angle(est.up, true_up) < 0.5, (frame, est.up, est.scores)
    assert est.margin > 0.3
    # the rotation takes the estimate to +z, and the capture's up to within the estimate's error
    np.testing.assert_allclose(est.rotation @ est.up, [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(est.rotation), 1.0, atol=1e-12)
    if frame != "colmap":        # axis-aligned frames are snapped exactly
        np.testing.assert_array_equal(est.up, true_up.round())


@pytest.mark.parametrize("frame", list(FRAMES))
def test_top_down_wrist_camera_over_a_table(frame):
    """The image's up points along the table here (a fixed-yaw wrist): only the supports and the
    viewing direction tell gravity; distant walls are seen too."""
    parts = _room(w=7.0, d=5.0, ceiling=False)
    pts, nrm, w = _samples(parts)
    R = FRAMES[frame]
    P, N, C = _rotated(R, pts, nrm, _wrist_top_down())
    est = estimate_up(P, N, w, C)
    assert _angle(est.up, R @ [0, 0, 1]) < 0.5, (frame, est.scores)
    # the upright-camera cue alone would have picked the robot's x axis
    assert up_scores(R @ [1, 0, 0], N, w, -C[:, :3, 1], C[:, :3, 2])["upright"] > 0.99


def test_corridor_whose_walls_outweigh_the_floor():
    """Walls 2x the floor's area: the supports' sign and the cameras still find the floor."""
    parts = _room(w=12.0, d=1.6, h=3.0, ceiling=False, furniture=False)
    assert sum(m.area for m in parts[1:]) > 2 * parts[0].area
    pts, nrm, w = _samples(parts)
    R = FRAMES["y-up"]
    P, N, C = _rotated(R, pts, nrm, _handheld(w=12.0, d=1.6))
    est = estimate_up(P, N, w, C)
    np.testing.assert_array_equal(est.up, [0, 1, 0])


def test_tilted_capture_is_levelled_to_the_floor():
    """A SLAM world 4 degrees off gravity: the estimate is the floor normal, not the nearest axis."""
    R = Rotation.from_euler("xy", [4.0, -2.0], degrees=True).as_matrix()
    pts, nrm, w = _samples(_room())
    P, N, C = _rotated(R, pts, nrm, _handheld())
    est = estimate_up(P, N, w, C)
    assert _angle(est.up, R @ [0, 0, 1]) < 0.3
    assert _angle(est.up, [0, 0, 1]) > 4.0


def test_noisy_normals_and_bad_rows():
    rng = np.random.default_rng(1)
    pts, nrm, w = _samples(_room())
    nrm = nrm + rng.normal(0, 0.15, nrm.shape)             # ~9 degrees of normal noise
    nrm[:50] = np.nan
    w = w.copy()
    w[50:60] = 0
    pts[60:70] = np.inf
    R = FRAMES["colmap"]
    with np.errstate(invalid="ignore"):
        P, N, C = _rotated(R, pts, nrm, _handheld())
    est = estimate_up(P, N, w, C)
    assert _angle(est.up, R @ [0, 0, 1]) < 1.0


def test_cameras_only_and_nothing_at_all():
    R = FRAMES["y-up"]
    C = np.einsum("ij,njk->nik", np.block([[R, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]), _handheld())
    est = estimate_up(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), C)
    assert _angle(est.up, [0, 1, 0]) < 20
    none = estimate_up(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 4, 4)))
    assert none.source == "default" and np.array_equal(none.up, [0, 0, 1])


def test_parse_and_rotation():
    assert parse_up("auto") is None and parse_up("") is None
    np.testing.assert_array_equal(parse_up("-Y"), [0, -1, 0])
    np.testing.assert_allclose(parse_up("0,0,2"), [0, 0, 1])
    for bad in ("up", "1,2", "0,0,0", "nan,0,1"):
        with pytest.raises(PsimapError, match="--up"):
            parse_up(bad)
    rng = np.random.default_rng(0)
    for u in list(rng.normal(size=(20, 3))) + [np.array([0, 0, -1.0]), np.array([0, 0, 1.0]),
                                                np.array([1e-9, 0, -1.0])]:
        R = rotation_to_z_up(u)
        np.testing.assert_allclose(R @ (u / np.linalg.norm(u)), [0, 0, 1], atol=1e-9)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) > 0
    # y-up is a quarter turn about x: y -> z, z -> -y
    np.testing.assert_allclose(rotation_to_z_up([0, 1, 0]), [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-15)
    assert np.array_equal(snap_to_axis(np.array([0.01, 0.0, 0.99995])), [0, 0, 1])
    tilted = np.array([np.sin(np.radians(2)), 0, np.cos(np.radians(2))])
    assert np.array_equal(snap_to_axis(tilted), tilted)
    given = resolve_up("-z", None, None, None, None)
    assert given.source == "given" and np.allclose(given.rotation @ [0, 0, -1], [0, 0, 1])


# ---- on a trained map ---------------------------------------------------------------------------
def _small_scene():
    from psimap.data.frames import ClassInfo
    from psimap.scene import scene_from_meshes

    floor = trimesh.creation.box(extents=[3.0, 2.5, 0.02]).apply_translation([0, 0, -0.01])
    table = trimesh.creation.box(extents=[1.0, 0.6, 0.05]).apply_translation([0.3, 0.1, 0.72])
    box = trimesh.creation.box(extents=[0.2, 0.14, 0.12]).apply_translation([0.3, 0.1, 0.81])
    w, h, n = 64, 48, 6
    c2ws = [look_at(np.array([1.6 * np.cos(a), 1.6 * np.sin(a), 1.5]), [0.3, 0.1, 0.7])
            for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]
    cams = camera_rig(c2ws, w, h, 50.0)
    return scene_from_meshes([floor, table, box], [0, 0, 5], [1, 2, 3],
                             [ClassInfo(1, "floor", False), ClassInfo(2, "table", False), ClassInfo(3, "box", True)],
                             cams, colors=[(0.5, 0.5, 0.5), (0.6, 0.4, 0.2), (0.9, 0.1, 0.1)])


@pytest.mark.parametrize("frame", ["y-up", "z-down", "colmap"])
def test_rotated_scene_renders_the_same_and_its_up_is_found(frame):
    """A checkpoint turned into another world frame: every camera still sees the same image (the
    renderer with non-identity world rotations), the estimate finds its up, and turning it back
    restores the original map."""
    scene = _small_scene()
    R = FRAMES[frame]
    turned = scene.rotated(R)
    np.testing.assert_allclose(turned.config["world_rotation"], R, atol=1e-12)
    for i in (0, 3):
        a, b = scene.render(i), turned.render(i)
        np.testing.assert_allclose(b.depth.numpy(), a.depth.numpy(), atol=2e-4)
        np.testing.assert_allclose(b.rgb.numpy(), a.rgb.numpy(), atol=2e-3)
    est = estimate_up(*turned.up_evidence())
    assert _angle(est.up, R @ [0, 0, 1]) < 0.5
    back = turned.rotated(est.rotation)
    # a rotation about the vertical is free: compare heights and normals' vertical components
    np.testing.assert_allclose(back.surfels["means"][:, 2].numpy(), scene.surfels["means"][:, 2].numpy(),
                               atol=0.01)
    up_back = back.up_evidence()[1][:, 2]
    np.testing.assert_allclose(np.abs(up_back), np.abs(scene.up_evidence()[1][:, 2]), atol=0.01)
    if frame != "colmap":      # an axis-aligned frame comes back exactly (snapped estimate)
        np.testing.assert_allclose(est.rotation @ R, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(back.surfels["means"].numpy(), scene.surfels["means"].numpy(), atol=1e-5)


SHARED = __import__("pathlib").Path(__file__).resolve().parents[2] / "shared" / "data" / "7scenes-chess"


@pytest.mark.skipif(not SHARED.is_dir(), reason="needs ../shared/data (7-Scenes chess)")
def test_real_kinect_capture_finds_its_floor_and_table():
    """7-Scenes chess: KinectFusion's world is its first camera's frame (pitched down at the chess
    table), not gravity. The estimate is the same whatever frame the capture is given in, and in
    the frame it gives, the table top and the floor are level."""
    from psimap.data import load
    from psimap.geometry.tsdf import fuse_tsdf

    seq = load(SHARED)
    frames = [seq[i] for i in range(0, len(seq), 10)]
    mesh = fuse_tsdf([f.depth for f in frames], [f.K for f in frames], [f.c2w for f in frames], voxel_size=0.03)
    c2w = np.stack([f.c2w for f in frames])
    ups = []
    for frame in ("z-up", "colmap"):
        R = FRAMES[frame]
        T = np.eye(4)
        T[:3, :3] = R
        est = estimate_up(mesh.triangles_center @ R.T, mesh.face_normals @ R.T, mesh.area_faces, T @ c2w)
        ups.append(R.T @ est.up)
        assert est.margin > 0.5
    assert _angle(ups[0], ups[1]) < 0.5
    assert _angle(ups[0], [0, 0, 1]) > 60         # the capture's frame is far from Z-up
    # level: the estimate is the direction the floor and the table top face, to a degree: tilting
    # it by 3 degrees either way loses level surface
    def level(u):
        return mesh.area_faces[mesh.face_normals @ u > np.cos(np.radians(3))].sum() / mesh.area_faces.sum()

    up = ups[0] / np.linalg.norm(ups[0])
    assert level(up) > 0.1
    a = np.cross(up, [1.0, 0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    for axis in (a, -a, b, -b):
        tilted = np.cos(np.radians(3)) * up + np.sin(np.radians(3)) * axis
        assert level(tilted) < level(up)


def test_normals_leaning_towards_the_cameras_are_levelled_by_the_points():
    """Surfels seen obliquely through noisy depth have normals leaning towards the camera (7-Scenes
    chess: 5.8 degrees). The points of the floor and the table top still lie on level planes: the
    estimate follows the points, not the normals' bias."""
    R = FRAMES["colmap"]
    pts, nrm, w = _samples(_room())
    horizontal = np.abs(nrm[:, 2]) > 0.9
    lean = Rotation.from_euler("x", 6.0, degrees=True).as_matrix()   # every horizontal normal tilted
    nrm = nrm.copy()
    nrm[horizontal] = nrm[horizontal] @ lean.T
    P, N, C = _rotated(R, pts, nrm, _handheld())
    est = estimate_up(P, N, w, C)
    assert _angle(est.up, R @ [0, 0, 1]) < 0.5
