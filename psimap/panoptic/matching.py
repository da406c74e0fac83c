"""Per-frame Hungarian matching of instance queries to a frame's 2D pseudo-label masks (paper §4.2).

2D instance ids are per frame only, so every frame is matched afresh: the cost of giving query q the
mask m is Dice + BCE (+ a class term), solved with scipy's `linear_sum_assignment`. Matches whose Dice
cost is near 1 (the query's rendered mask barely overlaps the 2D mask), or whose query draws no more
on the mask than around it, are rejected, so a query is never dragged across the scene onto an
object it does not cover.

Dice is measured inside each mask's neighbourhood (`mask_windows`), not over the whole frame: the
softmax over queries leaves every query a diffuse tail (~0.03 per pixel after pruning, ~550 summed
over a 160x120 frame at 15 % noise), which swamped the overlap with a 5-20 px mask. Every query's
whole-frame Dice cost to such a mask was > 0.98, so small objects (mugs, bottles, balls) were never
matched, their queries never trained, and they were absorbed by the surface they stand on.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from psimap.panoptic.config import PanopticConfig


@dataclass
class Match:
    """query_idx [M] and mask_idx [M] long tensors (matched pairs); cost [M] the matched costs."""

    query_idx: torch.Tensor
    mask_idx: torch.Tensor
    cost: torch.Tensor


def masks_from_ids(instance: torch.Tensor, min_pixels: int = 1):
    """Split a per-frame instance-id map [H, W] into binary masks [M, H, W] (id 0 = no instance).

    Returns (masks [M, H, W] bool, ids [M] long). Masks with fewer than `min_pixels` pixels are dropped.
    """
    ids, counts = torch.unique(instance[instance > 0], return_counts=True)
    ids = ids[counts >= min_pixels]
    if ids.numel() == 0:
        return torch.zeros((0,) + tuple(instance.shape), dtype=torch.bool, device=instance.device), ids
    return instance.unsqueeze(0) == ids.view(-1, 1, 1), ids


def mask_windows(masks: torch.Tensor) -> torch.Tensor:
    """Each mask's neighbourhood [M, H, W] bool: its bounding box grown by its own height and width
    on every side (3x the box per axis, clipped to the image). masks [M, H, W] bool."""
    m, h, w = masks.shape
    if m == 0:
        return masks.clone()
    rows, cols = masks.any(2), masks.any(1)                                   # [M, H], [M, W]
    ar_h = torch.arange(h, device=masks.device)
    ar_w = torch.arange(w, device=masks.device)
    y0 = torch.where(rows, ar_h, h).min(1).values
    y1 = torch.where(rows, ar_h, -1).max(1).values
    x0 = torch.where(cols, ar_w, w).min(1).values
    x1 = torch.where(cols, ar_w, -1).max(1).values
    gy, gx = (y1 - y0 + 1).clamp_min(1), (x1 - x0 + 1).clamp_min(1)
    in_y = (ar_h[None] >= (y0 - gy)[:, None]) & (ar_h[None] <= (y1 + gy)[:, None])
    in_x = (ar_w[None] >= (x0 - gx)[:, None]) & (ar_w[None] <= (x1 + gx)[:, None])
    return in_y[:, :, None] & in_x[:, None, :]


def dice_cost(prob: torch.Tensor, target: torch.Tensor, eps: float = 1.0,
              window: torch.Tensor | None = None) -> torch.Tensor:
    """Pairwise Dice cost: prob [Q, P] in [0, 1], target [M, P] {0, 1} -> [Q, M] in [0, 1].

    window [M, P] {0, 1} (optional, containing the target): the query's mass counts only there.
    """
    inter = prob @ target.T
    mass = prob.sum(-1, keepdim=True) if window is None else prob @ window.T
    denom = mass + target.sum(-1).unsqueeze(0)
    return 1.0 - (2.0 * inter + eps) / (denom + eps)


def bce_cost(logit: torch.Tensor, target: torch.Tensor, window: torch.Tensor | None = None) -> torch.Tensor:
    """Pairwise mean BCE: logit [Q, P], target [M, P] -> [Q, M] (expanded without [Q, M, P] memory);
    with window [M, P] the mean runs over each mask's window."""
    pos = F.binary_cross_entropy_with_logits(logit, torch.ones_like(logit), reduction="none")
    neg = F.binary_cross_entropy_with_logits(logit, torch.zeros_like(logit), reduction="none")
    if window is None:
        p = logit.shape[-1]
        return (pos @ target.T + neg @ (1.0 - target).T) / max(p, 1)
    return (pos @ target.T + neg @ (window - target).T) / window.sum(-1).clamp_min(1.0).unsqueeze(0)


def window_pixels(prob: torch.Tensor, target: torch.Tensor, window: torch.Tensor | None):
    """(x [P', Q], target [M, P'], window [M, P']): prob [Q, P] pixel-major (x = prob.T, gathered
    row by row: the render's own layout, no transposed copy) and the masks, restricted to the pixels
    of some window (every windowed term is measured inside them; all pixels without windows)."""
    x = prob.T
    if window is not None:
        inside = window.any(0)
        if not bool(inside.all()):
            idx = torch.nonzero(inside).flatten()
            return x.index_select(0, idx), target.index_select(1, idx), window.index_select(1, idx)
    return x, target, window


def match_sums_reference(prob: torch.Tensor, target: torch.Tensor, window: torch.Tensor | None = None,
                         clamp: float | None = None) -> torch.Tensor:
    """The sums the matching costs read, [5, M, Q]: over each mask's pixels p, log p and log(1 - p),
    over its window's pixels p and log(1 - p) (every pixel without windows). prob [Q, P] in (0, 1);
    target [M, P] {0, 1}; window [M, P] {0, 1} containing its target; clamp: the probabilities are
    first clamped to [clamp, 1 - clamp]. The torch form of the native kernel of the same name
    (psimap.render.native.match_sums)."""
    x, target, window = window_pixels(prob, target, window)                        # x [P', Q]
    if clamp is not None:
        x = x.clamp(clamp, 1 - clamp)
    log1m = torch.log1p(x.neg())
    on_mask = [target @ x, target @ torch.log(x), target @ log1m]                  # [M, Q] each
    if window is None:
        on_window = [x.sum(0).expand_as(on_mask[0]), log1m.sum(0).expand_as(on_mask[0])]
    else:
        on_window = [window @ x, window @ log1m]
    return torch.stack(on_mask + on_window)


def match_sums(prob: torch.Tensor, target: torch.Tensor, window: torch.Tensor | None = None,
               clamp: float | None = None, backend: str = "auto") -> torch.Tensor:
    """match_sums_reference's value [5, M, Q] in prob's dtype: the native kernel (one pass over the
    window pixels' rows, csrc/match_lanes.inl) for float32 CPU probabilities with windows and a
    clamp where it is built (backend "auto" or "native"; "native" raises where it cannot run), else
    the torch form. In torch: a clamped copy, two logarithms and a negation of every window
    pixel's row, read back by matrix products, ~10 ms a step at 85 queries, ~2 ms at 21."""
    native = (backend in ("auto", "native") and window is not None and clamp is not None and 0 < clamp < 0.5
              and prob.device.type == "cpu" and prob.dtype == torch.float32)
    if native:
        from psimap.render.api import native_available

        native = native_available()
    if backend == "native" and not native:
        raise ValueError("match_sums: the native kernel needs float32 CPU probabilities, windows, a clamp "
                         "and the built module")
    if not native:
        return match_sums_reference(prob, target, window, clamp)
    from psimap.render.native import match_sums as fused

    # per mask and pixel: 0 outside the mask's window, 1 in it, 2 on the mask (the window holds it)
    codes = (window > 0).to(torch.uint8) + (target > 0).to(torch.uint8)                      # [M, P]
    return fused(prob.T, codes, clamp, 1 - clamp).to(prob.dtype)


def match_costs(prob: torch.Tensor, target: torch.Tensor, window: torch.Tensor | None = None,
                eps: float = 1.0, clamp: float | None = None, backend: str = "auto") -> dict:
    """The matching's terms, [Q, M] each: "dice" and "bce" (dice_cost's and bce_cost's values), and
    with a window "on_mask" / "on_ring", each query's mean probability on the mask and on the rest of
    its window ("ring_pixels" [1, M]: that rest's size).

    prob [Q, P] in (0, 1); target [M, P] {0, 1}; window [M, P] {0, 1} containing its target. With
    windows only the pixels of some window are read (every term is measured inside them). clamp:
    the probabilities are first clamped to [clamp, 1 - clamp]. The sums come from `match_sums`
    (backend: which form).
    """
    inter, log_t, log1m_t, mass, log1m_w = (s.T for s in match_sums(prob, target, window, clamp, backend))
    n_t = target.sum(-1).unsqueeze(0)                                                # [1, M]
    n_w = torch.full_like(n_t, float(prob.shape[1])) if window is None else window.sum(-1).unsqueeze(0)
    out = {"dice": 1.0 - (2.0 * inter + eps) / (mass + n_t + eps),
           "bce": (log1m_t - log_t - log1m_w) / n_w.clamp_min(1.0)}
    if window is not None:
        out["on_mask"] = inter / n_t.clamp_min(1.0)
        out["on_ring"] = (mass - inter) / (n_w - n_t).clamp_min(1.0)
        out["ring_pixels"] = n_w - n_t
    return out


def hungarian_match(prob: torch.Tensor, target: torch.Tensor, *, class_cost: torch.Tensor | None = None,
                    w_dice: float = 1.0, w_bce: float = 1.0, w_class: float = 1.0,
                    reject_dice: float = PanopticConfig.reject_dice, window: torch.Tensor | None = None) -> Match:
    """Match Q query masks to M target masks on Dice + BCE (+ class) cost.

    prob [Q, P]: rendered per-query probabilities on P sampled pixels (in [0, 1]);
    target [M, P]: binary 2D masks on the same pixels; class_cost [Q, M] optional (e.g. 1 - p(class));
    window [M, P] optional: each mask's neighbourhood (`mask_windows`), where Dice and BCE are
    measured (None: the whole frame). Pairs whose Dice cost exceeds `reject_dice`, or whose query's
    mean probability on the mask is not above its mean on the rest of the window (it draws the
    surroundings as much as the mask: a shelf's query on a bottle mask, or a query's diffuse tail),
    are dropped.
    """
    q, m = prob.shape[0], target.shape[0]
    empty = torch.zeros(0, dtype=torch.long, device=prob.device)
    if q == 0 or m == 0:
        return Match(empty, empty, torch.zeros(0, device=prob.device))
    with torch.no_grad():
        t = target.float()
        win = None if window is None else torch.maximum(window.float(), t)
        terms = match_costs(prob.detach().float(), t, win, clamp=1e-6)
        cost = w_dice * terms["dice"] + w_bce * terms["bce"]
        if class_cost is not None:
            cost = cost + w_class * class_cost.detach().float()
        cost = torch.nan_to_num(cost, nan=1e6, posinf=1e6, neginf=1e6)
        reject = terms["dice"] > reject_dice
        if win is not None:
            # "not above" up to float rounding: a uniform tail gives equal means summed in
            # different orders
            reject |= (terms["ring_pixels"] > 0) & (terms["on_mask"] <= terms["on_ring"] * (1.0 + 1e-5))
    from scipy.optimize import linear_sum_assignment

    rows, cols = linear_sum_assignment(cost.cpu().numpy())
    keep = ~reject.cpu().numpy()[rows, cols]
    rows, cols = rows[keep], cols[keep]
    qi = torch.as_tensor(np.asarray(rows, dtype=np.int64), device=prob.device)
    mi = torch.as_tensor(np.asarray(cols, dtype=np.int64), device=prob.device)
    return Match(qi, mi, cost[qi, mi].to(prob.device) if qi.numel() else torch.zeros(0, device=prob.device))


def matched_mask_loss(prob: torch.Tensor, target: torch.Tensor, match: Match, eps: float = 1.0,
                      window: torch.Tensor | None = None, matched: torch.Tensor | None = None) -> torch.Tensor:
    """Dice + BCE over the matched pairs (differentiable in prob, or in `matched`); 0 when nothing
    matched.

    prob [Q, P] in (0, 1), target [M, P] {0, 1}; window [M, P] (optional): Dice inside each mask's
    neighbourhood, as matched; BCE always over all pixels (it pushes the query's tail down
    everywhere). matched [P, len(match.query_idx)] (optional): the matched queries' probabilities,
    pixel-major, in their place (prob then need not carry a gradient).
    """
    if match.query_idx.numel() == 0:
        return prob.sum() * 0.0
    # the matched rows gathered as columns of prob.T: the field's prob is the transposed view of a
    # pixel-major render [P, Q], whose gradient then stays pixel-major (a row gather's gradient was
    # a [Q, P] block that the render's backward copied transposed: ~3 ms a step at 93 queries)
    if matched is None:
        matched = prob.T.index_select(1, match.query_idx)
    p = matched.T.clamp(1e-6, 1 - 1e-6)
    t = target[match.mask_idx].to(p.dtype)
    inter = (p * t).sum(-1)
    mass = p.sum(-1) if window is None else (p * torch.maximum(window[match.mask_idx].to(p.dtype), t)).sum(-1)
    dice = 1.0 - (2.0 * inter + eps) / (mass + t.sum(-1) + eps)
    # the BCE of a {0, 1} target is -log p on the mask and -log(1 - p) off it: one logarithm a
    # pixel (torch's vectorised one) where F.binary_cross_entropy takes two scalar ones (room, ten
    # matched masks x 20k pixels: 3.5 -> 1.8 ms forward and backward; within an ulp of it)
    bce = -torch.log(torch.where(t > 0, p, 1.0 - p)).mean(-1)
    return (dice + bce).mean()
