"""The naive lift-and-merge baseline: recovers consistent ids from shuffled per-frame ids on a clean
scene, keeps the multi-stage pipeline's known failure (a merged mask glues objects), and handles
degenerate input."""
from __future__ import annotations

import numpy as np
import pytest

from psimap import PsimapError
from psimap.data.frames import Frame
from psimap.metrics.panoptic import panoptic_metrics
from psimap.panoptic.baseline import BaselineConfig, baseline_panoptic
from test_labels import CLASSES, two_box_scene


@pytest.fixture(scope="module")
def world():
    """GT scene and frames whose instance ids are re-drawn every frame (no cross-frame tracking)."""
    from psimap.panoptic.labels import render_labels

    scene = two_box_scene()
    rng = np.random.default_rng(3)
    frames, gts = [], []
    for i in range(4):
        K, c2w, w, h = scene.camera(i)
        # one sample per pixel, as the test was built: the pseudo-labels then overlap the depth
        # footprint of each box fully (the merged-mask test glues the boxes through that overlap)
        gi, gs = render_labels(scene, K, c2w, w, h, supersample=1)
        out = scene.render(i)
        depth = np.where(out.alpha.numpy() > 0.5, out.median_depth.numpy(), 0).astype(np.float32)
        perm = np.r_[0, rng.choice(np.arange(5, 60), 2, replace=False)]
        frames.append(Frame(rgb=np.zeros((h, w, 3), np.float32), depth=depth, K=K, c2w=c2w,
                            semantic=gs.astype(np.uint16), instance=perm[gi].astype(np.uint16), name=f"f{i}"))
        gts.append((gs, gi))
    return scene, frames, gts


def score(scene, labels, frames, gts):
    from psimap.panoptic.labels import render_labels
    from psimap.scene import Scene

    s = {k: v for k, v in scene.surfels.items()}
    s["instance_id"], s["semantic_id"] = labels["instance_id"], labels["semantic_id"]
    pred = Scene(s, classes=scene.classes, cameras=scene.cameras)
    seq = []
    for f, (gs, gi) in zip(frames, gts):
        pi, ps = render_labels(pred, f.K, f.c2w, f.width, f.height, supersample=1)   # as the GT
        seq.append((ps, pi, gs, gi))
    return panoptic_metrics(seq, thing_classes=[2, 3])


def test_recovers_consistent_ids(world):
    scene, frames, gts = world
    out = baseline_panoptic(scene.surfels["means"], frames, CLASSES)
    assert out["segments"] == 2
    assert out["instance_class"] == {1: 2, 2: 2}
    gt = scene.instance_ids().numpy()
    # each true object's labelled surfels carry one predicted id, distinct between objects (unseen
    # faces, e.g. the box bottoms, may stay unlabelled)
    got = []
    for iid in (1, 2):
        lab = out["instance_id"][(gt == iid) & (out["instance_id"] > 0)]
        ids, n = np.unique(lab, return_counts=True)
        assert n.sum() > 0.4 * (gt == iid).sum() and n.max() > 0.95 * n.sum()
        got.append(ids[n.argmax()])
    assert got[0] != got[1]
    assert (out["instance_id"][gt == 0] > 0).sum() < 0.05 * (gt == 0).sum()   # voxel-sized bleed
    m = score(scene, out, frames, gts)
    assert m["pq"] > 0.85 and m["miou"] > 0.9, m


def test_merged_masks_glue_objects(world):
    scene, frames, gts = world
    merged = []
    for f in frames:                                    # a 2D model that always merges the two boxes
        inst = np.where(f.instance > 0, 9, 0).astype(np.uint16)
        merged.append(Frame(rgb=f.rgb, depth=f.depth, K=f.K, c2w=f.c2w, semantic=f.semantic, instance=inst))
    out = baseline_panoptic(scene.surfels["means"], merged, CLASSES)
    assert out["segments"] == 1
    m = score(scene, out, frames, gts)
    box = m["per_class"][2]
    assert box["tp"] <= 1 and box["fn"] >= 1 and box["pq"] < 0.6   # at most the bigger box survives


def test_single_frame_segments_are_dropped(world):
    scene, frames, _ = world
    out = baseline_panoptic(scene.surfels["means"], frames[:1], CLASSES)
    assert out["segments"] == 0 and not out["instance_id"].any()
    out = baseline_panoptic(scene.surfels["means"], frames[:1], CLASSES, BaselineConfig(min_frames=1))
    assert out["segments"] == 2


def test_degenerate_inputs(world):
    scene, frames, _ = world
    means = scene.surfels["means"]
    blank = [Frame(rgb=f.rgb, depth=f.depth, K=f.K, c2w=f.c2w, semantic=np.zeros_like(f.semantic),
                   instance=np.zeros_like(f.instance)) for f in frames]
    out = baseline_panoptic(means, blank, CLASSES)          # frames without masks: nothing, no crash
    assert out["segments"] == 0 and not out["semantic_id"].any()
    nodepth = [Frame(rgb=f.rgb, depth=np.full_like(f.depth, np.nan), K=f.K, c2w=f.c2w, semantic=f.semantic,
                     instance=f.instance) for f in frames]
    with pytest.raises(PsimapError, match="valid depth"):
        baseline_panoptic(means, nodepth, CLASSES)
    mixed = frames[:2] + nodepth[:2]                        # NaN depth frames are skipped
    assert baseline_panoptic(means, mixed, CLASSES)["segments"] == 2
    empty = baseline_panoptic(np.zeros((0, 3)), frames, CLASSES)
    assert empty["instance_id"].shape == (0,)
    with pytest.raises(PsimapError, match="no frames"):
        baseline_panoptic(means, [], CLASSES)
    with pytest.raises(PsimapError, match=r"\[N, 3\]"):
        baseline_panoptic(np.zeros((4, 2)), frames, CLASSES)
