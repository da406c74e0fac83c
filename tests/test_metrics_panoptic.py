"""Panoptic metrics on hand-built label maps with known answers."""
from __future__ import annotations

import numpy as np
import pytest

from psimap import PsimapError
from psimap.metrics.panoptic import PanopticAccumulator, panoptic_metrics


def row(n: int, spans: dict[tuple[int, int], int]) -> np.ndarray:
    """A [1, n] uint16 map with value v on each half-open pixel span (a, b)."""
    a = np.zeros((1, n), np.uint16)
    for (lo, hi), v in spans.items():
        a[0, lo:hi] = v
    return a


def two_object_scene(h=6, w=8):
    """GT: floor (class 1, stuff) on the left, objects 1 and 2 (class 2, thing) on the right."""
    sem = np.ones((h, w), np.uint16)
    inst = np.zeros((h, w), np.uint16)
    sem[:3, 4:] = 2
    inst[:3, 4:] = 1
    sem[3:, 4:] = 2
    inst[3:, 4:] = 2
    return sem, inst


def test_identical_labels_score_one():
    sem, inst = two_object_scene()
    m = panoptic_metrics([(sem, inst, sem, inst)] * 3, thing_classes=[2])
    for k in ("pq", "sq", "rq", "pq_thing", "pq_stuff", "miou", "macc", "mcov", "mwcov", "pq_frame"):
        assert m[k] == 1.0, k
    assert m["n_gt_instances"] == 2 and m["n_frames"] == 3
    assert m["per_class"][2]["tp"] == 2 and m["per_class"][1]["tp"] == 1


def test_relabelled_but_consistent_ids_still_score_one():
    sem, inst = two_object_scene()
    pinst = np.where(inst == 1, 40000, np.where(inst == 2, 7, 0)).astype(np.uint32)
    # Stuff instance ids are ignored: one segment per stuff class.
    pinst[sem == 1] = 99
    m = panoptic_metrics([(sem, pinst, sem, inst)] * 2, thing_classes=[2])
    assert m["pq"] == 1.0 and m["mcov"] == 1.0


def test_ids_swapped_between_frames_break_scene_pq_not_frame_pq():
    sem, inst = two_object_scene()
    swapped = np.where(inst == 1, 2, np.where(inst == 2, 1, 0)).astype(np.uint16)
    frames = [(sem, inst, sem, inst), (sem, swapped, sem, inst)]
    m = panoptic_metrics(frames, thing_classes=[2])
    # Each predicted id covers half of each GT object over the sequence: IoU 1/3, never > 0.5.
    assert m["pq_thing"] == 0.0
    assert m["per_class"][2] == pytest.approx(
        {"pq": 0.0, "sq": 0.0, "rq": 0.0, "tp": 0, "fp": 2, "fn": 2, "isthing": True, "iou": 1.0,
         "acc": 1.0})
    assert m["pq_stuff"] == 1.0 and m["pq"] == 0.5
    assert m["pq_frame"] == 1.0
    assert m["miou"] == 1.0  # semantics did not change
    assert m["mcov"] == pytest.approx(1 / 3)


def test_hand_computed_tp_fp_fn():
    # GT: two class-1 instances of 10 px. Pred: id 7 covers 6 px of the first (IoU 0.6, TP),
    # id 8 covers 4 px of the second (IoU 0.4: FP, and the second GT instance is a FN).
    gs = row(20, {(0, 20): 1})
    gi = row(20, {(0, 10): 1, (10, 20): 2})
    ps = row(20, {(0, 6): 1, (10, 14): 1})
    pi = row(20, {(0, 6): 7, (10, 14): 8})
    m = panoptic_metrics([(ps, pi, gs, gi)], thing_classes=[1])
    assert m["sq"] == pytest.approx(0.6)
    assert m["rq"] == pytest.approx(0.5)
    assert m["pq"] == pytest.approx(0.3)
    c = m["per_class"][1]
    assert (c["tp"], c["fp"], c["fn"]) == (1, 1, 1)
    # Coverage: instance 1 -> 0.6, instance 2 -> 0.4; equal areas.
    assert m["mcov"] == pytest.approx(0.5) and m["mwcov"] == pytest.approx(0.5)
    # Semantic: 10 of 20 class-1 pixels predicted as class 1, no other predictions on GT.
    assert m["miou"] == pytest.approx(0.5) and m["macc"] == pytest.approx(0.5)


def test_void_rules():
    # GT: instance 1 on px 0..9, void on 10..19, instance 2 on 20..29 (all class 1).
    gs = row(30, {(0, 10): 1, (20, 30): 1})
    gi = row(30, {(0, 10): 1, (20, 30): 2})
    # A predicted segment lying entirely on void is no false positive.
    ps = row(30, {(0, 30): 1})
    pi = row(30, {(0, 10): 5, (10, 20): 6, (20, 30): 7})
    assert panoptic_metrics([(ps, pi, gs, gi)], [1])["pq"] == 1.0
    # Void pixels of a prediction stay out of the IoU union: id 5 also covers 6 void px -> IoU 1.
    pi = row(30, {(0, 16): 5, (20, 30): 7})
    ps = row(30, {(0, 16): 1, (20, 30): 1})
    assert panoptic_metrics([(ps, pi, gs, gi)], [1])["pq"] == 1.0
    # Id 6 on 6 void + 4 GT px (60 % void): not a FP; id 7 keeps 6 of 10 px: IoU 0.6.
    ps = row(30, {(0, 10): 1, (14, 30): 1})
    pi = row(30, {(0, 10): 5, (14, 24): 6, (24, 30): 7})
    m = panoptic_metrics([(ps, pi, gs, gi)], [1])
    c = m["per_class"][1]
    assert (c["tp"], c["fp"], c["fn"]) == (2, 0, 0)
    assert m["pq"] == pytest.approx(0.8) and m["rq"] == 1.0
    # Exactly half on void (4 void + 4 GT) is a FP.
    ps = row(30, {(0, 10): 1, (16, 30): 1})
    pi = row(30, {(0, 10): 5, (16, 24): 6, (24, 30): 7})
    m = panoptic_metrics([(ps, pi, gs, gi)], [1])
    c = m["per_class"][1]
    assert (c["tp"], c["fp"], c["fn"]) == (2, 1, 0)
    assert m["rq"] == pytest.approx(0.8) and m["pq"] == pytest.approx(0.64)
    # Predictions on void pixels (16..19 here) do not count against semantic IoU either
    # (counted, they would give 20 / 24).
    assert m["miou"] == 1.0


def test_thing_pixels_without_instance_are_void_and_pred_void_is_unlabelled():
    gs = row(20, {(0, 20): 1})
    gi = row(20, {(0, 10): 1})        # px 10..19: class 1 but no instance -> void for PQ
    ps = row(20, {(0, 20): 1})
    pi = row(20, {(0, 20): 3})
    m = panoptic_metrics([(ps, pi, gs, gi)], [1])
    assert m["pq"] == 1.0  # the 10 extra px lie on void
    # Predicting nothing: all FN, PQ 0, mIoU 0.
    z = np.zeros_like(gs)
    m = panoptic_metrics([(z, z, gs, gi)], [1])
    assert m["pq"] == 0.0 and m["per_class"][1]["fn"] == 1 and m["miou"] == 0.0


def test_semantic_miou_macc_hand_computed():
    gs = row(20, {(0, 10): 1, (10, 20): 2})
    ps = row(20, {(0, 15): 1, (15, 20): 2})
    z = np.zeros_like(gs)
    m = panoptic_metrics([(ps, z, gs, z)])
    assert m["miou"] == pytest.approx((10 / 15 + 5 / 10) / 2)
    assert m["macc"] == pytest.approx((1.0 + 0.5) / 2)
    # Both classes inferred as stuff (no GT instance ids): stuff PQ, class 1 IoU 2/3 > 0.5 -> TP.
    assert m["thing_classes"] == []
    assert m["per_class"][1]["tp"] == 1 and m["per_class"][2]["tp"] == 0
    assert np.isnan(m["mcov"]) and np.isnan(m["pq_thing"])


def test_weighted_coverage():
    gs = row(40, {(0, 40): 1})
    gi = row(40, {(0, 10): 1, (10, 40): 2})
    ps = gs.copy()
    pi = row(40, {(0, 10): 4, (10, 25): 5, (25, 40): 6})
    m = panoptic_metrics([(ps, pi, gs, gi)], [1])
    assert m["mcov"] == pytest.approx((1.0 + 0.5) / 2)
    assert m["mwcov"] == pytest.approx((10 * 1.0 + 30 * 0.5) / 40)


def test_inferred_things_and_large_ids():
    sem, inst = two_object_scene()
    big = (inst.astype(np.uint32) * 3_000_000)
    m = panoptic_metrics([(sem, big, sem, inst)])
    assert m["thing_classes"] == [2] and m["pq"] == 1.0


def test_bad_inputs():
    a = np.zeros((4, 4), np.uint16)
    with pytest.raises(PsimapError, match="differ in size"):
        panoptic_metrics([(a, a, a, np.zeros((4, 5), np.uint16))])
    with pytest.raises(PsimapError, match="integer"):
        panoptic_metrics([(a.astype(float), a, a, a)])
    with pytest.raises(PsimapError, match="non-negative"):
        panoptic_metrics([(a - 1, a, a, a.astype(np.int32) - 1)])
    with pytest.raises(PsimapError, match="2D"):
        panoptic_metrics([(a[None], a, a, a)])
    with pytest.raises(PsimapError, match="no frames"):
        panoptic_metrics([])
    # All-void GT and prediction: nothing to score, NaN not a crash.
    m = panoptic_metrics([(a, a, a, a)])
    assert np.isnan(m["pq"]) and np.isnan(m["miou"]) and np.isnan(m["pq_frame"])


def test_accumulator_matches_one_shot_and_many_segments_use_sparse_counts():
    rng = np.random.default_rng(0)
    gs = rng.integers(1, 4, (40, 50)).astype(np.uint16)
    gi = rng.integers(0, 300, (40, 50)).astype(np.uint16)
    ps = np.where(rng.random(gs.shape) < 0.9, gs, 2).astype(np.uint16)
    pi = rng.integers(0, 300, (40, 50)).astype(np.uint16)
    acc = PanopticAccumulator([2, 3])
    acc.add(ps, pi, gs, gi)
    acc.add(gs, gi, gs, gi)
    a = acc.result()
    b = panoptic_metrics([(ps, pi, gs, gi), (gs, gi, gs, gi)], [2, 3])
    assert a["pq"] == b["pq"] and a["miou"] == b["miou"]
    # Semantic check against a direct confusion count over both frames.
    gt = np.concatenate([gs.ravel(), gs.ravel()])
    pr = np.concatenate([ps.ravel(), gs.ravel()])
    ious = [((gt == c) & (pr == c)).sum() / ((gt == c) | (pr == c)).sum() for c in (1, 2, 3)]
    assert a["miou"] == pytest.approx(np.mean(ious))
