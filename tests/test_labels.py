"""`render_labels` / `write_labels` / `psimap labels`: 3D-consistent COCO panoptic labels from a scene."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from psimap import PsimapError
from psimap.data.frames import ClassInfo, Frame
from psimap.panoptic.coco import STUFF_OFFSET, decode_rgb

CLASSES = [ClassInfo(1, "floor", False), ClassInfo(2, "box", True), ClassInfo(3, "lamp", True)]
W, H, F = 40, 30, 34.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
CENTRES = {1: [-0.35, 0.0, 0.15], 2: [0.35, 0.1, 0.2]}


def look_at(eye, target) -> np.ndarray:
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    c2w[:3, 3] = eye
    return c2w


def cameras(n=4):
    c2ws = [look_at(np.array([1.6 * np.cos(t), 1.6 * np.sin(t), 1.0]), [0, 0, 0.15])
            for t in np.linspace(0.3, 2 * np.pi + 0.3, n, endpoint=False)]
    # one camera looking up at the empty sky: a frame with no masks at all
    c2ws.append(look_at(np.array([0.0, 0.0, 3.0]), [0.0, 0.01, 6.0]))
    return {"K": np.stack([K] * len(c2ws)), "c2w": np.stack(c2ws), "width": W, "height": H,
            "names": [f"view_{i:02d}" for i in range(len(c2ws))]}


def two_box_scene(instance_ids=(0, 1, 2), semantic_ids=(1, 2, 2)):
    from psimap.scene import scene_from_meshes

    floor = trimesh.creation.box([2.0, 2.0, 0.02], trimesh.transformations.translation_matrix([0, 0, -0.01]))
    a = trimesh.creation.box([0.3, 0.3, 0.3], trimesh.transformations.translation_matrix(CENTRES[1]))
    b = trimesh.creation.box([0.25, 0.25, 0.4], trimesh.transformations.translation_matrix(CENTRES[2]))
    return scene_from_meshes([floor, a, b], list(instance_ids), list(semantic_ids), CLASSES, cameras(),
                             spacing=0.05)


def project(c2w, p):
    pc = np.linalg.inv(c2w) @ np.r_[p, 1.0]
    u = K @ pc[:3]
    return int(u[1] / u[2]), int(u[0] / u[2])


@pytest.fixture(scope="module")
def scene():
    return two_box_scene()


def test_render_labels_are_the_3d_ids(scene):
    from psimap.panoptic.labels import render_labels

    for i in range(4):
        Kc, c2w, w, h = scene.camera(i)
        inst, sem = render_labels(scene, Kc, c2w, w, h)
        assert inst.shape == (H, W) and inst.dtype == np.int64
        assert set(np.unique(inst)) <= {0, 1, 2}
        assert set(np.unique(sem)) <= {0, 1, 2}
        for iid, centre in CENTRES.items():           # the top face centre of each box carries its id
            top = np.array(centre) + [0, 0, 0.15 if iid == 1 else 0.2]
            r, c = project(c2w, top)
            assert inst[r, c] == iid and sem[r, c] == 2
        # thing pixels are the instance pixels (up to silhouette pixels where both boxes blend:
        # the instance argmax splits their weight, the class argmax sums it); the floor is stuff
        assert ((inst > 0) == (sem == 2)).mean() > 0.98
        assert not (inst[sem == 1]).any()
        assert (sem == 1).sum() > 0.2 * H * W
    _, c2w, w, h = scene.camera(4)
    inst, sem = render_labels(scene, K, c2w, w, h)      # sky: nothing covers any pixel
    assert not inst.any() and not sem.any()


def test_chunked_channels_match_one_pass(scene, monkeypatch):
    from psimap.panoptic import labels

    Kc, c2w, w, h = scene.camera(1)
    ref = labels.render_labels(scene, Kc, c2w, w, h)
    monkeypatch.setattr(labels, "CHANNELS_PER_PASS", 1)
    chunked = labels.render_labels(scene, Kc, c2w, w, h)
    assert np.array_equal(ref[0], chunked[0]) and np.array_equal(ref[1], chunked[1])


def test_topk_one_still_labels_objects(scene):
    from psimap.panoptic.labels import render_labels

    Kc, c2w, w, h = scene.camera(0)
    full = render_labels(scene, Kc, c2w, w, h)
    k1 = render_labels(scene, Kc, c2w, w, h, topk=1)
    assert (full[0] == k1[0]).mean() > 0.95


def test_instance_class_vote():
    from psimap.panoptic.labels import instance_classes

    s = two_box_scene(semantic_ids=(1, 2, 3))
    sem = s.surfels["semantic_id"].clone()
    inst = s.surfels["instance_id"]
    idx = np.flatnonzero(inst.numpy() == 2)
    sem[idx[: len(idx) // 4]] = 2                       # a minority of box 2's surfels say "box"
    s.surfels["semantic_id"] = sem
    assert instance_classes(s) == {1: 2, 2: 3}


def read_out(out):
    from PIL import Image

    meta = json.loads((out / "panoptic.json").read_text())
    pngs = {p.stem: decode_rgb(np.asarray(Image.open(p).convert("RGB"))) for p in out.glob("*.png")}
    return meta, pngs


def test_write_labels_coco(scene, tmp_path):
    from psimap.panoptic.labels import write_labels

    out = tmp_path / "labels"
    write_labels(scene, None, out)
    meta, pngs = read_out(out)
    assert sorted(pngs) == [f"view_{i:02d}" for i in range(5)]
    assert [(c["id"], c["name"], c["isthing"]) for c in meta["categories"]] == [(1, "floor", 0), (2, "box", 1),
                                                                              (3, "lamp", 1)]
    by_file = {a["file_name"]: a for a in meta["annotations"]}
    seen = set()
    for stem, seg in pngs.items():
        ids = set(np.unique(seg).tolist()) - {0}
        assert ids <= {1, 2, STUFF_OFFSET + 1}, (stem, ids)
        seen |= ids
        segs = {s["id"]: s for s in by_file[f"{stem}.png"]["segments_info"]}
        assert set(segs) == ids
        for sid, s in segs.items():
            assert s["area"] == int((seg == sid).sum())
            assert s["category_id"] == (1 if sid == STUFF_OFFSET + 1 else 2)
    assert seen == {1, 2, STUFF_OFFSET + 1}             # the same ids in every frame
    assert by_file["view_04.png"]["segments_info"] == [] and not pngs["view_04"].any()


def test_write_labels_zero_instances(tmp_path):
    from psimap.panoptic.labels import write_labels

    s = two_box_scene(instance_ids=(0, 0, 0))
    write_labels(s, None, tmp_path / "l")
    meta, pngs = read_out(tmp_path / "l")
    ids = set().union(*(set(np.unique(p).tolist()) for p in pngs.values())) - {0}
    # boxes are a thing class without an instance: void; floor stays one stuff segment
    assert ids == {STUFF_OFFSET + 1}


def test_write_labels_frames_and_bad_input(scene, tmp_path):
    from psimap.panoptic.labels import write_labels

    Kc, c2w, w, h = scene.camera(2)
    fr = Frame(rgb=np.zeros((h, w, 3), np.float32), depth=np.zeros((h, w), np.float32), K=Kc, c2w=c2w,
               name="kitchen_0001")
    write_labels(scene, [fr], tmp_path / "one")
    assert (tmp_path / "one" / "kitchen_0001.png").is_file()
    with pytest.raises(PsimapError, match="share the image stem"):
        write_labels(scene, [fr, fr], tmp_path / "two")
    assert not (tmp_path / "two").exists()              # nothing half-written
    with pytest.raises(PsimapError, match="no such data folder"):
        write_labels(scene, tmp_path / "missing", tmp_path / "three")


def make_data(scene, root, gt_labels=False):
    """A scene folder whose frames are the scene's cameras (depth rendered from the surfels; with
    gt_labels, the scene's rendered labels as the GT label maps)."""
    from psimap.data.scene_format import write_scene
    from psimap.panoptic.labels import render_labels

    frames = []
    for i in range(len(scene.cameras["names"])):
        Kc, c2w, w, h = scene.camera(i)
        out = scene.render(i)
        depth = np.where(out.alpha.numpy() > 0.5, out.median_depth.numpy(), 0).astype(np.float32)
        gi, gs = render_labels(scene, Kc, c2w, w, h) if gt_labels else (None, None)
        frames.append(Frame(rgb=np.zeros((h, w, 3), np.float32), depth=depth, K=Kc, c2w=c2w,
                            name=f"img_{i:03d}", gt_semantic=gs, gt_instance=gi))
    return write_scene(root, frames, CLASSES)


def test_eval_checkpoint_reports_panoptic(scene, tmp_path, capsys):
    """`psimap eval scene.ckpt DATA`: DATA without gt/mesh.ply but with GT label maps -> panoptic only."""
    from psimap.cli import main
    from psimap.metrics.evaluate import evaluate

    data = make_data(scene, tmp_path / "data", gt_labels=True)
    ckpt = tmp_path / "scene.ckpt"
    scene.save(ckpt)
    res = evaluate(ckpt, data)
    assert "geometry" not in res
    p = res["panoptic"]
    assert p["pq"] == pytest.approx(1.0) and p["miou"] == pytest.approx(1.0) and p["n_gt_instances"] == 2
    # ids swapped between the boxes: still consistent, still perfect; glued into one: box PQ drops
    for ids, expect in (((0, 2, 1), 1.0), ((0, 1, 1), None)):
        other = two_box_scene(instance_ids=ids)
        other.save(tmp_path / "other.ckpt")
        p = evaluate(tmp_path / "other.ckpt", data)["panoptic"]
        if expect:
            assert p["pq"] == pytest.approx(expect)
        else:
            assert p["per_class"][2]["tp"] <= 1 and p["per_class"][2]["fn"] >= 1 and p["pq"] < 0.85
    assert main(["eval", str(ckpt), str(data), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["panoptic"]["pq"] == pytest.approx(1.0)
    # a scene without labels and DATA without gt mesh: no panoptic metrics, only its fit to the
    # frames (metrics/fit.py: DATA's depth is the scene's own render here, so it fits)
    bare = two_box_scene()
    for k in ("instance_id", "semantic_id"):
        bare.surfels.pop(k)
    bare.save(tmp_path / "bare.ckpt")
    assert main(["eval", str(tmp_path / "bare.ckpt"), str(data), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"fit"} and out["fit"]["depth_mae_cm"] < 0.1 and out["fit"]["coverage"] > 0.99


def test_cli_labels(scene, tmp_path, capsys):
    from psimap.cli import main

    ckpt = tmp_path / "scene.ckpt"
    scene.save(ckpt)
    data = make_data(scene, tmp_path / "data")
    out = tmp_path / "labels"
    assert main(["labels", str(ckpt), str(data), "--out", str(out)]) == 0
    meta, pngs = read_out(out)
    assert sorted(pngs) == [f"img_{i:03d}" for i in range(5)]
    assert len(meta["images"]) == 5
    ids = set().union(*(set(np.unique(p).tolist()) for p in pngs.values()))
    assert {1, 2, STUFF_OFFSET + 1} <= ids
    capsys.readouterr()
    # bad input: one line on stderr, exit 1, nothing written
    assert main(["labels", str(tmp_path / "nope.ckpt"), str(data), "--out", str(tmp_path / "x")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope.ckpt" in err[0]
    (tmp_path / "bad.ckpt").write_bytes(b"not a checkpoint")
    assert main(["labels", str(tmp_path / "bad.ckpt"), str(data), "--out", str(tmp_path / "x")]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"psimap labels: error: {tmp_path / 'bad.ckpt'}: not a psimap scene checkpoint (not a torch zip archive)"
    assert main(["labels", str(ckpt), str(tmp_path / "nodata"), "--out", str(tmp_path / "x")]) == 1
    assert "nodata" in capsys.readouterr().err
    assert main(["labels", str(ckpt), str(data), "--out", str(tmp_path / "x"), "--topk", "-1"]) == 1
    assert "--topk" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    # Top-K 1: each pixel takes its heaviest surfel's label: nearly the same labels (measured 99.45 %
    # of pixels), not identical (identical would mean --topk never reached the renderer)
    assert main(["labels", str(ckpt), str(data), "--out", str(tmp_path / "k1"), "--topk", "1"]) == 0
    _, pngs1 = read_out(tmp_path / "k1")
    agree = np.mean([np.mean(pngs1[k] == pngs[k]) for k in pngs])
    assert sorted(pngs1) == sorted(pngs) and 0.95 < agree < 1.0


@pytest.mark.parametrize("radius_px, min_iou", [(5.0, 0.8), (8.0, 0.9)])
def test_small_sphere_label_matches_its_projected_disc(radius_px, min_iou):
    """GT surfels of a small sphere in front of a wall: the label mask is the sphere's projected disc.

    One sample per pixel, the renderer's low-pass filter bleeds ~1 px past the limb (IoU 0.71 / 0.84
    at radius 5 / 8 px); supersampled labels stay within ~1/2 px (0.84 / 0.94).
    """
    from psimap.panoptic.labels import render_labels
    from psimap.scene import scene_from_meshes

    w, h, f = 64, 48, 60.0
    k = np.array([[f, 0, w / 2 - 0.5], [0, f, h / 2 - 0.5], [0, 0, 1.0]])
    z = 2.0
    r = radius_px * z / f
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=r)
    sphere.apply_translation([0, 0, z])
    wall = trimesh.creation.box(extents=[4, 4, 0.01])
    wall.apply_translation([0, 0, z + 0.5])
    cams = {"K": k[None], "c2w": np.eye(4)[None], "width": w, "height": h, "names": ["c"]}
    classes = [{"id": 1, "name": "wall", "isthing": False}, {"id": 2, "name": "ball", "isthing": True}]
    sc = scene_from_meshes([sphere, wall], [1, 0], [2, 1], classes, cams)
    ys, xs = np.mgrid[0:h, 0:w]
    ray = np.stack([(xs - k[0, 2]) / f, (ys - k[1, 2]) / f, np.ones((h, w))], -1)
    disc = ray[..., 2] / np.linalg.norm(ray, axis=-1) >= np.cos(np.arcsin(r / z))
    inst, sem = render_labels(sc, k, np.eye(4), w, h)
    ball = inst == 1
    assert (ball & disc).sum() / (ball | disc).sum() >= min_iou
    assert np.array_equal(ball, sem == 2)
    # the centroid is not shifted (overhang would move it towards the bleeding side)
    assert np.abs(np.argwhere(ball).mean(0) - np.argwhere(disc).mean(0)).max() < 0.35
    with pytest.raises(PsimapError, match="supersample"):
        render_labels(sc, k, np.eye(4), w, h, supersample=0)


def test_instance_pixels_take_the_instance_class(scene):
    """Surfels of one instance with mixed classes (a noisy semantic head): every pixel of that
    instance gets the instance's majority class, so no (class, instance) segment is split."""
    import torch

    from psimap.panoptic.labels import render_labels
    from psimap.scene import Scene

    s = dict(scene.surfels)
    sem = s["semantic_id"].clone()
    box1 = torch.nonzero(s["instance_id"] == 1).flatten()
    sem[box1[::4]] = 3                                   # a quarter of box 1 says "lamp"
    s["semantic_id"] = sem
    noisy = Scene(s, classes=scene.classes, cameras=scene.cameras)
    for i in range(4):
        Kc, c2w, w, h = scene.camera(i)
        inst, sem_map = render_labels(noisy, Kc, c2w, w, h)
        assert (inst == 1).sum() > 10
        assert (sem_map[inst == 1] == 2).all() and not (sem_map == 3).any()
