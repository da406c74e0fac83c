"""Scene folder writer/reader, ground truth and labeled PLY: round trips and bad input."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from psimap import PsimapError
from psimap.data import ClassInfo, Frame, load
from psimap.data.scene_format import (GL_TO_CV, read_gt, read_labeled_mesh, read_lidar, read_ply,
                                      write_labeled_ply, write_scene)

H, W = 6, 8


def _rot(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def _frames(n=3, seed=0, lidar=True, labels=True):
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        c2w = np.eye(4)
        c2w[:3, :3] = _rot(rng)
        c2w[:3, 3] = rng.normal(size=3)
        depth = rng.uniform(0.3, 6.0, (H, W)).astype(np.float32)
        depth[0, 0] = 0.0                      # invalid stays invalid
        K = np.array([[7.5, 0, 3.9], [0, 7.25, 2.6], [0, 0, 1]])
        if i == 2:
            K = K * np.array([[1.1], [1.1], [1]])  # per-frame intrinsics
        frames.append(Frame(
            rgb=rng.random((H, W, 3)).astype(np.float32), depth=depth, K=K, c2w=c2w,
            semantic=rng.integers(0, 5, (H, W)).astype(np.uint16) if labels else None,
            instance=rng.integers(0, 60000, (H, W)).astype(np.uint16) if labels else None,
            lidar=rng.normal(size=(17, 4)).astype(np.float32) if lidar else None,
            name=f"f{i:03d}",
            gt_semantic=rng.integers(0, 5, (H, W)).astype(np.uint16) if labels else None,
            gt_instance=rng.integers(0, 9, (H, W)).astype(np.uint16) if labels else None))
    return frames


CLASSES = [ClassInfo(1, "floor", False), ClassInfo(2, "wall", False), ClassInfo(3, "chair", True)]


def test_round_trip(tmp_path):
    import trimesh

    frames = _frames()
    mesh = trimesh.creation.icosphere(subdivisions=1)
    nf = len(mesh.faces)
    face_inst = np.arange(nf) % 7
    face_sem = (np.arange(nf) * 3) % 4
    objs = {4: trimesh.creation.box(extents=(1, 2, 3))}
    insts = [{"id": np.int64(4), "semantic": 3, "name": "chair", "support": np.int32(0)}]
    write_scene(tmp_path / "s", frames, CLASSES, gt_mesh=mesh, gt_face_instance=face_inst,
                gt_face_semantic=face_sem, gt_objects=objs, gt_instances=insts)
    seq = load(tmp_path / "s")
    assert len(seq) == 3 and seq.layout == "psimap"
    assert [(c.id, c.name, c.isthing) for c in seq.classes] == [(1, "floor", False), (2, "wall", False),
                                                                 (3, "chair", True)]
    assert seq.names == ["f000", "f001", "f002"]
    for src, got in zip(frames, seq):
        assert got.rgb.dtype == np.float32 and got.rgb.shape == (H, W, 3)
        assert np.abs(got.rgb - src.rgb).max() <= 0.5 / 255 + 1e-6
        assert got.depth.dtype == np.float32
        assert np.abs(got.depth - src.depth).max() <= 0.0005 + 1e-6   # 1 mm quantisation, rounded
        assert got.depth[0, 0] == 0.0
        np.testing.assert_allclose(got.K, src.K, atol=1e-9)
        np.testing.assert_allclose(got.c2w, src.c2w, atol=1e-6)
        for key in ("semantic", "instance", "gt_semantic", "gt_instance"):
            np.testing.assert_array_equal(getattr(got, key), getattr(src, key))
        np.testing.assert_array_equal(got.lidar, src.lidar)
        assert got.name == src.name
    # negative index and slice
    assert seq[-1].name == "f002" and [f.name for f in seq[0:2]] == ["f000", "f001"]
    with pytest.raises(IndexError):
        seq[3]

    gt = read_gt(tmp_path / "s")
    np.testing.assert_array_equal(gt.face_instance, face_inst)
    np.testing.assert_array_equal(gt.face_semantic, face_sem)
    np.testing.assert_allclose(gt.mesh.vertices, mesh.vertices, atol=1e-6)   # float32 on disk
    np.testing.assert_array_equal(gt.mesh.faces, mesh.faces)
    assert set(gt.objects) == {4}
    assert abs(trimesh.load(gt.objects[4]).volume - 6.0) < 1e-6
    assert gt.instances == [{"id": 4, "semantic": 3, "name": "chair", "support": 0}]
    assert all(type(v) in (int, str) for v in gt.instances[0].values())


def test_pose_convention_on_disk(tmp_path):
    """transforms.json holds OpenGL camera-to-world: the camera looks along its -z axis."""
    frames = _frames(n=1, lidar=False, labels=False)
    write_scene(tmp_path / "s", frames, [])
    meta = json.loads((tmp_path / "s" / "transforms.json").read_text())
    gl = np.array(meta["frames"][0]["transform_matrix"])
    fwd_cv = frames[0].c2w[:3, 2]                   # OpenCV forward = +z
    np.testing.assert_allclose(-gl[:3, 2], fwd_cv, atol=1e-12)
    np.testing.assert_allclose(gl @ GL_TO_CV, frames[0].c2w, atol=1e-12)
    # distortion this small (a tenth of a pixel on this 8-pixel image) is ignored, and the report says so
    meta["k1"] = 0.1
    (tmp_path / "s" / "transforms.json").write_text(json.dumps(meta))
    assert any(a.endswith("px): ignored") for a in load(tmp_path / "s").report.assumed)
    meta["k1"] = 0.0
    (tmp_path / "s" / "transforms.json").write_text(json.dumps(meta))
    meta["frames"][0]["transform_matrix"] = gl[:3].tolist()     # 3x4 as some exporters write it
    (tmp_path / "s" / "transforms.json").write_text(json.dumps(meta))
    f = load(tmp_path / "s" / "transforms.json")[0]   # the json file itself also loads
    np.testing.assert_allclose(f.c2w, frames[0].c2w, atol=1e-12)
    assert f.semantic is None and f.instance is None and f.lidar is None and f.gt_instance is None


def test_write_is_atomic_and_rejects_bad_frames(tmp_path):
    frames = _frames(n=2, lidar=False)
    frames[1].c2w = frames[1].c2w.copy()
    frames[1].c2w[0, 3] = np.inf
    with pytest.raises(PsimapError, match="non-finite"):
        write_scene(tmp_path / "s", frames, CLASSES)
    assert not (tmp_path / "s").exists()
    assert list(tmp_path.iterdir()) == []            # no temp folder left behind

    frames = _frames(n=1, lidar=False)
    frames[0].depth = frames[0].depth.copy()
    frames[0].depth[1, 1] = 70.0                    # > 65.535 m at 1 mm units
    with pytest.raises(PsimapError, match="exceeds"):
        write_scene(tmp_path / "s", frames, CLASSES)
    frames[0].depth[1, 1] = np.nan                  # non-finite depth -> invalid, not an error
    frames[0].depth[1, 2] = -1.0
    write_scene(tmp_path / "s", frames, CLASSES, depth_unit_scale_factor=0.0001)
    d = load(tmp_path / "s")[0].depth
    assert d[1, 1] == 0 and d[1, 2] == 0
    assert np.abs(d - np.nan_to_num(frames[0].depth).clip(0)).max() <= 0.00005 + 1e-6

    # replacing: an existing scene folder yes, anything else no
    write_scene(tmp_path / "s", frames[:1], CLASSES)
    assert len(load(tmp_path / "s")) == 1
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    with pytest.raises(PsimapError, match="folder psimap did not write"):
        write_scene(tmp_path / "mine", frames, CLASSES)
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep me"
    with pytest.raises(PsimapError, match="reserved"):
        write_scene(tmp_path / "t", frames, [ClassInfo(0, "void", False)])
    frames[0].instance = np.full((H, W), 70000)
    with pytest.raises(PsimapError, match="0..65535"):
        write_scene(tmp_path / "t", frames, CLASSES)
    with pytest.raises(PsimapError, match="no frames"):
        write_scene(tmp_path / "t", [], CLASSES)


def test_read_bad_scene_folders(tmp_path):
    from PIL import Image

    write_scene(tmp_path / "s", _frames(n=2, lidar=False), CLASSES)
    root = tmp_path / "s"
    meta_path = root / "transforms.json"
    meta = json.loads(meta_path.read_text())

    # missing file named in the message, found at open time (not at first access)
    (root / "depth" / "f001.png").unlink()
    with pytest.raises(PsimapError, match=r"missing file: .*depth/f001\.png"):
        load(root)
    # 8-bit depth PNG
    Image.fromarray(np.full((H, W), 7, np.uint8)).save(root / "depth" / "f001.png")
    with pytest.raises(PsimapError, match=r"f001\.png must be a 16-bit"):
        load(root)[1]
    # size mismatch between colour and depth
    Image.fromarray(np.full((H, W), 700, np.uint16)).save(root / "depth" / "f001.png")
    load(root)[1]
    Image.fromarray(np.zeros((H + 1, W, 3), np.uint8)).save(root / "images" / "f001.png")
    with pytest.raises(PsimapError, match=r"images/f001\.png is 8x7"):
        load(root)[1]
    # non-finite pose
    bad = json.loads(json.dumps(meta))
    bad["frames"][0]["transform_matrix"][1][3] = float("nan")
    meta_path.write_text(json.dumps(bad))
    with pytest.raises(PsimapError, match=r"transforms\.json frame 0.*non-finite"):
        load(root)
    # not a rotation
    bad["frames"][0]["transform_matrix"] = (np.eye(4) * 2).tolist()
    meta_path.write_text(json.dumps(bad))
    with pytest.raises(PsimapError, match="not a rigid"):
        load(root)
    # garbage JSON, missing keys
    meta_path.write_text("{not json")
    with pytest.raises(PsimapError, match="not valid JSON"):
        load(root)
    meta_path.write_text(json.dumps({"frames": [{"file_path": "images/f000.png"}], "fl_x": 1}))
    with pytest.raises(PsimapError, match="needs file_path, depth_file_path"):
        load(root)
    # an image that is not an image
    meta_path.write_text(json.dumps(meta))
    (root / "images" / "f000.png").write_bytes(b"garbage")
    with pytest.raises(PsimapError, match=r"cannot read image .*f000\.png"):
        load(root)[0]


def test_labeled_ply_formats(tmp_path):
    rng = np.random.default_rng(1)
    v = rng.normal(size=(9, 3)).astype(np.float32)
    f = rng.integers(0, 9, (11, 3))
    inst = rng.integers(-5, 1 << 20, 11)
    write_labeled_ply(tmp_path / "a.ply", v, f, {"instance": inst, "semantic": inst % 3},
                      vertex_colors=rng.integers(0, 256, (9, 3)).astype(np.uint8))
    ply = read_ply(tmp_path / "a.ply")
    np.testing.assert_array_equal(ply.vertices, v)
    np.testing.assert_array_equal(ply.faces, f)
    np.testing.assert_array_equal(ply.face_props["instance"], inst)
    assert set(ply.vertex_props) == {"red", "green", "blue"}
    mesh, props = read_labeled_mesh(tmp_path / "a.ply")
    assert len(mesh.faces) == 11 and np.array_equal(props["semantic"], inst % 3)

    # the same data as ASCII and big-endian, as other tools write it
    head = ["ply", None, "element vertex 9", "property float x", "property float y", "property float z",
            "element face 11", "property list uchar int vertex_indices", "property int instance",
            "end_header"]
    rows = [" ".join(map(repr, map(float, r))) for r in v] + \
           [f"3 {a} {b} {c} {i}" for (a, b, c), i in zip(f, inst)]
    head[1] = "format ascii 1.0"
    (tmp_path / "b.ply").write_text("\n".join(head + rows) + "\n")
    head[1] = "format binary_big_endian 1.0"
    vb = v.astype(">f4").tobytes()
    fb = np.empty(11, dtype=[("n", "u1"), ("i", ">i4", (3,)), ("inst", ">i4")])
    fb["n"], fb["i"], fb["inst"] = 3, f, inst
    (tmp_path / "c.ply").write_bytes(("\n".join(head) + "\n").encode() + vb + fb.tobytes())
    for name in ("b.ply", "c.ply"):
        p = read_ply(tmp_path / name)
        np.testing.assert_allclose(p.vertices, v, atol=1e-6)
        np.testing.assert_array_equal(p.faces, f)
        np.testing.assert_array_equal(p.face_props["instance"], inst)

    # truncated, quads, out-of-range indices, not a PLY
    data = (tmp_path / "a.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(data[:-10])
    with pytest.raises(PsimapError, match="truncated"):
        read_ply(tmp_path / "t.ply")
    fq = np.empty(1, dtype=[("n", "u1"), ("i", ">i4", (4,))])
    fq["n"], fq["i"] = 4, [0, 1, 2, 3]
    qhead = "\n".join(head[:8] + ["end_header"]).replace("element face 11", "element face 1") + "\n"
    (tmp_path / "q.ply").write_bytes(qhead.encode() + vb + fq.tobytes() + b"\0" * 8)
    with pytest.raises(PsimapError, match="non-triangle"):
        read_ply(tmp_path / "q.ply")
    with pytest.raises(PsimapError, match="out of range"):
        write_labeled_ply(tmp_path / "o.ply", v, f + 9)
    (tmp_path / "n.ply").write_text("solid foo")
    with pytest.raises(PsimapError, match="not a PLY"):
        read_ply(tmp_path / "n.ply")
    # empty mesh round-trips
    write_labeled_ply(tmp_path / "e.ply", np.zeros((0, 3)), np.zeros((0, 3)), {"instance": np.zeros(0)})
    e = read_ply(tmp_path / "e.ply")
    assert e.vertices.shape == (0, 3) and e.faces.shape == (0, 3) and e.face_props["instance"].shape == (0,)


def test_read_lidar_ply_and_npy(tmp_path):
    pts = np.array([[0, 1, 2, 0.5], [3, 4, 5, 0.25]], np.float32)
    head = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n" \
           "property float z\nproperty float intensity\nend_header\n"
    (tmp_path / "l.ply").write_text(head + "\n".join(" ".join(map(str, r)) for r in pts) + "\n")
    np.testing.assert_array_equal(read_lidar(tmp_path / "l.ply"), pts)
    np.save(tmp_path / "l3.npy", pts[:, :3])
    np.testing.assert_array_equal(read_lidar(tmp_path / "l3.npy")[:, 3], [0, 0])
    np.save(tmp_path / "bad.npy", np.full((2, 4), np.nan))
    with pytest.raises(PsimapError, match="non-finite"):
        read_lidar(tmp_path / "bad.npy")
    np.save(tmp_path / "bad2.npy", np.zeros((2, 5)))
    with pytest.raises(PsimapError, match="N x 4"):
        read_lidar(tmp_path / "bad2.npy")


def test_import_is_light():
    code = "import sys, psimap.data; print('numpy' in sys.modules, 'PIL' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]
