"""Panoptic metrics over a whole sequence: scene-level PQ / SQ / RQ, mIoU, mAcc, mCov, mW-Cov.

Scene level means segments are accumulated over *all* frames: a GT instance is the union of its
pixels in every frame, a predicted segment the union of the pixels carrying its id. A prediction
whose ids are consistent across frames scores like a per-frame one; one whose ids change between
frames is penalised. The per-frame PQ (`pq_frame`, averaged over frames) is reported beside it so
the difference is visible.

Rules (COCO panoptic, as panopticapi): a segment is (class, instance id); stuff classes form one
segment per class (their instance ids are ignored); GT pixels of class 0 (void), and thing pixels
without an instance id, are void: they are left out of IoU unions, and a predicted segment lying
more than half on void is not a false positive. A match (TP) is a GT and a predicted segment of the
same class with IoU > 0.5 (unique by construction). Class-averaged over classes with TP+FP+FN > 0.

Implementation: each frame is reduced to a table of (GT key, predicted key, pixel count) with
np.unique + bincount over encoded pairs (no per-pixel Python); key = class << 32 | instance.
Everything else is computed from the accumulated tables.
"""
from __future__ import annotations

from typing import Iterable

import numpy as np

from psimap import PsimapError

_SHIFT = np.uint64(32)
_LOW = np.uint64(0xFFFFFFFF)


def _keys(semantic: np.ndarray, instance: np.ndarray) -> np.ndarray:
    return (semantic.astype(np.uint64) << _SHIFT) | instance.astype(np.uint64)


def _check_map(a, what: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 2:
        raise PsimapError(f"{what}: expected a 2D label map, got shape {a.shape}")
    if a.dtype.kind not in "ui":
        if a.dtype.kind == "b":
            return a.astype(np.uint8)
        raise PsimapError(f"{what}: label maps must be integer, got {a.dtype}")
    if a.dtype.kind == "i" and a.size and a.min() < 0:
        raise PsimapError(f"{what}: label maps must be non-negative")
    if a.size and int(a.max()) > 0xFFFFFFFF:
        raise PsimapError(f"{what}: label ids must fit in 32 bits")
    return a


def pair_table(pred_semantic, pred_instance, gt_semantic, gt_instance, what: str = "frame"):
    """One frame reduced to (gt_keys [M] u64, pred_keys [M] u64, counts [M] i64).

    All four maps: [H, W] non-negative integers of the same shape.
    """
    ps, pi = _check_map(pred_semantic, f"{what} pred semantic"), _check_map(pred_instance, f"{what} pred instance")
    gs, gi = _check_map(gt_semantic, f"{what} gt semantic"), _check_map(gt_instance, f"{what} gt instance")
    if not (ps.shape == pi.shape == gs.shape == gi.shape):
        raise PsimapError(f"{what}: label maps differ in size: pred {ps.shape}/{pi.shape}, "
                          f"gt {gs.shape}/{gi.shape}")
    ug, ginv = np.unique(_keys(gs, gi).ravel(), return_inverse=True)
    up, pinv = np.unique(_keys(ps, pi).ravel(), return_inverse=True)
    pair = ginv.ravel().astype(np.int64) * len(up) + pinv.ravel()
    if len(ug) * len(up) <= 4 * pair.size:   # dense count table is small: bincount
        counts = np.bincount(pair, minlength=len(ug) * len(up))
        nz = np.flatnonzero(counts)
        counts = counts[nz]
    else:                                    # many segments on both sides: sparse count
        nz, counts = np.unique(pair, return_counts=True)
    return ug[nz // len(up)], up[nz % len(up)], counts.astype(np.int64)


def _merge(gk: np.ndarray, pk: np.ndarray, n: np.ndarray):
    """Sum counts of identical (gk, pk) rows."""
    if gk.size == 0:
        return gk, pk, n
    pairs, inv = np.unique(np.stack([gk, pk], axis=1), axis=0, return_inverse=True)
    return pairs[:, 0], pairs[:, 1], np.bincount(inv.ravel(), weights=n).astype(np.int64)


def _canonical(gk, pk, n, things: set[int]):
    """Stuff -> one segment per class (instance 0); thing pixels without instance -> void (key 0)."""
    def canon(k):
        sem = (k >> _SHIFT).astype(np.int64)
        inst = k & _LOW
        is_thing = np.isin(sem, list(things)) if things else np.zeros(sem.shape, bool)
        k = np.where(is_thing, k, sem.astype(np.uint64) << _SHIFT)
        return np.where((sem == 0) | (is_thing & (inst == 0)), np.uint64(0), k).astype(np.uint64)

    return _merge(canon(gk), canon(pk), n)


def _pq_from_table(gk, pk, n, things: set[int], iou_threshold: float = 0.5) -> dict:
    """Per-class TP / FP / FN / IoU sums and the PQ family, from a canonical pair table."""
    gsem, psem = (gk >> _SHIFT).astype(np.int64), (pk >> _SHIFT).astype(np.int64)
    g_ids, g_inv = np.unique(gk, return_inverse=True)
    p_ids, p_inv = np.unique(pk, return_inverse=True)
    g_area = np.bincount(g_inv, weights=n)
    p_area = np.bincount(p_inv, weights=n)
    p_void = np.bincount(p_inv, weights=np.where(gk == 0, n, 0))
    cand = (gk != 0) & (pk != 0) & (gsem == psem)
    union = g_area[g_inv] + p_area[p_inv] - n - p_void[p_inv]
    iou = np.where(cand, n / np.maximum(union, 1), 0.0)
    tp = cand & (iou > iou_threshold)
    g_matched = np.zeros(len(g_ids), bool)
    p_matched = np.zeros(len(p_ids), bool)
    g_matched[g_inv[tp]] = True
    p_matched[p_inv[tp]] = True

    g_cls = (g_ids >> _SHIFT).astype(np.int64)
    p_cls = (p_ids >> _SHIFT).astype(np.int64)
    fn_seg = (g_ids != 0) & ~g_matched
    fp_seg = (p_ids != 0) & ~p_matched & (p_void <= 0.5 * p_area)
    classes = sorted(set(g_cls[g_ids != 0].tolist()) | set(p_cls[p_ids != 0].tolist()))
    per_class = {}
    for c in classes:
        n_tp = int((tp & (gsem == c)).sum())
        n_fp = int((fp_seg & (p_cls == c)).sum())
        n_fn = int((fn_seg & (g_cls == c)).sum())
        if n_tp + n_fp + n_fn == 0:
            continue
        iou_sum = float(iou[tp & (gsem == c)].sum())
        denom = n_tp + 0.5 * n_fp + 0.5 * n_fn
        per_class[c] = {"pq": iou_sum / denom, "sq": iou_sum / n_tp if n_tp else 0.0,
                        "rq": n_tp / denom, "tp": n_tp, "fp": n_fp, "fn": n_fn,
                        "isthing": c in things}

    def avg(key, sel):
        vals = [v[key] for c, v in per_class.items() if sel(c)]
        return float(np.mean(vals)) if vals else float("nan")

    return {"pq": avg("pq", lambda c: True), "sq": avg("sq", lambda c: True),
            "rq": avg("rq", lambda c: True),
            "pq_thing": avg("pq", lambda c: c in things), "pq_stuff": avg("pq", lambda c: c not in things),
            "per_class": per_class}


def _semantic_from_table(gk, pk, n) -> dict:
    """mIoU and mAcc over classes present (non-void) in GT."""
    gsem, psem = (gk >> _SHIFT).astype(np.int64), (pk >> _SHIFT).astype(np.int64)
    valid = gsem != 0
    classes = np.unique(gsem[valid])
    iou, acc = {}, {}
    for c in classes.tolist():
        tp = n[valid & (gsem == c) & (psem == c)].sum()
        gt_c = n[valid & (gsem == c)].sum()
        pred_c = n[valid & (psem == c)].sum()
        iou[c] = float(tp / (gt_c + pred_c - tp))
        acc[c] = float(tp / gt_c)
    nan = float("nan")
    return {"miou": float(np.mean(list(iou.values()))) if iou else nan,
            "macc": float(np.mean(list(acc.values()))) if acc else nan, "iou": iou, "acc": acc}


def _coverage_from_table(gk, pk, n, things: set[int]) -> dict:
    """mCov / mW-Cov over GT thing instances: best IoU with any predicted thing instance
    (class-agnostic: predicted instances are keyed by their instance id alone)."""
    gsem = (gk >> _SHIFT).astype(np.int64)
    psem = (pk >> _SHIFT).astype(np.int64)
    pinst = (pk & _LOW).astype(np.int64)
    thing_list = list(things)
    g_thing = (gk != 0) & np.isin(gsem, thing_list)
    p_thing = (pk != 0) & np.isin(psem, thing_list) & (pinst != 0)
    g_ids, g_inv = np.unique(gk, return_inverse=True)
    g_area = np.bincount(g_inv, weights=n)
    # Predicted instance area over non-void GT pixels (void stays out of the union, as in PQ).
    p_ids, p_inv = np.unique(np.where(p_thing, pinst, -1), return_inverse=True)
    p_area = np.bincount(p_inv, weights=np.where(gk != 0, n, 0))
    rows = g_thing & p_thing
    pairs, inv = (np.unique(np.stack([g_inv[rows], p_inv[rows]], 1), axis=0, return_inverse=True)
                  if rows.any() else (np.zeros((0, 2), np.int64), np.zeros(0, np.int64)))
    inter = np.bincount(inv.ravel(), weights=n[rows]) if rows.any() else np.zeros(0)
    iou = inter / (g_area[pairs[:, 0]] + p_area[pairs[:, 1]] - inter) if len(inter) else inter
    gt_things = np.unique(g_inv[g_thing])
    cov = np.zeros(len(g_ids))
    np.maximum.at(cov, pairs[:, 0], iou)
    if gt_things.size == 0:
        return {"mcov": float("nan"), "mwcov": float("nan"), "n_gt_instances": 0}
    w = g_area[gt_things]
    return {"mcov": float(cov[gt_things].mean()), "mwcov": float((cov[gt_things] * w).sum() / w.sum()),
            "n_gt_instances": int(gt_things.size)}


class PanopticAccumulator:
    """Accumulates frames; `result()` gives the sequence-level metrics.

    thing_classes: ids of thing classes; None infers them from the data (a class is a thing if any
    of its GT pixels, or failing GT pixels any predicted pixel, carries a non-zero instance id).
    """

    def __init__(self, thing_classes: Iterable[int] | None = None, iou_threshold: float = 0.5):
        self.thing_classes = None if thing_classes is None else {int(c) for c in thing_classes}
        self.iou_threshold = iou_threshold
        self.frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def add(self, pred_semantic, pred_instance, gt_semantic, gt_instance, name: str = "") -> None:
        """Add one frame: four [H, W] non-negative integer maps (pred first, then GT)."""
        what = f"frame {name or len(self.frames)}"
        self.frames.append(pair_table(pred_semantic, pred_instance, gt_semantic, gt_instance, what))

    def _things(self, gk, pk, n) -> set[int]:
        if self.thing_classes is not None:
            return self.thing_classes
        gsem, psem = (gk >> _SHIFT).astype(np.int64), (pk >> _SHIFT).astype(np.int64)
        g_thing = set(np.unique(gsem[(gk & _LOW) != 0]).tolist())
        p_thing = set(np.unique(psem[(pk & _LOW) != 0]).tolist()) - set(np.unique(gsem).tolist())
        return (g_thing | p_thing) - {0}

    def result(self) -> dict:
        if not self.frames:
            raise PsimapError("no frames to evaluate")
        gk, pk, n = _merge(*(np.concatenate(parts) for parts in zip(*self.frames)))
        things = self._things(gk, pk, n)
        cgk, cpk, cn = _canonical(gk, pk, n, things)
        out = _pq_from_table(cgk, cpk, cn, things, self.iou_threshold)
        sem = _semantic_from_table(gk, pk, n)
        out.update(miou=sem["miou"], macc=sem["macc"])
        out.update(_coverage_from_table(cgk, cpk, cn, things))
        frame_pq = [_pq_from_table(*_canonical(*f, things), things, self.iou_threshold)["pq"]
                    for f in self.frames]
        frame_pq = [v for v in frame_pq if not np.isnan(v)]
        out["pq_frame"] = float(np.mean(frame_pq)) if frame_pq else float("nan")
        for c, v in out["per_class"].items():
            v["iou"] = sem["iou"].get(c, float("nan"))
            v["acc"] = sem["acc"].get(c, float("nan"))
        out["n_frames"] = len(self.frames)
        out["thing_classes"] = sorted(things)
        return out


def panoptic_metrics(frames: Iterable, thing_classes: Iterable[int] | None = None,
                     iou_threshold: float = 0.5) -> dict:
    """Scene-level panoptic metrics of a sequence.

    frames: iterable of (pred_semantic, pred_instance, gt_semantic, gt_instance), each [H, W]
    non-negative integers (0 = none / void). Returns pq, sq, rq, pq_thing, pq_stuff, miou, macc,
    mcov, mwcov, pq_frame (per-frame PQ averaged over frames), n_gt_instances, n_frames,
    thing_classes, per_class {class id: pq, sq, rq, tp, fp, fn, iou, acc, isthing}. Undefined
    averages (nothing to average) are NaN.
    """
    acc = PanopticAccumulator(thing_classes, iou_threshold)
    for f in frames:
        acc.add(*f)
    return acc.result()
