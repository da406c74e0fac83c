"""Real-data layout loaders (7-Scenes, ScanNet, Replica) on tiny hand-written fixtures, layout
detection, bad input, and the shared real 7-Scenes chess frames when ../shared is present."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from psimap import PsimapError
from psimap.data import load
from psimap.data.loaders import detect_layout

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
CHESS = SHARED / "7scenes-chess"
H, W = 6, 8


def _pose(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = q, rng.normal(size=3)
    return c2w


def _save(path: Path, arr) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr).save(path)


def _rgb(rng, h=H, w=W):
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)


# --------------------------------------------------------------------------------------------------
# 7-Scenes


def _seven_scenes(root: Path, n=3, seed=0):
    rng = np.random.default_rng(seed)
    K = np.array([[5.0, 0, 3.5], [0, 5.5, 2.5], [0, 0, 1]])
    np.savetxt(root / "camera-intrinsics.txt", K) if root.mkdir(parents=True) is None else None
    truth = []
    for i in range(n):
        rgb, raw, c2w = _rgb(rng), rng.integers(1, 4000, (H, W)).astype(np.uint16), _pose(rng)
        raw[0, 0], raw[1, 0] = 0, 65535
        _save(root / f"frame-{i:06d}.color.png", rgb)     # png: lossless, so values compare exactly
        _save(root / f"frame-{i:06d}.depth.png", raw)
        np.savetxt(root / f"frame-{i:06d}.pose.txt", c2w)
        truth.append((rgb, raw, c2w))
    return K, truth


def test_7scenes_fixture(tmp_path):
    root = tmp_path / "chess"
    K, truth = _seven_scenes(root)
    seq = load(root)
    assert seq.layout == "7scenes" and len(seq) == 3 and seq.names[1] == "frame-000001"
    for f, (rgb, raw, c2w) in zip(seq, truth):
        np.testing.assert_allclose(f.rgb, rgb / 255.0, atol=1e-7)
        expected = raw * 0.001
        expected[raw == 65535] = 0.0                      # Kinect "no measurement"
        np.testing.assert_allclose(f.depth, expected, atol=1e-6)
        assert f.depth[0, 0] == 0 and f.depth[1, 0] == 0
        np.testing.assert_allclose(f.K, K)
        np.testing.assert_allclose(f.c2w, c2w, atol=1e-12)
        assert f.semantic is None and f.instance is None and f.lidar is None
    # without camera-intrinsics.txt: the 7-Scenes Kinect default
    (root / "camera-intrinsics.txt").unlink()
    np.testing.assert_allclose(load(root)[0].K, [[585, 0, 320], [0, 585, 240], [0, 0, 1]])


def test_7scenes_bad_input(tmp_path):
    root = tmp_path / "s"
    _seven_scenes(root)
    (root / "frame-000002.depth.png").unlink()
    with pytest.raises(PsimapError, match=r"missing file: .*frame-000002\.depth\.png"):
        load(root)
    _save(root / "frame-000002.depth.png", np.full((H, W), 9, np.uint8))     # 8-bit depth
    with pytest.raises(PsimapError, match=r"frame-000002\.depth\.png must be a 16-bit"):
        load(root)[2]
    _save(root / "frame-000002.depth.png", np.full((H + 2, W), 900, np.uint16))
    with pytest.raises(PsimapError, match=r"frame-000002\.color\.png is 8x6 but depth image .* is 8x8"):
        load(root)[2]
    pose = np.eye(4)
    pose[2, 3] = -np.inf
    np.savetxt(root / "frame-000001.pose.txt", pose)
    with pytest.raises(PsimapError, match=r"frame-000001\.pose\.txt.*non-finite"):
        load(root)
    (root / "frame-000001.pose.txt").write_text("1 0 0\n0 1 0\n")
    with pytest.raises(PsimapError, match=r"frame-000001\.pose\.txt: pose must be a 4x4"):
        load(root)
    (root / "frame-000001.pose.txt").write_text("a b c d\n")
    with pytest.raises(PsimapError, match=r"cannot parse numbers in .*frame-000001\.pose\.txt"):
        load(root)
    (root / "camera-intrinsics.txt").write_text("0 0 0\n0 0 0\n0 0 1\n")
    with pytest.raises(PsimapError, match="camera-intrinsics.txt: not a pinhole"):
        load(root)


# --------------------------------------------------------------------------------------------------
# ScanNet


def _scannet(root: Path, n=4, seed=0, color_scale=2, intrinsic_depth=True):
    rng = np.random.default_rng(seed)
    ch, cw = H * color_scale, W * color_scale
    Kc = np.array([[10.0, 0, 7.5, 0], [0, 11.0, 5.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    Kd = np.array([[5.2, 0, 3.6, 0], [0, 5.4, 2.4, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    (root / "intrinsic").mkdir(parents=True)
    np.savetxt(root / "intrinsic" / "intrinsic_color.txt", Kc)
    if intrinsic_depth:
        np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", Kd)
    truth = []
    for i in range(n):
        # a colour image made of constant 2x2 blocks so the resize to depth size is exact
        rgb = np.repeat(np.repeat(_rgb(rng), color_scale, 0), color_scale, 1)
        raw = rng.integers(0, 5000, (H, W)).astype(np.uint16)
        sem = np.repeat(np.repeat(rng.integers(0, 40, (H, W)).astype(np.uint16), color_scale, 0), color_scale, 1)
        inst = np.repeat(np.repeat(rng.integers(0, 300, (H, W)).astype(np.uint16), color_scale, 0),
                         color_scale, 1)
        c2w = _pose(rng)
        _save(root / "color" / f"{i}.png", rgb)
        _save(root / "depth" / f"{i}.png", raw)
        _save(root / "label-filt" / f"{i}.png", sem)
        _save(root / "instance-filt" / f"{i}.png", inst)
        (root / "pose").mkdir(exist_ok=True)
        np.savetxt(root / "pose" / f"{i}.txt", c2w)
        truth.append((rgb, raw, sem, inst, c2w))
    return Kc[:3, :3], Kd[:3, :3], truth


def test_scannet_fixture(tmp_path):
    root = tmp_path / "scene0000_00"
    Kc, Kd, truth = _scannet(root, n=11)          # 11 frames: numeric (not lexicographic) order
    (tmp_path / "scannetv2-labels.combined.tsv").write_text(
        "id\traw_category\tcategory\n1\twall\twall\n5\tchair\tchair\n")
    # a lost-tracking frame as real ScanNet writes it
    np.savetxt(root / "pose" / "3.txt", np.full((4, 4), -np.inf))
    with pytest.warns(UserWarning, match=r"skipped 1 of 11 frames with non-finite poses.*pose/3\.txt"):
        seq = load(root)
    assert seq.layout == "scannet" and len(seq) == 10
    assert seq.names == ["0", "1", "2", "4", "5", "6", "7", "8", "9", "10"]
    assert [(c.id, c.name, c.isthing) for c in seq.classes] == [(1, "wall", False), (5, "chair", True)]
    for f, name in zip(seq, seq.names):
        rgb, raw, sem, inst, c2w = truth[int(name)]
        assert f.rgb.shape == (H, W, 3)             # colour resized to the depth size
        np.testing.assert_allclose(f.rgb, rgb[::2, ::2] / 255.0, atol=1e-7)   # area average of 2x2 blocks
        np.testing.assert_allclose(f.depth, raw * 0.001, atol=1e-6)
        np.testing.assert_array_equal(f.semantic, sem[::2, ::2])   # nearest: ids never blended
        np.testing.assert_array_equal(f.instance, inst[::2, ::2])
        np.testing.assert_array_equal(f.gt_instance, f.instance)
        np.testing.assert_array_equal(f.gt_semantic, f.semantic)
        np.testing.assert_allclose(f.K, Kd)
        np.testing.assert_allclose(f.c2w, c2w, atol=1e-12)


def test_scannet_color_intrinsics_scaled(tmp_path):
    root = tmp_path / "scan"
    Kc, _, _ = _scannet(root, n=1, intrinsic_depth=False)
    K = load(root)[0].K
    # half resolution: f halves; centres map by the pixel-corner rule (c + 0.5) / 2 - 0.5
    np.testing.assert_allclose(K, [[5.0, 0, 3.5], [0, 5.5, 2.5], [0, 0, 1]])


def test_scannet_bad_input(tmp_path):
    root = tmp_path / "scan"
    _scannet(root, n=2)
    for i in range(2):
        np.savetxt(root / "pose" / f"{i}.txt", np.full((4, 4), -np.inf))
    with pytest.warns(UserWarning), pytest.raises(PsimapError, match="every pose is non-finite"):
        load(root)
    np.savetxt(root / "pose" / "0.txt", np.eye(4))
    (root / "pose" / "1.txt").unlink()
    with pytest.raises(PsimapError, match=r"missing file: .*pose/1\.txt"):
        load(root)
    np.savetxt(root / "pose" / "1.txt", np.eye(4))
    (root / "instance-filt" / "1.png").unlink()
    with pytest.raises(PsimapError, match=r"missing file: .*instance-filt/1\.png"):
        load(root)
    _save(root / "instance-filt" / "1.png", np.zeros((12, 16, 3), np.uint8))       # RGB, not ids
    with pytest.raises(PsimapError, match=r"instance-filt/1\.png must be a single-channel"):
        load(root)[1]
    _save(root / "instance-filt" / "1.png", np.zeros((12, 16), np.uint16))
    _save(root / "depth" / "1.png", np.zeros((H + 1, W), np.uint16))
    with pytest.raises(PsimapError, match=r"depth/1\.png is 8x7, expected 8x6"):
        load(root)[1]
    for name in ("intrinsic_depth.txt", "intrinsic_color.txt"):
        (root / "intrinsic" / name).unlink()
    with pytest.raises(PsimapError, match="intrinsic_depth.txt"):
        load(root)


# --------------------------------------------------------------------------------------------------
# Replica (NICE-SLAM layout)


def _replica(root: Path, n=3, seed=0, cam=True):
    rng = np.random.default_rng(seed)
    (root / "results").mkdir(parents=True)
    truth, rows = [], []
    for i in range(n):
        rgb, raw, c2w = _rgb(rng), rng.integers(0, 65535, (H, W)).astype(np.uint16), _pose(rng)
        _save(root / "results" / f"frame{i:06d}.png", rgb)
        _save(root / "results" / f"depth{i:06d}.png", raw)
        rows.append(" ".join(repr(float(v)) for v in c2w.reshape(-1)))
        truth.append((rgb, raw, c2w))
    (root / "traj.txt").write_text("\n".join(rows) + "\n")
    if cam:
        (root.parent / "cam_params.json").write_text(json.dumps(
            {"camera": {"w": W, "h": H, "fx": 6.0, "fy": 6.5, "cx": 3.5, "cy": 2.5, "scale": 6553.5}}))
    return truth


def test_replica_fixture(tmp_path):
    root = tmp_path / "room0"
    truth = _replica(root)
    seq = load(root)
    assert seq.layout == "replica" and len(seq) == 3 and seq.names == ["frame000000", "frame000001",
                                                                        "frame000002"]
    for f, (rgb, raw, c2w) in zip(seq, truth):
        np.testing.assert_allclose(f.rgb, rgb / 255.0, atol=1e-7)
        np.testing.assert_allclose(f.depth, raw / 6553.5, rtol=1e-6, atol=1e-7)
        assert 0 <= f.depth.max() <= 10.0
        np.testing.assert_allclose(f.K, [[6.0, 0, 3.5], [0, 6.5, 2.5], [0, 0, 1]])
        np.testing.assert_allclose(f.c2w, c2w, atol=1e-12)


def test_replica_bad_input(tmp_path):
    root = tmp_path / "room0"
    _replica(root, cam=False)
    # no cam_params.json: the standard Replica camera, whose size these 8x6 images do not have
    with pytest.raises(PsimapError, match=r"depth000000\.png is 8x6 but the camera is 1200x680"):
        load(root)[0]
    rows = (root / "traj.txt").read_text().splitlines()
    (root / "traj.txt").write_text("\n".join(rows[:2]) + "\n")
    with pytest.raises(PsimapError, match=r"traj\.txt has 2 poses for 3 frames"):
        load(root)
    (root / "traj.txt").write_text("\n".join(rows[:2] + [" ".join(rows[2].split()[:15])]))
    with pytest.raises(PsimapError, match=r"traj\.txt line 3: expected 16 numbers"):
        load(root)
    (root / "traj.txt").write_text("\n".join(rows[:2] + [rows[2].replace(rows[2].split()[3], "nan", 1)]))
    with pytest.raises(PsimapError, match=r"traj\.txt line 3.*non-finite"):
        load(root)
    (root / "traj.txt").write_text("\n".join(rows))
    (root / "cam_params.json").write_text('{"camera": {"w": 8}}')
    with pytest.raises(PsimapError, match="cam_params.json: expected"):
        load(root)
    (root / "results" / "depth000001.png").unlink()
    with pytest.raises(PsimapError, match=r"missing file: .*depth000001\.png"):
        load(root)


# --------------------------------------------------------------------------------------------------
# detection


def test_detect_layout_and_unknown_folders(tmp_path):
    with pytest.raises(PsimapError, match="no such file or folder"):
        load(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(PsimapError, match="not a recognised layout"):
        load(tmp_path / "empty")
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(PsimapError, match="expected a scene folder"):
        load(tmp_path / "x.txt")
    _seven_scenes(tmp_path / "a")
    _scannet(tmp_path / "b", n=1)
    _replica(tmp_path / "c" / "room", n=1)
    assert [detect_layout(tmp_path / p) for p in ("a", "b", "c/room")] == ["7scenes", "scannet", "replica"]


# --------------------------------------------------------------------------------------------------
# real data


def _reprojection(a, b, c2w_a=None):
    """Back-project frame a's depth to world, project into frame b; returns (median |z_b - depth_b|
    in metres, fraction within 5 cm) over pixels valid in both."""
    v, u = np.nonzero(a.depth > 0)
    z = a.depth[v, u].astype(np.float64)
    pts = np.stack([(u - a.K[0, 2]) / a.K[0, 0] * z, (v - a.K[1, 2]) / a.K[1, 1] * z, z, np.ones_like(z)], 1)
    world = pts @ (a.c2w if c2w_a is None else c2w_a).T
    cam_b = world @ np.linalg.inv(b.c2w).T
    zb = cam_b[:, 2]
    front = zb > 0.1
    ub = np.round(cam_b[front, 0] / zb[front] * b.K[0, 0] + b.K[0, 2]).astype(int)
    vb = np.round(cam_b[front, 1] / zb[front] * b.K[1, 1] + b.K[1, 2]).astype(int)
    inside = (ub >= 0) & (ub < b.width) & (vb >= 0) & (vb < b.height)
    measured = b.depth[vb[inside], ub[inside]]
    valid = measured > 0
    if valid.sum() < 1000:
        return np.inf, 0.0
    err = np.abs(measured[valid] - zb[front][inside][valid])
    return float(np.median(err)), float((err < 0.05).mean())


@pytest.mark.skipif(not CHESS.is_dir(), reason="shared 7-Scenes frames not present")
def test_shared_7scenes_chess():
    seq = load(CHESS)
    assert seq.layout == "7scenes" and len(seq) == 150
    a, b = seq[0], seq[80]                    # 0.44 m apart
    for f in (a, b):
        assert f.rgb.shape == (480, 640, 3) and f.rgb.dtype == np.float32
        assert 0.0 <= f.rgb.min() and f.rgb.max() <= 1.0 and f.rgb.std() > 0.05
        assert f.depth.shape == (480, 640)
        valid = f.depth[f.depth > 0]
        assert valid.size > 0.8 * f.depth.size
        assert 0.5 < valid.min() and valid.max() < 4.5           # Kinect range of this room
        assert 1.0 < np.median(valid) < 3.0
    np.testing.assert_allclose(a.K, [[585, 0, 320], [0, 585, 240], [0, 0, 1]])
    assert np.linalg.norm(a.c2w[:3, 3] - b.c2w[:3, 3]) > 0.3
    # the same surface seen from both frames lands on the same world points (measured: 1.3 cm, 92 %)
    median, within = _reprojection(a, b)
    assert median < 0.025 and within > 0.85
    # and the check has teeth: reading the poses as world-to-camera breaks it (measured: 34 cm)
    wrong, _ = _reprojection(a, b, c2w_a=np.linalg.inv(a.c2w))
    assert wrong > 0.1


def test_each_loader_states_what_it_read_and_assumed(tmp_path):
    """`FrameSequence.report` / `describe()`: resolution, depth scale, poses, intrinsics source, skipped
    frames and assumptions, per layout."""
    _seven_scenes(tmp_path / "chess")
    (tmp_path / "chess" / "camera-intrinsics.txt").unlink()
    r = load(tmp_path / "chess").report
    assert r.resolution == (W, H) and "0.001" in r.depth and "65535" in r.depth
    assert r.assumed == ["no camera-intrinsics.txt: the 7-Scenes Kinect default intrinsics"]
    assert "585" in r.intrinsics and "OpenCV" in r.poses

    _scannet(tmp_path / "scan", n=4, intrinsic_depth=False)
    np.savetxt(tmp_path / "scan" / "pose" / "2.txt", np.full((4, 4), -np.inf))
    with pytest.warns(UserWarning):
        seq = load(tmp_path / "scan")
    r = seq.report
    assert r.skipped == ["1 of 4 frames: non-finite pose (tracking lost)"]
    assert r.intrinsics == f"intrinsic/intrinsic_color.txt scaled to the depth size {W}x{H}"
    assert r.assumed == [f"colour {2 * W}x{2 * H} resized to the depth size"] and r.labels.startswith("label-filt/")
    lines = seq.describe().splitlines()
    assert lines[0] == f"scannet {tmp_path / 'scan'}: 3 frames, {W}x{H}"
    assert lines[1] == "  skipped 1 of 4 frames: non-finite pose (tracking lost)"

    _replica(tmp_path / "replica" / "room0", cam=False)
    r = load(tmp_path / "replica" / "room0").report
    assert r.resolution == (1200, 680) and "6553.5" in r.depth
    assert r.assumed == ["no cam_params.json: the standard Replica camera"]
