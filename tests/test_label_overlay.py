"""labels.json: per-frame labels that `psimap segment` / `import-masks` add to a capture of any layout."""
from __future__ import annotations

import json

import numpy as np
import pytest

from psimap import PsimapError
from psimap.data import load
from psimap.data.frames import ClassInfo
from psimap.data.label_overlay import MANIFEST, write_label_overlay
from test_loaders import H, W, _seven_scenes

CLASSES = [ClassInfo(1, "floor", False), ClassInfo(7, "object", True)]


def _labels(seed):
    rng = np.random.default_rng(seed)
    sem = rng.choice([0, 1, 7], size=(H, W)).astype(np.uint16)
    inst = np.where(sem == 7, rng.integers(1, 300, (H, W)), 0).astype(np.uint16)
    return sem, inst


def test_overlay_supplies_labels_and_classes(tmp_path):
    root = tmp_path / "chess"
    _seven_scenes(root, n=3)
    assert load(root)[0].semantic is None
    written = {"frame-000000": _labels(0), "frame-000002": _labels(2)}
    write_label_overlay(root, CLASSES, ((n, s, i) for n, (s, i) in written.items()), source="test")
    seq = load(root)
    assert [(c.id, c.name, c.isthing) for c in seq.classes] == [(1, "floor", False), (7, "object", True)]
    for idx, name in ((0, "frame-000000"), (2, "frame-000002")):
        f = seq[idx]
        assert np.array_equal(f.semantic, written[name][0]) and np.array_equal(f.instance, written[name][1])
        assert f.instance.max() > 255                   # 16-bit ids survive
    assert seq[1].semantic is None and seq[1].instance is None   # a frame the file does not list
    assert "labels.json (test): 2 of 3 frames, 2 classes (1 things)" in seq.describe()
    # nothing temporary is left behind
    assert sorted(p.name for p in root.iterdir() if p.name.startswith(".")) == []


def test_overlay_refuses_to_replace_without_force(tmp_path):
    root = tmp_path / "chess"
    _seven_scenes(root, n=2)
    write_label_overlay(root, CLASSES, [("frame-000000", *_labels(0))], source="test")
    before = (root / "semantic" / "frame-000000.png").read_bytes()
    with pytest.raises(PsimapError, match="--force"):
        write_label_overlay(root, CLASSES, [("frame-000000", *_labels(5))], source="test")
    assert (root / "semantic" / "frame-000000.png").read_bytes() == before
    # a user's own label PNG (no labels.json yet) is protected the same way
    (root / MANIFEST).unlink()
    with pytest.raises(PsimapError, match="already exist"):
        write_label_overlay(root, CLASSES, [("frame-000000", *_labels(5))], source="test")
    write_label_overlay(root, CLASSES, [("frame-000000", *_labels(5))], source="test", force=True)
    assert np.array_equal(load(root)[0].semantic, _labels(5)[0])


def test_overlay_bad_input_writes_nothing(tmp_path):
    root = tmp_path / "chess"
    _seven_scenes(root, n=2)
    sem, inst = _labels(0)
    bad = sem.copy()
    bad[0, 0] = 9                                       # not in the class table
    with pytest.raises(PsimapError, match=r"semantic ids \[9\]"):
        write_label_overlay(root, CLASSES, [("frame-000000", sem, inst), ("frame-000001", bad, inst)],
                            source="test")
    assert not (root / MANIFEST).exists() and not (root / "semantic" / "frame-000000.png").exists()
    with pytest.raises(PsimapError, match="duplicate"):
        write_label_overlay(root, CLASSES + [ClassInfo(1, "x", True)], [("frame-000000", sem, inst)], source="t")
    # wrong size, unknown frame name, malformed manifest: one error naming the file
    write_label_overlay(root, CLASSES, [("frame-000000", sem[:, :-1], inst[:, :-1])], source="test")
    with pytest.raises(PsimapError, match=f"is {W - 1}x{H} but frame frame-000000 is {W}x{H}"):
        load(root)[0]
    meta = json.loads((root / MANIFEST).read_text())
    meta["frames"]["frame-000009"] = meta["frames"]["frame-000000"]
    (root / MANIFEST).write_text(json.dumps(meta))
    with pytest.raises(PsimapError, match="frame-000009"):
        load(root)
    (root / MANIFEST).write_text("{}")
    with pytest.raises(PsimapError, match="labels.json"):
        load(root)
