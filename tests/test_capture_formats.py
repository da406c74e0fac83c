"""Foreign capture layouts (TUM RGB-D, BOP, nerfstudio's processed transforms.json): a few frames of a
generated scene (real geometry and labels) are written in each layout, loaded back and compared
number by number; bad input gives one PsimapError line."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from psimap import PsimapError
from psimap.data import load
from psimap.data.loaders import detect_layout
from psimap.data.scene_format import GL_TO_CV


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Six 64x48 frames of a generated room: rgb, depth (m), K, c2w, gt instance / semantic."""
    from psimap.data.synthetic import generate

    root = tmp_path_factory.mktemp("gen") / "scene"
    generate(root, seed=0, frames=6, width=64, height=48, progress=False)
    return list(load(root))


def _save(path: Path, arr) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr).save(path)


def _rgb8(f) -> np.ndarray:
    return np.round(f.rgb * 255).astype(np.uint8)


# --------------------------------------------------------------------------------------------------
# TUM RGB-D

T0 = 1305031102.0


def _tum(root: Path, frames, intrinsics=True) -> list[float]:
    """TUM sequence of `frames`; groundtruth samples 5 ms either side of each colour timestamp,
    turned by -/+ 0.2 rad about z and shifted -/+ 1 cm, so only slerp + lerp at the colour time
    gives the frame's pose back. Returns the colour timestamps."""
    root.mkdir(parents=True)
    rgb_lines, depth_lines, gt_lines = ["# color images", "# timestamp filename"], ["# depth"], \
        ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    stamps = []
    for i, f in enumerate(frames):
        t = T0 + i / 30.0
        stamps.append(t)
        _save(root / "rgb" / f"{t:.6f}.png", _rgb8(f))
        _save(root / "depth" / f"{t + 0.004:.6f}.png", np.round(f.depth * 5000).astype(np.uint16))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + 0.004:.6f} depth/{t + 0.004:.6f}.png")
        for s in (-1, 1):
            R = f.c2w[:3, :3] @ Rotation.from_rotvec([0, 0, 0.2 * s]).as_matrix()
            pos = f.c2w[:3, 3] + 0.01 * s
            q = Rotation.from_matrix(R).as_quat()                     # x y z w, TUM's order
            gt_lines.append(f"{t + 0.005 * s:.6f} " + " ".join(f"{v:.9f}" for v in (*pos, *q)))
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    if intrinsics:
        fx, fy, cx, cy = (float(v) for v in frames[0].K[[0, 1, 0, 1], [0, 1, 2, 2]])
        (root / "intrinsics.txt").write_text(f"# fx fy cx cy\n{fx!r} {fy!r} {cx!r} {cy!r}\n")
    return stamps


def test_tum_reads_back_what_was_written(tmp_path, frames):
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    stamps = _tum(root, frames)
    assert detect_layout(root) == "tum"
    seq = load(root)
    assert seq.layout == "tum" and len(seq) == len(frames) and seq.names[2] == f"{stamps[2]:.6f}"
    for f, g in zip(frames, seq):
        # slerp / lerp at the colour time (nearest-sample would be 0.2 rad / 1 cm off; a 1.3e9 s
        # timestamp in float64 carries 2e-7 s: up to 5e-5 of the 10 ms between samples)
        np.testing.assert_allclose(g.c2w, f.c2w, atol=1e-4)
        np.testing.assert_array_equal(g.depth, (np.round(f.depth * 5000) / 5000).astype(np.float32))
        np.testing.assert_array_equal(g.rgb, _rgb8(f) / np.float32(255))
        np.testing.assert_allclose(g.K, f.K, rtol=1e-12)
    assert seq.report.resolution == (64, 48) and seq.report.intrinsics == "intrinsics.txt"
    assert "5000" in seq.report.depth and not seq.report.assumed and not seq.report.skipped


def test_tum_skips_frames_without_depth_or_pose_and_says_so(tmp_path, frames):
    root = tmp_path / "tum"
    stamps = _tum(root, frames[:4], intrinsics=False)
    img, dimg = f"rgb/{stamps[0]:.6f}.png", f"depth/{stamps[0] + 0.004:.6f}.png"
    far, gap = stamps[3] + 2.0, stamps[3] + 1.0
    with open(root / "groundtruth.txt", "a") as fh:          # one far sample: a 2 s gap before it
        fh.write(f"{far:.6f} 0 0 0 0 0 0 1\n")
    with open(root / "rgb.txt", "a") as fh:
        fh.write(f"{T0 - 1.0:.6f} {img}\n"                   # before the groundtruth starts
                 f"{stamps[3] + 0.5:.6f} {img}\n"            # no depth within 0.02 s
                 f"{gap:.6f} {img}\n")                       # 1 s from the nearest groundtruth sample
    with open(root / "depth.txt", "a") as fh:
        fh.write(f"{T0 - 1.0:.6f} {dimg}\n{gap + 0.003:.6f} {dimg}\n")
    with pytest.warns(UserWarning, match="skipped 1 frames: no depth image within 0.02 s") as rec:
        seq = load(root)
    assert len(seq) == 4
    assert seq.report.skipped == ["1 frames: no depth image within 0.02 s",
                                  "1 frames: outside the groundtruth time span",
                                  "1 frames: no groundtruth pose within 0.05 s"]
    assert "outside the groundtruth time span" in str(rec[0].message)
    np.testing.assert_allclose(seq[0].K, [[525, 0, 319.5], [0, 525, 239.5], [0, 0, 1]])
    text = seq.describe()
    assert text.splitlines()[0] == f"tum {root}: 4 frames, 64x48"
    assert "assumed: no intrinsics.txt: TUM's ROS default" in text and "skipped 1 frames: outside" in text


def test_tum_association_is_one_to_one_closest_first():
    from psimap.data.capture_formats import associate

    rgb = np.array([0.0, 0.010, 0.050])
    depth = np.array([0.012, 0.049, 0.100])
    # 0.010 takes 0.012 (2 ms) before 0.0 could (12 ms); 0.0 then has nothing within 20 ms.
    assert associate(rgb, depth, 0.02) == {1: 0, 2: 1}


def test_tum_bad_input(tmp_path, frames):
    root = tmp_path / "tum"
    _tum(root, frames[:2])
    gt = (root / "groundtruth.txt").read_text()
    (root / "groundtruth.txt").write_text(gt + f"{T0 + 0.001:.6f} 0 0 0 0 0 1\n")
    with pytest.raises(PsimapError, match=r"groundtruth.txt line 7: expected timestamp and 7 numbers"):
        load(root)
    (root / "groundtruth.txt").write_text(gt.replace(gt.splitlines()[3].split()[1], "nan", 1))
    with pytest.raises(PsimapError, match=r"groundtruth.txt line 4: non-finite value"):
        load(root)
    (root / "groundtruth.txt").write_text(gt)
    (root / "intrinsics.txt").write_text("525 525 319.5\n")
    with pytest.raises(PsimapError, match=r"intrinsics.txt: expected 'fx fy cx cy'"):
        load(root)
    (root / "intrinsics.txt").unlink()
    depth0 = root / (root / "depth.txt").read_text().splitlines()[1].split()[1]
    _save(depth0, np.zeros((48, 60), np.uint16))
    with pytest.raises(PsimapError, match=r"is 64x48 but depth image .* is 60x48"):
        load(root)[0]
    depth0.unlink()
    with pytest.raises(PsimapError, match=r"missing file: .*depth.*\(listed in .*depth.txt\)"):
        load(root)
    (root / "groundtruth.txt").unlink()
    with pytest.raises(PsimapError, match=r"missing file: .*groundtruth.txt"):
        load(root)


# --------------------------------------------------------------------------------------------------
# BOP


def _object_world_poses() -> dict[int, np.ndarray]:
    """Where the three BOP objects stand in the generated scene's world (static)."""
    out = {}
    for n, oid in enumerate((5, 2, 9)):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec([0.3 * n, -0.2, 0.5 + n]).as_matrix()
        T[:3, 3] = [0.4 * n - 0.3, 0.2 * n, 0.5]
        out[oid] = T
    return out


def _bop(root: Path, frames, with_w2c=True, depth_scale=0.25):
    """BOP scene: the generated scene's three largest gt instances become objects 5, 2, 9 (their gt
    masks the visible masks); object poses from _object_world_poses."""
    root.mkdir(parents=True)
    ids = np.bincount(np.concatenate([f.gt_instance.ravel() for f in frames]))
    ids[0] = 0
    inst = np.argsort(ids)[::-1][:3]
    world = _object_world_poses()
    cams, gts = {}, {}
    for i, f in enumerate(frames):
        w2c = np.linalg.inv(f.c2w)
        cam = {"cam_K": f.K.ravel().tolist(), "depth_scale": depth_scale}
        if with_w2c:
            cam.update(cam_R_w2c=w2c[:3, :3].ravel().tolist(), cam_t_w2c=(w2c[:3, 3] * 1000).tolist())
        cams[str(i)] = cam
        gts[str(i)] = []
        for g, (oid, T) in enumerate(world.items()):
            m2c = w2c @ T
            gts[str(i)].append({"cam_R_m2c": m2c[:3, :3].ravel().tolist(),
                                "cam_t_m2c": (m2c[:3, 3] * 1000).tolist(), "obj_id": oid})
            _save(root / "mask_visib" / f"{i:06d}_{g:06d}.png",
                  np.where(f.gt_instance == inst[g], 255, 0).astype(np.uint8))
        _save(root / "rgb" / f"{i:06d}.png", _rgb8(f))
        _save(root / "depth" / f"{i:06d}.png", np.round(f.depth * 1000 / depth_scale).astype(np.uint16))
    (root / "scene_camera.json").write_text(json.dumps(cams))
    (root / "scene_gt.json").write_text(json.dumps(gts))
    return inst


def test_bop_reads_back_what_was_written(tmp_path, frames):
    root = tmp_path / "000048"
    inst = _bop(root, frames)
    assert detect_layout(root) == "bop"
    seq = load(root)
    assert seq.layout == "bop" and len(seq) == len(frames) and seq.names[0] == "000000"
    assert [(c.id, c.name, c.isthing) for c in seq.classes] == [(2, "obj_000002", True), (5, "obj_000005", True),
                                                                (9, "obj_000009", True)]
    for f, g in zip(frames, seq):
        np.testing.assert_allclose(g.c2w, f.c2w, atol=1e-9)
        np.testing.assert_allclose(g.K, f.K, rtol=1e-12)
        np.testing.assert_allclose(g.depth, np.round(f.depth * 4000) / 4000, atol=1e-6)   # 0.25 mm units
        np.testing.assert_array_equal(g.rgb, _rgb8(f) / np.float32(255))
        for gt_index, oid in enumerate((5, 2, 9)):
            on = f.gt_instance == inst[gt_index]
            assert np.all(g.instance[on] == gt_index + 1) and np.all(g.semantic[on] == oid)
        np.testing.assert_array_equal(g.instance == 0, ~np.isin(f.gt_instance, inst))
    assert "cam_R_w2c" in seq.report.poses and not seq.report.assumed


def test_bop_without_camera_poses_anchors_the_world_to_an_object(tmp_path, frames):
    root = tmp_path / "lm"
    _bop(root, frames, with_w2c=False)
    # Object 2 is seen twice in image 3 (a second instance): object 5, seen once everywhere, anchors.
    gts = json.loads((root / "scene_gt.json").read_text())
    gts["3"].append(dict(gts["3"][1]))
    (root / "scene_gt.json").write_text(json.dumps(gts))
    _save(root / "mask_visib" / "000003_000003.png", np.zeros((48, 64), np.uint8))
    seq = load(root)
    anchor = np.linalg.inv(_object_world_poses()[5])     # the world is object 5's frame
    for f, g in zip(frames, seq):
        np.testing.assert_allclose(g.c2w, anchor @ f.c2w, atol=1e-9)
    assert "world = the frame of obj_id 5" in seq.report.poses
    spread = float(seq.report.assumed[0].split("up to ")[1].split(" mm")[0])
    assert spread < 0.01                                   # static: objects 2 and 9 stay put
    # Move object 9 by 5 cm in one image: the scene is not static, and the loader says so.
    gts["4"][2]["cam_t_m2c"][0] += 50.0
    (root / "scene_gt.json").write_text(json.dumps(gts))
    with pytest.warns(UserWarning, match="not static"):
        seq = load(root)
    assert seq.report.assumed[0].endswith("move up to 50.0 mm in its frame")


def test_bop_overlapping_masks_go_to_the_nearer_object(tmp_path, frames):
    root = tmp_path / "bop"
    _bop(root, frames[:1])
    gts = json.loads((root / "scene_gt.json").read_text())
    z = [e["cam_t_m2c"][2] for e in gts["0"]]
    both = np.zeros((48, 64), np.uint8)
    both[10:20, 10:30] = 255
    _save(root / "mask_visib" / "000000_000000.png", both)
    _save(root / "mask_visib" / "000000_000002.png", both)
    f = load(root)[0]
    nearer = 0 if z[0] < z[2] else 2
    assert np.all(f.instance[10:20, 10:30] == nearer + 1)
    assert np.all(f.semantic[10:20, 10:30] == (5, 2, 9)[nearer])


def test_bop_bad_input(tmp_path, frames):
    root = tmp_path / "bop"
    _bop(root, frames[:2])
    cams = (root / "scene_camera.json").read_text()
    (root / "scene_camera.json").write_text(cams[:-5])
    with pytest.raises(PsimapError, match=r"scene_camera.json is not valid JSON"):
        load(root)
    bad = json.loads(cams)
    bad["1"]["cam_t_w2c"][1] = float("nan")
    (root / "scene_camera.json").write_text(json.dumps(bad))
    with pytest.raises(PsimapError, match=r"scene_camera.json image 1: cam_t_w2c has non-finite values"):
        load(root)
    (root / "scene_camera.json").write_text(cams)
    _save(root / "mask_visib" / "000001_000002.png", np.zeros((24, 32), np.uint8))
    with pytest.raises(PsimapError, match=r"mask .*000001_000002.png is 32x24 but depth image .* is 64x48"):
        load(root)[1]
    (root / "mask_visib" / "000001_000002.png").unlink()
    with pytest.raises(PsimapError, match=r"missing file: .*000001_000002.png \(scene_gt.json lists 3 objects"):
        load(root)


# --------------------------------------------------------------------------------------------------
# nerfstudio


# A Y-up world (what phones and nerfstudio write): Z-up world points map to Y-up ones.
Z_TO_Y_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])


def _nerfstudio(root: Path, frames, **extra) -> None:
    """nerfstudio processed folder: colour JPEG-free (PNG, so values compare) at twice the depth's
    resolution in images/, millimetre depth PNGs in depth/, intrinsics of the colour image in
    nerfstudio's pixel convention (centres at +0.5), poses OpenGL in a Y-up world, no `classes`."""
    root.mkdir(parents=True)
    K = frames[0].K
    meta = {"camera_model": "OPENCV", "fl_x": 2 * K[0, 0], "fl_y": 2 * K[1, 1],
            "cx": 2 * (K[0, 2] + 0.5), "cy": 2 * (K[1, 2] + 0.5), "w": 2 * frames[0].width, "h": 2 * frames[0].height,
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
            "applied_transform": np.eye(4)[:3].tolist(), "frames": [], **extra}
    for i, f in enumerate(frames):
        big = np.repeat(np.repeat(_rgb8(f), 2, axis=0), 2, axis=1)   # 2x2 blocks: the box resize is exact
        _save(root / "images" / f"frame_{i + 1:05d}.png", big)
        _save(root / "depth" / f"frame_{i + 1:05d}.png", np.round(f.depth * 1000).astype(np.uint16))
        meta["frames"].append({"file_path": f"images/frame_{i + 1:05d}.png",
                               "depth_file_path": f"depth/frame_{i + 1:05d}.png",
                               "transform_matrix": (Z_TO_Y_UP @ f.c2w @ GL_TO_CV).tolist(), "colmap_im_id": i + 1})
    (root / "transforms.json").write_text(json.dumps(meta))


def test_nerfstudio_reads_back_what_was_written(tmp_path, frames):
    root = tmp_path / "polycam"
    _nerfstudio(root, frames)
    seq = load(root)
    assert seq.layout == "nerfstudio" and len(seq) == len(frames) and seq.classes == []
    for f, g in zip(frames, seq):
        assert g.depth.shape == (48, 64) and g.rgb.shape == (48, 64, 3)
        np.testing.assert_allclose(g.K, f.K, atol=1e-9)          # halved, half-pixel convention undone
        np.testing.assert_allclose(g.c2w, Z_TO_Y_UP @ f.c2w, atol=1e-9)
        np.testing.assert_array_equal(g.depth, (np.round(f.depth * 1000).astype(np.float64) * 0.001).astype(np.float32))
        np.testing.assert_allclose(g.rgb, _rgb8(f) / 255.0, atol=1e-6)
        assert g.semantic is None
    r = seq.report
    assert r.resolution == (64, 48) and "colour 128x96 resampled to the depth size 64x48" in r.depth
    assert "cx, cy - 0.5" in r.intrinsics
    assert any("millimetres" in a for a in r.assumed) and any("Y-up" in a for a in r.assumed)


def test_nerfstudio_distortion_is_undistorted_above_half_a_pixel(tmp_path, frames):
    from psimap.data.lens import max_displacement

    k1 = 0.05
    root = tmp_path / "ns"
    _nerfstudio(root, frames[:1], k1=k1)
    # A distorted colour image that is a ramp in its own pixel coordinates: its undistorted
    # version at (u, v) must hold the distorted position of (u, v), which the model gives in
    # closed form for k1 alone: x_d = x (1 + k1 r^2).
    u, v = np.meshgrid(np.arange(128.0), np.arange(96.0))
    ramp = np.stack([u * 1.5, v * 2.0, np.zeros_like(u)], -1).astype(np.uint8)
    _save(root / "images" / "frame_00001.png", ramp)
    seq = load(root)
    g = seq[0]
    K = g.K
    uu, vv = np.meshgrid(np.arange(64.0), np.arange(48.0))
    x, y = (uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1]
    d = 1 + k1 * (x * x + y * y)
    ud, vd = K[0, 0] * x * d + K[0, 2], K[1, 1] * y * d + K[1, 2]
    inside = (ud > 1) & (ud < 62) & (vd > 1) & (vd < 46)
    assert inside.mean() > 0.8
    # the 128x96 ramp box-resized to 64x48 is the ramp at half scale, offset by half a pixel
    np.testing.assert_allclose(g.rgb[..., 0][inside] * 255, (2 * ud[inside] + 0.5) * 1.5, atol=1.0)
    np.testing.assert_allclose(g.rgb[..., 1][inside] * 255, (2 * vd[inside] + 0.5) * 2.0, atol=1.0)
    # the largest shift, at a corner of the 128x96 colour image: |(x, y)| k1 r^2 in pixels
    Kc = frames[0].K * [[2], [2], [1]] + [[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]]
    cx, cy = (np.array([0, 127.0]) - Kc[0, 2]) / Kc[0, 0], (np.array([0, 95.0]) - Kc[1, 2]) / Kc[1, 1]
    corners = [math.hypot(Kc[0, 0] * a * k1 * (a * a + b * b), Kc[1, 1] * b * k1 * (a * a + b * b))
               for a in cx for b in cy]
    assert max_displacement(Kc, (96, 128), {"k1": k1}) == pytest.approx(max(corners), rel=1e-9)
    assert any(f"up to {max(corners):.1f} px: images undistorted" in a for a in seq.report.assumed)
    assert max(corners) > 1.0
    # depth is resampled, never blended: every value is one the depth image holds
    raw = (np.round(frames[0].depth * 1000).astype(np.float64) * 0.001).astype(np.float32)
    assert set(np.unique(g.depth)) <= set(np.unique(raw)) | {0.0}
    # the same coefficients 10x smaller move pixels < 0.5 px here: ignored, and said
    _nerfstudio(tmp_path / "ns2", frames[:1], k1=k1 / 100)
    seq2 = load(tmp_path / "ns2")
    assert any(a.endswith("px): ignored") for a in seq2.report.assumed)
    np.testing.assert_allclose(seq2[0].rgb, _rgb8(frames[0]) / 255.0, atol=1e-6)


def test_nerfstudio_bad_input(tmp_path, frames):
    root = tmp_path / "ns"
    _nerfstudio(root, frames[:2])
    meta = json.loads((root / "transforms.json").read_text())

    def write(**change):
        (root / "transforms.json").write_text(json.dumps({**meta, **change}))

    write(camera_model="OPENCV_FISHEYE")
    with pytest.raises(PsimapError, match=r"camera_model 'OPENCV_FISHEYE' is not a pinhole camera"):
        load(root)
    nodepth = [dict(fr) for fr in meta["frames"]]
    del nodepth[1]["depth_file_path"]
    write(frames=nodepth)
    with pytest.raises(PsimapError, match=r"frame 1 has no depth_file_path \(nor a lidar_file_path\): psimap trains on RGB-D"):
        load(root)
    nan = [dict(fr) for fr in meta["frames"]]
    nan[0]["transform_matrix"] = [[math.nan] * 4] * 4
    write(frames=nan)
    with pytest.raises(PsimapError, match=r"frame 0 .*non-finite"):
        load(root)
    write()
    _save(root / "depth" / "frame_00002.png", np.zeros((48, 48), np.uint16))
    with pytest.raises(PsimapError, match=r"frame_00002.png is 48x48 but the colour camera is 128x96 "
                                          r"\(different aspect ratios"):
        load(root)[1]
    (root / "images" / "frame_00001.png").unlink()
    with pytest.raises(PsimapError, match=r"missing file: .*frame_00001.png \(listed in"):
        load(root)


# --------------------------------------------------------------------------------------------------
# the CLI


def test_bad_capture_through_psimap_train_is_one_line_and_no_checkpoint(tmp_path, frames, capsys):
    from psimap.cli import main

    root = tmp_path / "tum"
    _tum(root, frames[:2])
    gt = (root / "groundtruth.txt").read_text().splitlines()
    gt[3] = gt[3].rsplit(" ", 1)[0] + " inf"
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    out = tmp_path / "x.ckpt"
    assert main(["train", str(root), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("psimap train: error: ") and "groundtruth.txt line 4" in err[0]
    assert not out.exists()


def test_psimap_train_prints_what_it_read(tmp_path, frames, capsys, monkeypatch):
    """`psimap train` states how the capture was understood before training on it."""
    import psimap.train.trainer as trainer
    from psimap.cli import main

    def stop(seq, cfg, resume=None):
        raise PsimapError(f"stopped before training {len(seq)} frames")

    monkeypatch.setattr(trainer, "train", stop)
    root = tmp_path / "bop"
    _bop(root, frames[:3])
    assert main(["train", str(root), "--out", str(tmp_path / "x.ckpt")]) == 1
    err = capsys.readouterr().err.splitlines()
    assert err[0] == f"bop {root}: 3 frames, 64x48"
    assert err[1].startswith("  depth: uint16 PNG x depth_scale mm") and err[2].startswith("  poses: scene_camera.json")
    assert err[4].startswith("  labels: mask_visib/: instance = gt index + 1, class = obj_id (3 object classes)")
    assert err[-1] == "psimap train: error: stopped before training 3 frames"
    assert not (tmp_path / "x.ckpt").exists()
