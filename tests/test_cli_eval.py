"""`psimap eval` end to end on a tiny scene folder written by the test itself."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from psimap.cli import main
from raycast import labelled_depth
from psimap.camera import look_at

W, H, F = 32, 24, 22.0


def scene_mesh():
    """Floor (class 1, stuff) with two boxes on it (class 2, instances 1 and 2). Returns mesh and
    per-face semantic / instance."""
    floor = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    a = trimesh.creation.box((0.4, 0.4, 0.4))
    a.apply_translation([-0.4, 0, 0.2])
    b = trimesh.creation.box((0.3, 0.3, 0.5))
    b.apply_translation([0.4, 0.1, 0.25])
    parts = [(floor, 1, 0), (a, 2, 1), (b, 2, 2)]
    mesh = trimesh.util.concatenate([p for p, _, _ in parts])
    sem = np.concatenate([np.full(len(p.faces), s) for p, s, _ in parts])
    inst = np.concatenate([np.full(len(p.faces), i) for p, _, i in parts])
    return mesh, sem, inst


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    import open3d as o3d

    from psimap.data.frames import ClassInfo, Frame
    from psimap.data.scene_format import write_scene

    mesh, fsem, finst = scene_mesh()
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                     o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
    frames = []
    for i, ang in enumerate(np.linspace(0, 2 * np.pi, 4, endpoint=False)):
        c2w = look_at(np.array([1.8 * np.cos(ang), 1.8 * np.sin(ang), 1.2]), [0, 0, 0.2])
        depth, ginst, gsem = labelled_depth(rc, K, c2w, W, H, finst, fsem)
        frames.append(Frame(rgb=np.full((H, W, 3), 0.5, np.float32), depth=depth, K=K, c2w=c2w,
                            semantic=gsem, instance=ginst, gt_semantic=gsem, gt_instance=ginst,
                            name=f"frame_{i:03d}"))
    classes = [ClassInfo(1, "floor", False), ClassInfo(2, "box", True)]
    root = tmp_path_factory.mktemp("evaldata") / "scene"
    write_scene(root, frames, classes, gt_mesh=mesh, gt_face_instance=finst, gt_face_semantic=fsem)
    return root


def run(capsys, *args):
    rc = main(["eval", *map(str, args)])
    out, err = capsys.readouterr()
    return rc, out, err


def gt_labels(data: Path):
    from psimap.data.scene_format import read_label_png

    for p in sorted((data / "gt" / "semantic").glob("*.png")):
        yield p.stem, read_label_png(p), read_label_png(data / "gt" / "instance" / p.name)


def write_sem_inst(root: Path, maps: dict[str, tuple[np.ndarray, np.ndarray]]) -> Path:
    from PIL import Image

    for sub in ("semantic", "instance"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    for stem, (sem, inst) in maps.items():
        Image.fromarray(sem.astype(np.uint16)).save(root / "semantic" / f"{stem}.png")
        Image.fromarray(inst.astype(np.uint16)).save(root / "instance" / f"{stem}.png")
    return root


def test_gt_mesh_against_itself(data, capsys):
    rc, out, err = run(capsys, data / "gt" / "mesh.ply", data, "--json")
    assert rc == 0, err
    g = json.loads(out)["geometry"]
    assert "panoptic" not in json.loads(out)
    assert g["f1"] == 1.0 and g["precision"] == 1.0 and g["recall"] == 1.0
    assert g["chamfer_l1"] < 1e-3
    # Floor under the boxes and box bottoms are seen by no camera.
    assert 0.5 < g["gt_seen_fraction"] < 0.97
    assert g["threshold"] == 0.05 and g["n_pred_points"] >= 10_000


def test_shifted_mesh_and_threshold(data, capsys, tmp_path):
    mesh = trimesh.load(data / "gt" / "mesh.ply", force="mesh", process=False)
    mesh.apply_translation([0, 0, 0.02])
    pred = tmp_path / "shifted.obj"
    mesh.export(pred)
    rc, out, err = run(capsys, pred, data, "--json")
    assert rc == 0, err
    g = json.loads(out)["geometry"]
    # Horizontal surfaces (most of the area) are 2 cm off, vertical ones mostly 0.
    assert 0.012 < g["accuracy"] < 0.0201 and 0.012 < g["completeness"] < 0.0201
    assert g["f1"] == 1.0
    rc, out, _ = run(capsys, pred, data, "--json", "--threshold", "0.01")
    assert json.loads(out)["geometry"]["f1"] < 0.5
    # The same numbers through the Python API.
    from psimap.metrics.evaluate import evaluate

    assert evaluate(pred, data, threshold=0.01)["geometry"] == pytest.approx(
        {k: v for k, v in json.loads(out)["geometry"].items()})


def test_label_folder_consistent_and_swapped(data, capsys, tmp_path):
    gts = list(gt_labels(data))
    relabel = {1: 300, 2: 17}
    good = {s: (sem, np.vectorize(lambda v: relabel.get(v, 0))(inst)) for s, sem, inst in gts}
    rc, out, err = run(capsys, write_sem_inst(tmp_path / "good", good), data, "--json")
    assert rc == 0, err
    p = json.loads(out)["panoptic"]
    for k in ("pq", "sq", "rq", "miou", "macc", "mcov", "mwcov", "pq_frame", "pq_thing", "pq_stuff"):
        assert p[k] == 1.0, k
    assert p["n_frames"] == 4 and p["missing_frames"] == [] and p["n_gt_instances"] == 2
    # Ids of the two boxes swapped in half of the frames: per frame perfect, scene-level not.
    swapped = dict(good)
    for s, sem, inst in gts[::2]:
        swapped[s] = (sem, np.vectorize(lambda v: {1: 17, 2: 300}.get(v, 0))(inst))
    rc, out, err = run(capsys, write_sem_inst(tmp_path / "swapped", swapped), data, "--json")
    p = json.loads(out)["panoptic"]
    assert p["pq_frame"] == 1.0 and p["pq_stuff"] == 1.0 and p["miou"] == 1.0
    assert p["pq_thing"] < 0.8 and p["mcov"] < 0.8


def write_coco(root: Path, gts, skip=(), extra_id=None) -> Path:
    from PIL import Image

    root.mkdir(parents=True)
    anns = []
    for stem, sem, inst in gts:
        if stem in skip:
            continue
        seg = np.zeros(sem.shape, np.int64)
        seg[sem == 1] = 70000                          # stuff segment, id > 256^2
        seg[(sem == 2) & (inst == 1)] = 258            # ids that need the G channel
        seg[(sem == 2) & (inst == 2)] = 513
        if extra_id is not None:
            seg[0, 0] = extra_id
        rgb = np.stack([seg % 256, seg // 256 % 256, seg // 65536], -1).astype(np.uint8)
        Image.fromarray(rgb).save(root / f"{stem}.png")
        anns.append({"image_id": stem, "file_name": f"{stem}.png",
                     "segments_info": [{"id": 70000, "category_id": 1}, {"id": 258, "category_id": 2},
                                       {"id": 513, "category_id": 2}]})
    cats = [{"id": 1, "name": "floor", "isthing": 0}, {"id": 2, "name": "box", "isthing": 1}]
    (root / "panoptic.json").write_text(json.dumps({"categories": cats, "annotations": anns}))
    return root


def test_coco_panoptic_folder_and_missing_frames(data, capsys, tmp_path):
    gts = list(gt_labels(data))
    rc, out, err = run(capsys, write_coco(tmp_path / "coco", gts), data, "--json")
    assert rc == 0, err
    assert json.loads(out)["panoptic"]["pq"] == 1.0
    rc, out, err = run(capsys, write_coco(tmp_path / "coco_missing", gts, skip={gts[1][0]}), data, "--json")
    p = json.loads(out)["panoptic"]
    assert p["missing_frames"] == [gts[1][0]] and "no prediction" in err
    assert p["pq"] < 1.0 and p["miou"] < 1.0
    # The readable table says the same.
    rc, out, err = run(capsys, tmp_path / "coco_missing", data)
    assert rc == 0 and "per-frame PQ" in out and "1 frames had no prediction" in out


def test_plot_png(data, capsys, tmp_path, monkeypatch):
    """--plot draws the numbers the metrics report: read back from the figure, not the PNG bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    figs, close = [], plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: figs.append(fig) or close(fig))
    # geometry: a prediction that misses one box, so precision and recall differ
    mesh, _, finst = scene_mesh()
    pred = tmp_path / "pred.ply"
    mesh.submesh([np.flatnonzero(finst != 2)], append=True).export(pred)
    png = tmp_path / "geom.png"
    rc, out, err = run(capsys, pred, data, "--plot", png, "--samples", "5000", "--json")
    assert rc == 0, err
    g = json.loads(out)["geometry"]
    assert g["precision"] > 0.99 and g["recall"] < 0.95
    assert np.asarray(Image.open(png).convert("RGB")).std() > 20
    curves = {ln.get_label(): ln.get_data() for ln in figs[-1].axes[0].get_lines()}
    for key, name in (("precision", "precision"), ("recall", "recall"), ("f1", "F1")):
        x, y = curves[name]
        assert np.interp(g["threshold"] * 100, x, y) == pytest.approx(g[key], abs=0.02), name
    # panoptic: one frame without a prediction, so PQ (lower IoU) and RQ differ per class
    png2 = tmp_path / "pan.png"
    folder = write_coco(tmp_path / "coco", gts := list(gt_labels(data)), skip={gts[1][0]})
    rc, out, err = run(capsys, folder, data, "--json")
    per = json.loads(out)["panoptic"]["per_class"]
    rc, out, err = run(capsys, folder, data, "--plot", png2)
    assert rc == 0, err
    assert np.asarray(Image.open(png2).convert("RGB")).std() > 20
    ax = figs[-1].axes[0]
    assert [c.get_label() for c in ax.containers] == ["PQ", "SQ", "RQ", "IoU"]
    for bars, key in zip(ax.containers, ("pq", "sq", "rq", "iou")):
        np.testing.assert_allclose([b.get_height() for b in bars], [per[c][key] for c in sorted(per)],
                                   atol=1e-12, err_msg=key)
    assert any(per[c]["pq"] < per[c]["rq"] for c in per), per     # the bars can tell the metrics apart


def test_bad_inputs_give_one_line_errors(data, capsys, tmp_path):
    def error(*args, match):
        rc, out, err = run(capsys, *args)
        assert rc == 1, (out, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("psimap eval: error:") and match in lines[0], err

    error(tmp_path / "nope.ply", data, match="no such file")
    error(data / "gt" / "mesh.ply", tmp_path / "nodata", match="no such data folder")
    (tmp_path / "notes.txt").write_text("hi")
    error(tmp_path / "notes.txt", data, match="PRED must be a mesh")
    (tmp_path / "broken.ply").write_bytes(b"ply\nformat nonsense\n")
    error(tmp_path / "broken.ply", data, match="broken.ply")
    (tmp_path / "empty_labels").mkdir()
    error(tmp_path / "empty_labels", data, match="panoptic.json")
    gts = list(gt_labels(data))
    small = {s: (sem[:-1], inst[:-1]) for s, sem, inst in gts}
    error(write_sem_inst(tmp_path / "small", small), data, match="ground truth is 32x24")
    error(write_coco(tmp_path / "unlisted", gts, extra_id=999), data, match="segment id 999")
    other = {f"other_{i}": (sem, inst) for i, (_, sem, inst) in enumerate(gts)}
    error(write_sem_inst(tmp_path / "other", other), data, match="no predicted frame matches")
    (tmp_path / "bad.ckpt").write_bytes(b"not a checkpoint")
    error(tmp_path / "bad.ckpt", data, match="bad.ckpt: not a psimap scene checkpoint")
    # DATA without ground truth
    import shutil

    nogt = tmp_path / "nogt"
    shutil.copytree(data, nogt, ignore=shutil.ignore_patterns("gt"))
    error(data / "gt" / "mesh.ply", nogt, match="gt/mesh.ply not found")
    error(write_coco(tmp_path / "coco2", gts), nogt, match="ground-truth label maps")


def test_checkpoint_is_evaluated_through_its_mesh(data, capsys, tmp_path, monkeypatch):
    import sys
    import types

    ckpt = tmp_path / "scene.ckpt"
    ckpt.write_bytes(b"stand-in")
    gt_mesh = trimesh.load(data / "gt" / "mesh.ply", force="mesh", process=False)
    seen = []

    class FakeScene:
        def mesh(self):
            return gt_mesh

        def render(self, K, c2w, width, height):        # renders nothing: its fit covers nothing
            z = np.zeros((height, width), np.float32)
            return types.SimpleNamespace(alpha=z, median_depth=z, rgb=np.zeros((height, width, 3), np.float32))

    fake = types.ModuleType("psimap.scene")
    fake.load_scene = lambda path: seen.append(str(path)) or FakeScene()
    monkeypatch.setitem(sys.modules, "psimap.scene", fake)
    rc, out, err = run(capsys, ckpt, data, "--json", "--samples", "5000")
    assert rc == 0, err
    assert seen == [str(ckpt)] and json.loads(out)["geometry"]["f1"] == 1.0
    assert json.loads(out)["fit"]["coverage"] == 0.0
    # Without the training stage installed: one clear line.
    monkeypatch.setitem(sys.modules, "psimap.scene", None)
    rc, out, err = run(capsys, ckpt, data)
    assert rc == 1 and "evaluating a checkpoint needs the training stage" in err
