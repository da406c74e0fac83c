"""`psimap import-masks`: COCO panoptic, COCO instances (RLE / polygons, results + --images) and SAM
masks encoded here from hand-made label maps of a tiny 7-Scenes capture, imported, and compared
pixel for pixel; the overlap rule, --min-area / --min-score, the class mapping, and every bad input
(one PsimapError naming it, nothing written)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from psimap import PsimapError
from psimap.data import load
from psimap.data.masks_import import (decode_segmentation, import_masks, match_frame, min_area_pixels,
                                      paint_masks)
from test_loaders import CHESS, H, W, _seven_scenes

pytest.importorskip("pycocotools")
from pycocotools import mask as cocomask  # noqa: E402

# source categories as a COCO model names them; ids as COCO's
CATEGORIES = [{"id": 1, "name": "person", "isthing": 1}, {"id": 67, "name": "dining table", "isthing": 1},
              {"id": 47, "name": "cup", "isthing": 1}, {"id": 190, "name": "floor-wood", "isthing": 0}]
MAPPING = {"classes": {"dining table": "table", "190": {"name": "floor", "isthing": False}, "person": None}}


def _scene(seed: int):
    """Hand-made source labels of one 6x8 frame: (category [H, W], segment [H, W]) with a floor (stuff,
    two separate regions), a table, two cups, a person; 0 = void."""
    cat = np.zeros((H, W), np.int64)
    seg = np.zeros((H, W), np.int64)
    cat[4:, :], seg[4:, :] = 190, 1                   # floor
    cat[1:4, 0:5], seg[1:4, 0:5] = 67, 2              # table
    cat[0, 1:3], seg[0, 1:3] = 47, 3                  # cup 1
    cat[0:2, 6:8], seg[0:2, 6:8] = 47, 4              # cup 2
    cat[3:6, 6], seg[3:6, 6] = 1, 5                   # person (mapped to void)
    if seed:
        cat[0, 4], seg[0, 4] = 47, 6                  # a third cup
        cat[5, 0], seg[5, 0] = 0, 0                   # a void pixel
    return cat, seg


def _expected(cat):
    """(semantic names [H, W] object array) after MAPPING: '' = void."""
    names = {67: "table", 47: "cup", 190: "floor", 1: "", 0: ""}
    return np.vectorize(names.get)(cat)


def _check_import(root: Path, frame: int, cat, seg, *, thing_cats=(67, 47), names=None):
    """The imported labels of `frame` are `cat` / `seg` pixel for pixel: classes by name, every thing
    segment one instance id of its own, stuff / void / crowd instance 0."""
    seq = load(root)
    f = seq[frame]
    by_id = {c.id: c.name for c in seq.classes}
    got = np.vectorize(lambda i: by_id.get(int(i), ""))(f.semantic)
    want = _expected(cat) if names is None else names
    assert np.array_equal(got, want), (got, want)
    thing = np.isin(cat, thing_cats) & (want != "") & (seg > 0)      # seg 0: a crowd region
    assert np.all(f.instance[~thing] == 0)
    pairs = set(zip(seg[thing].tolist(), f.instance[thing].tolist()))
    assert len(pairs) == len(set(seg[thing].tolist())) == len({i for _, i in pairs})   # a bijection
    assert all(i > 0 for _, i in pairs)
    return f, seq


def _nothing_written(root: Path):
    assert not (root / "labels.json").exists()
    assert not (root / "semantic").exists() and not (root / "instance").exists()
    assert not [p for p in root.iterdir() if p.name.startswith(".psimap")]


@pytest.fixture()
def capture(tmp_path):
    root = tmp_path / "chess"
    _seven_scenes(root, n=3)
    return root


# --------------------------------------------------------------------------------------------------
# COCO panoptic


def _panoptic(folder: Path, frames: dict[str, tuple], *, name="panoptic_val", extra_segment=None):
    """COCO panoptic as Mask2Former writes it: name.json + name/<image stem>.png (id = R + 256 G + 256^2 B).
    Segment ids are made large so all three channels are used."""
    png_dir = folder / name
    png_dir.mkdir(parents=True)
    images, anns = [], []
    for k, (stem, (cat, seg)) in enumerate(frames.items()):
        sid = np.where(seg > 0, seg * 70001, 0)
        rgb = np.stack([sid % 256, sid // 256 % 256, sid // 65536], -1).astype(np.uint8)
        Image.fromarray(rgb).save(png_dir / f"{stem}.png")
        infos = [{"id": int(s) * 70001, "category_id": int(cat[seg == s][0]), "iscrowd": 0,
                  "area": int((seg == s).sum())} for s in np.unique(seg[seg > 0])]
        if extra_segment is not None and k == 0:
            infos = [i for i in infos if i["id"] != extra_segment * 70001]
        images.append({"id": 100 + k, "file_name": f"{stem}.color.png", "height": H, "width": W})
        anns.append({"image_id": 100 + k, "file_name": f"{stem}.png", "segments_info": infos})
    path = folder / f"{name}.json"
    path.write_text(json.dumps({"images": images, "annotations": anns, "categories": CATEGORIES}))
    return path


def test_coco_panoptic_round_trip_with_mapping(capture, tmp_path):
    frames = {"frame-000000": _scene(0), "frame-000001": _scene(1)}
    js = _panoptic(tmp_path / "m2f", frames)
    (tmp_path / "map.json").write_text(json.dumps(MAPPING))
    s = import_masks(capture, js, classes=tmp_path / "map.json", min_area=0)
    assert s["format"] == "coco-panoptic" and s["labelled"] == 2 and s["without_masks"] == ["frame-000002"]
    # the person is mapped to null: no class, its pixels void; the rest renamed
    # a class keeps its source id: COCO's ids survive the mapping
    assert s["classes"] == [(47, "cup", True), (67, "table", True), (190, "floor", False)]
    for i, (cat, seg) in enumerate(frames.values()):
        f, seq = _check_import(capture, i, cat, seg)
        assert f.semantic[3, 6] == 0 and f.instance[3, 6] == 0          # the person: void
    assert seq[2].semantic is None                                         # frame without masks
    assert s["kept"] == 4 + 5 and s["void_class"] == 2 and s["read"] == 5 + 6


def test_psimap_labels_output_round_trips(capture, tmp_path):
    """`psimap labels` writes panoptic.json next to its PNGs: the folder itself is --masks."""
    from psimap.data.frames import ClassInfo
    from psimap.panoptic.coco import write_coco_panoptic

    cat, seg = _scene(1)
    ids = {190: 2, 67: 5, 47: 6, 1: 9}
    sem = np.vectorize(lambda c: ids.get(c, 0))(cat)
    inst = np.where(np.isin(cat, (67, 47, 1)), seg + 40, 0)
    classes = [ClassInfo(2, "floor", False), ClassInfo(5, "table", True), ClassInfo(6, "cup", True),
               ClassInfo(9, "person", True)]
    write_coco_panoptic(tmp_path / "labels", [("frame-000001", inst, sem)], classes, {})
    s = import_masks(capture, tmp_path / "labels", min_area=0)
    assert s["format"] == "coco-panoptic" and s["without_masks"] == ["frame-000000", "frame-000002"]
    names = np.vectorize({190: "floor", 67: "table", 47: "cup", 1: "person", 0: ""}.get)(cat)
    _check_import(capture, 1, cat, seg, thing_cats=(67, 47, 1), names=names)


# --------------------------------------------------------------------------------------------------
# COCO instances


def _uncompressed(mask: np.ndarray) -> dict:
    """Uncompressed RLE written by hand (column-major runs, starting with a run of zeros)."""
    flat = mask.T.ravel().astype(np.int64)
    edges = np.flatnonzero(np.diff(flat)) + 1
    runs = np.diff(np.concatenate([[0], edges, [flat.size]])).tolist()
    if flat[0]:
        runs = [0] + runs
    return {"size": list(mask.shape), "counts": runs}


def _compressed(mask: np.ndarray) -> dict:
    rle = cocomask.encode(np.asfortranarray(mask.astype(np.uint8)))
    return {"size": rle["size"], "counts": rle["counts"].decode()}


def _instances(cat, seg, image_id, *, polygon_for=None):
    anns = []
    for k, s in enumerate(np.unique(seg[seg > 0])):
        m = seg == s
        encoding = (_compressed, _uncompressed)[k % 2](m)
        anns.append({"image_id": image_id, "category_id": int(cat[m][0]), "segmentation": encoding,
                     "iscrowd": 0, "area": int(m.sum()), "score": 0.9 - 0.01 * k})
    return anns


def test_coco_instances_dataset_and_results_round_trip(capture, tmp_path):
    cat0, seg0 = _scene(0)
    cat1, seg1 = _scene(1)
    images = [{"id": 7, "file_name": "chess/frame-000000.color.png", "height": H, "width": W},
              {"id": 8, "file_name": "frame-000001.color.png", "height": H, "width": W}]
    anns = _instances(cat0, seg0, 7) + _instances(cat1, seg1, 8)
    # a polygon (a rectangle round pixels x 2..3 of row 5 of frame 1) and a crowd region on frame 0
    poly = [[2.0, 5.0, 4.0, 5.0, 4.0, 6.0, 2.0, 6.0]]
    anns.append({"image_id": 8, "category_id": 47, "segmentation": poly, "iscrowd": 0, "score": 0.95})
    crowd = np.zeros((H, W), bool)
    crowd[5, 5] = True
    anns.append({"image_id": 7, "category_id": 47, "segmentation": _uncompressed(crowd), "iscrowd": 1})
    ds = tmp_path / "instances.json"
    ds.write_text(json.dumps({"images": images, "annotations": anns, "categories": CATEGORIES}))
    (tmp_path / "map.json").write_text(json.dumps(MAPPING))

    s = import_masks(capture, ds, classes=tmp_path / "map.json", min_area=0, min_score=0.5)
    assert s["format"] == "coco-instances" and s["labelled"] == 2
    f0, _ = _check_import(capture, 0, np.where(crowd, 47, cat0), np.where(crowd, 0, seg0))
    assert f0.semantic[5, 5] != 0 and f0.instance[5, 5] == 0            # crowd: the class, no instance
    poly_px = decode_segmentation(poly, (H, W), "test")
    cat1p, seg1p = np.where(poly_px, 47, cat1), np.where(poly_px, 99, seg1)
    assert poly_px.sum() >= 2                                           # it covers the floor it lies on
    _check_import(capture, 1, cat1p, seg1p)

    # the same annotations as a detector's results list: no images[]; --images supplies them, and
    # --min-score drops the detections under it
    results = [{k: a[k] for k in ("image_id", "category_id", "segmentation", "score") if k in a} for a in anns
               if not a.get("iscrowd")]
    for r in results:
        if r["image_id"] == 7 and r["category_id"] == 190:
            r["score"] = 0.3                                            # the floor of frame 0
    (tmp_path / "results.json").write_text(json.dumps(results))
    with pytest.raises(PsimapError, match="pass --images"):
        import_masks(capture, tmp_path / "results.json", force=True)
    s = import_masks(capture, tmp_path / "results.json", images=ds, classes=tmp_path / "map.json", min_area=0,
                     min_score=0.5, force=True)
    assert s["low_score"] == 1
    _check_import(capture, 0, np.where(cat0 == 190, 0, cat0), np.where(cat0 == 190, 0, seg0))


# --------------------------------------------------------------------------------------------------
# SAM


def _sam_folder(folder: Path, masks, scores):
    """amg.py's output for one image: <i>.png (0 / 255) + metadata.csv."""
    folder.mkdir(parents=True)
    rows = ["id,area,bbox_x0,bbox_y0,bbox_w,bbox_h,point_input_x,point_input_y,predicted_iou,stability_score,"
            "crop_box_x0,crop_box_y0,crop_box_w,crop_box_h"]
    for i, (m, (iou, stab)) in enumerate(zip(masks, scores)):
        Image.fromarray((m * 255).astype(np.uint8)).save(folder / f"{i}.png")
        rows.append(f"{i},{int(m.sum())},0,0,1,1,0.5,0.5,{iou},{stab},0,0,{W},{H}")
    (folder / "metadata.csv").write_text("\n".join(rows) + "\n")


def _sam_json(path: Path, masks, scores):
    path.write_text(json.dumps([{"segmentation": _compressed(m), "area": int(m.sum()), "predicted_iou": iou,
                                 "stability_score": stab, "bbox": [0, 0, 1, 1]}
                                for m, (iou, stab) in zip(masks, scores)]))


def test_sam_folders_and_json_round_trip_with_overlaps(capture, tmp_path):
    _, seg0 = _scene(0)
    cat, seg = _scene(1)
    segs = [seg == s for s in np.unique(seg[seg > 0])]
    scores = [(0.95, 0.97)] * len(segs)
    # one more mask: the table with the cups standing on it, scored higher than both: the cups lie
    # inside it and stay on top (the small-on-large rule); it takes the table's pixels, and the table's
    # own mask, a worse guess of the same region, keeps nothing and is dropped
    table_and_cup = (seg == 2) | (seg == 6) | (seg == 3)
    masks, sc = segs + [table_and_cup], scores + [(0.99, 0.99)]
    # and a worse, low-score duplicate of cup 2 (0.6 x 0.7 = 0.42 < --min-score 0.5)
    masks, sc = masks + [seg == 4], sc + [(0.6, 0.7)]
    _sam_folder(tmp_path / "amg" / "frame-000001.color", masks, sc)
    _sam_json(tmp_path / "amg" / "frame-000000.color.json", [seg0 == s for s in np.unique(seg0[seg0 > 0])],
              scores[:-1])
    s = import_masks(capture, tmp_path / "amg", min_area=0)
    assert s["format"] == "sam" and s["labelled"] == 2 and s["classes"] == [(1, "object", True)]
    assert s["low_score"] == 1 and s["hidden"] == 1
    for frame in (0, 1):
        c, sg = _scene(frame)
        names = np.where(sg > 0, "object", "")
        # every SAM mask is a thing of class object: floor included
        _check_import(capture, frame, c, sg, thing_cats=tuple(np.unique(c[c > 0])), names=names)


def test_overlap_rule_score_then_area_and_nesting():
    h, w = 40, 60
    big = np.zeros((h, w), bool)
    big[5:35, 5:55] = True                            # a table
    cup = np.zeros((h, w), bool)
    cup[10:16, 10:16] = True                          # lies inside the table
    left = np.zeros((h, w), bool)
    left[20:30, 51:60] = True                         # overlaps the table's right edge: 40 of its 90 pixels
    # the table scores highest, yet the cup nested in it stays on top
    owner, kept, stats = paint_masks([big, cup], [0.99, 0.5], min_area=1)
    assert np.all(owner[cup] == 1) and np.all(owner[big & ~cup] == 0) and kept == [1, 0]
    # partial overlap: the higher score takes the shared pixels, whichever is larger
    both = big & left
    owner, kept, _ = paint_masks([big, left], [0.9, 0.8], min_area=1)
    assert np.all(owner[both] == 0) and np.all(owner[left & ~big] == 1)
    owner, kept, _ = paint_masks([big, left], [0.8, 0.9], min_area=1)
    assert np.all(owner[both] == 1) and np.all(owner[big & ~left] == 0)
    # equal scores: the smaller mask on top
    owner, _, _ = paint_masks([big, left], [0.9, 0.9], min_area=1)
    assert np.all(owner[both] == 1)
    # a worse near-duplicate of the cup keeps less than half of itself: dropped, not a sliver
    dup = np.zeros((h, w), bool)
    dup[10:17, 10:16] = True
    owner, kept, stats = paint_masks([cup, dup, big], [0.9, 0.8, 0.7], min_area=1)
    assert 1 not in kept and stats["hidden"] == 1 and np.all(owner[cup] == 0)
    # --min-area: masks under it dropped, and what a mask keeps visible is held to it too
    owner, kept, stats = paint_masks([big, cup], [0.9, 0.9], min_area=37)
    assert kept == [0] and stats["small"] == 1 and np.all(owner[cup] == 0)
    sliver = np.zeros((h, w), bool)
    sliver[5:35, 54:56] = True                        # 30 x 2, half of it outside the table
    owner, kept, stats = paint_masks([big, sliver], [0.9, 0.5], min_area=31)
    assert kept == [0] and stats["hidden"] == 1
    owner, kept, stats = paint_masks([big, sliver], [0.9, 0.5], min_area=30)
    assert kept == [0, 1] and int((owner == 1).sum()) == 30
    assert min_area_pixels(0.01, (h, w)) == 24 and min_area_pixels(24, (h, w)) == 24
    assert min_area_pixels(0.0005, (480, 640)) == 154


def test_min_area_through_the_import(capture, tmp_path):
    cat, seg = _scene(1)
    segs = [seg == s for s in np.unique(seg[seg > 0])]   # areas: floor 13, table 15, cups 2, 4, 1, person 3
    _sam_json(tmp_path / "frame-000000.json", segs, [(1.0, 1.0)] * len(segs))
    s = import_masks(capture, tmp_path / "frame-000000.json", min_area=4)
    assert s["small"] == 3 and s["kept"] == 3
    f = load(capture)[0]
    assert np.array_equal(f.semantic > 0, np.isin(seg, (1, 2, 4)))
    # as a share of the image: 4 / 48 pixels
    s = import_masks(capture, tmp_path / "frame-000000.json", min_area=4 / 48, force=True)
    assert s["small"] == 3 and s["kept"] == 3


def test_frame_matching():
    names = {"frame-000000", "0", "1305031102.175304", "frame-000000.color.x"}
    assert match_frame("frame-000000.color.jpg", names) == "frame-000000"
    assert match_frame("scans/color/0.jpg", names) == "0"
    assert match_frame("1305031102.175304.png", names) == "1305031102.175304"
    assert match_frame("frame-000000.color.x.png", names) == "frame-000000.color.x"   # longest first
    assert match_frame("frame-000001.color.jpg", names) is None


# --------------------------------------------------------------------------------------------------
# bad input


def test_bad_inputs_name_the_problem_and_write_nothing(capture, tmp_path):
    frames = {"frame-000000": _scene(0)}
    m = tmp_path / "m"

    def expect(path, pattern, **kw):
        with pytest.raises(PsimapError, match=pattern):
            import_masks(capture, path, min_area=0, **kw)
        _nothing_written(capture)

    # a PNG segment segments_info does not list
    js = _panoptic(m / "a", frames, extra_segment=2)
    expect(js, r"segment ids \[140002\] are not in segments_info")
    # an unknown category id
    meta = json.loads(js.read_text())
    meta["annotations"][0]["segments_info"].append({"id": 140002, "category_id": 77})
    js.write_text(json.dumps(meta))
    expect(js, "category_id 77, which \"categories\" does not list")
    # masks for a frame the capture does not have
    js = _panoptic(m / "b", {"frame-000009": _scene(0)})
    expect(js, r"no frame of .* is named like 'frame-000009.color.png'")
    # malformed JSON, malformed RLE, an RLE of another size than its image, polygons of nothing
    (m / "bad.json").write_text("{\"annotations\": [")
    expect(m / "bad.json", "not valid JSON")
    cat, seg = _scene(0)
    img = [{"id": 1, "file_name": "frame-000000.color.png", "height": H, "width": W}]
    for segm, pattern in (({"size": [H, W], "counts": "0"}, r"malformed RLE \(runs add up to 0 pixels, not 6x8"),
                          ({"size": [H, W], "counts": [10, 5, 100]}, "malformed RLE"),
                          ({"size": [H, W], "counts": "zz{"}, "outside the RLE alphabet"),
                          ({"size": [H + 1, W], "counts": [(H + 1) * W]}, "RLE is 8x7 but its image is 8x6"),
                          ([[1, 2, 3]], "at least 3 finite"), ({"counts": "x"}, "RLE needs")):
        (m / "i.json").write_text(json.dumps({"images": img, "categories": CATEGORIES, "annotations": [
            {"image_id": 1, "category_id": 47, "segmentation": segm}]}))
        expect(m / "i.json", pattern)
    (m / "i.json").write_text(json.dumps({"images": img, "categories": CATEGORIES, "annotations": [
        {"image_id": 2, "category_id": 47, "segmentation": _compressed(seg == 2)}]}))
    expect(m / "i.json", "image_id 2 is not in")
    # a mask of another size than the frame (the image entry agrees with the mask, not the frame)
    big = np.kron(seg == 2, np.ones((2, 2), bool))
    img2 = [{"id": 1, "file_name": "frame-000000.color.png", "height": 2 * H, "width": 2 * W}]
    (m / "i.json").write_text(json.dumps({"images": img2, "categories": CATEGORIES, "annotations": [
        {"image_id": 1, "category_id": 47, "segmentation": _compressed(big)}]}))
    expect(m / "i.json", f"mask is {2 * W}x{2 * H} but frame frame-000000 is {W}x{H} .*--resize")
    # ... which --resize accepts (nearest: exactly the table again)
    import_masks(capture, m / "i.json", min_area=0, resize=True)
    assert np.array_equal(load(capture)[0].instance > 0, seg == 2)
    # labels exist now: refused without --force, before any mask is read
    expect_existing = pytest.raises(PsimapError, match="--force")
    with expect_existing:
        import_masks(capture, m / "i.json", resize=True)
    # SAM: a mask PNG of the wrong size
    sam = m / "sam" / "frame-000001"
    _sam_folder(sam, [np.ones((H + 1, W), bool)], [(0.9, 0.9)])
    with pytest.raises(PsimapError, match=f"mask is {W}x{H + 1} but frame frame-000001 is {W}x{H}"):
        import_masks(capture, sam, force=True)


def test_class_mapping_rules_and_errors(capture, tmp_path):
    frames = {"frame-000000": _scene(0)}
    js = _panoptic(tmp_path / "m", frames)
    mp = tmp_path / "map.json"
    mp.write_text(json.dumps({"classes": {"cup": "mug", "dinning table": "table"}, "unmapped": "error"}))
    with pytest.raises(PsimapError, match="'person' .* is not in the class mapping"):
        import_masks(capture, js, classes=mp)
    _nothing_written(capture)
    # "object": unmapped things become object, unmapped stuff void; a typo'd key is reported
    s = import_masks(capture, js, classes=mp, unmapped="object", min_area=0)
    assert [(n, t) for _, n, t in s["classes"]] == [("object", True), ("mug", True)]
    assert s["unused_mapping_keys"] == ["dinning table"]
    cat, _ = _scene(0)
    f = load(capture)[0]
    names = {c.id: c.name for c in load(capture).classes}
    assert {names[int(i)] for i in np.unique(f.semantic[cat == 67])} == {"object"}
    assert np.all(f.semantic[cat == 190] == 0)
    # two sources onto one class, one a thing, the other stuff: refused with the fix in the message
    mp.write_text(json.dumps({"classes": {"cup": "thing", "floor-wood": "thing"}}))
    with pytest.raises(PsimapError, match="class 'thing' is a thing class for 'cup' and a stuff class"):
        import_masks(capture, js, classes=mp, force=True)
    mp.write_text(json.dumps({"classes": {"cup": 3}}))
    with pytest.raises(PsimapError, match="expected a class name"):
        import_masks(capture, js, classes=mp, force=True)


def test_class_ids_keep_the_source_ids_unless_zero_based():
    from psimap.data.masks_import import build_classes

    cats = {3: ("cup", True), 9: ("bowl", True), 12: ("wall", False), 20: ("mug", True)}
    classes, to_class, _ = build_classes(cats, {3, 9, 12, 20}, {"mug": ("cup", None)}, "keep")
    assert [(c.id, c.name, c.isthing) for c in classes] == [(3, "cup", True), (9, "bowl", True), (12, "wall", False)]
    assert to_class == {3: 3, 9: 9, 12: 12, 20: 3}
    classes, to_class, _ = build_classes(cats, {3, 9, 12}, None, "object")
    assert [(c.id, c.name) for c in classes] == [(3, "object")] and to_class == {3: 3, 9: 3, 12: 0}
    # 0-based source ids (0 would be void): renumbered 1.. in source order; void stays void
    cats0 = {0: ("cat", True), 5: ("dog", True), 7: ("grass", False)}
    classes, to_class, _ = build_classes(cats0, {0, 5, 7}, {"7": None}, "keep")
    assert [(c.id, c.name) for c in classes] == [(1, "cat"), (2, "dog")] and to_class == {0: 1, 5: 2, 7: 0}


@pytest.mark.shared
@pytest.mark.skipif(not CHESS.is_dir(), reason="shared 7-Scenes frames not present")
def test_sam_masks_on_real_7scenes_frames(tmp_path):
    """Two real 640x480 chess frames (copied: ../shared is never written), SAM amg.py folders named as
    it names them (`frame-000001.color`), masks cut from the real depth: near / mid / far bands,
    and a small one nested in the far band with a lower score."""
    import shutil

    root = tmp_path / "chess"
    root.mkdir()
    for name in ["camera-intrinsics.txt"] + [f"frame-00000{i}.{k}" for i in (0, 1)
                                             for k in ("color.jpg", "depth.png", "pose.txt")]:
        shutil.copy(CHESS / name, root / name)
    depth = load(root)[1].depth
    valid = depth > 0
    q1, q2 = np.quantile(depth[valid], [0.33, 0.66])
    bands = [valid & (depth < q1), valid & (depth >= q1) & (depth < q2), valid & (depth >= q2)]
    ys, xs = np.nonzero(bands[2])
    nested = np.zeros_like(valid)
    nested[ys[0]:ys[0] + 40, :][:, xs.min():xs.min() + 40] = True
    nested &= bands[2]
    _sam_folder(tmp_path / "amg" / "frame-000001.color", bands + [nested], [(0.99, 0.99)] * 3 + [(0.9, 0.9)])
    s = import_masks(root, tmp_path / "amg")
    assert s["labelled"] == 1 and s["without_masks"] == ["frame-000000"] and s["kept"] == 4
    f = load(root)[1]
    assert f.instance.shape == (480, 640) and np.array_equal(f.semantic > 0, valid)
    ids = [int(np.unique(f.instance[m & ~nested])[0]) for m in bands] + [int(np.unique(f.instance[nested])[0])]
    assert len(set(ids)) == 4 and ids[3] < ids[2]      # the nested mask above the far band (ids: top first)
    assert all(len(np.unique(f.instance[m & ~nested])) == 1 for m in bands)


def test_cli_error_is_one_line_and_exit_1(capture, tmp_path):
    psimap = Path(sys.executable).parent / "psimap"
    js = _panoptic(tmp_path / "m", {"frame-000007": _scene(0)})
    r = subprocess.run([str(psimap), "import-masks", str(capture), "--masks", str(js)], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr.count("\n") == 1 and r.stderr.startswith("psimap import-masks: error: ")
    assert "frame-000007" in r.stderr
    _nothing_written(capture)
