"""Per-frame Hungarian matching of instance queries to a frame's 2D pseudo-label masks (paper §4.2).

2D instance ids are per frame only, so every frame is matched afresh: the cost of giving query q the
mask m is Dice + BCE (+ a class term), solved with scipy's `linear_sum_assignment`. Matches whose Dice
cost is near 1 (the query's rendered mask barely overlaps the 2D mask) are rejected, so a query is
never dragged across the scene onto an object it does not cover.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F


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


def dice_cost(prob: torch.Tensor, target: torch.Tensor, eps: float = 1.0) -> torch.Tensor:
    """Pairwise Dice cost: prob [Q, P] in [0, 1], target [M, P] {0, 1} -> [Q, M] in [0, 1]."""
    inter = prob @ target.T
    denom = prob.sum(-1, keepdim=True) + target.sum(-1).unsqueeze(0)
    return 1.0 - (2.0 * inter + eps) / (denom + eps)


def bce_cost(logit: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Pairwise mean BCE: logit [Q, P], target [M, P] -> [Q, M] (expanded without [Q, M, P] memory)."""
    pos = F.binary_cross_entropy_with_logits(logit, torch.ones_like(logit), reduction="none")
    neg = F.binary_cross_entropy_with_logits(logit, torch.zeros_like(logit), reduction="none")
    p = logit.shape[-1]
    return (pos @ target.T + neg @ (1.0 - target).T) / max(p, 1)


def hungarian_match(prob: torch.Tensor, target: torch.Tensor, *, class_cost: torch.Tensor | None = None,
                    w_dice: float = 1.0, w_bce: float = 1.0, w_class: float = 1.0,
                    reject_dice: float = 0.95) -> Match:
    """Match Q query masks to M target masks on Dice + BCE (+ class) cost.

    prob [Q, P]: rendered per-query probabilities on P sampled pixels (in [0, 1]);
    target [M, P]: binary 2D masks on the same pixels; class_cost [Q, M] optional (e.g. 1 - p(class)).
    Pairs whose Dice cost exceeds `reject_dice` are dropped (no overlap worth supervising).
    """
    q, m = prob.shape[0], target.shape[0]
    empty = torch.zeros(0, dtype=torch.long, device=prob.device)
    if q == 0 or m == 0:
        return Match(empty, empty, torch.zeros(0, device=prob.device))
    with torch.no_grad():
        p = prob.detach().float().clamp(1e-6, 1 - 1e-6)
        t = target.float()
        dice = dice_cost(p, t)
        cost = w_dice * dice + w_bce * bce_cost(torch.logit(p), t)
        if class_cost is not None:
            cost = cost + w_class * class_cost.detach().float()
        cost = torch.nan_to_num(cost, nan=1e6, posinf=1e6, neginf=1e6)
    from scipy.optimize import linear_sum_assignment

    rows, cols = linear_sum_assignment(cost.cpu().numpy())
    keep = dice.cpu().numpy()[rows, cols] <= reject_dice
    rows, cols = rows[keep], cols[keep]
    qi = torch.as_tensor(np.asarray(rows, dtype=np.int64), device=prob.device)
    mi = torch.as_tensor(np.asarray(cols, dtype=np.int64), device=prob.device)
    return Match(qi, mi, cost[qi, mi].to(prob.device) if qi.numel() else torch.zeros(0, device=prob.device))


def matched_mask_loss(prob: torch.Tensor, target: torch.Tensor, match: Match, eps: float = 1.0) -> torch.Tensor:
    """Dice + BCE over the matched pairs (differentiable in prob); 0 when nothing matched.

    prob [Q, P] in (0, 1), target [M, P] {0, 1}.
    """
    if match.query_idx.numel() == 0:
        return prob.sum() * 0.0
    p = prob[match.query_idx].clamp(1e-6, 1 - 1e-6)
    t = target[match.mask_idx].to(p.dtype)
    inter = (p * t).sum(-1)
    dice = 1.0 - (2.0 * inter + eps) / (p.sum(-1) + t.sum(-1) + eps)
    bce = F.binary_cross_entropy(p, t, reduction="none").mean(-1)
    return (dice + bce).mean()
