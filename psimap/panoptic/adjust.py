"""Dynamic query adjustment (paper §4.1): drop useless queries and duplicate queries.

Useless: matched to a 2D mask in too small a fraction of the frames where the query was visible
(noisy masks create queries that nothing supports). Duplicate: a query whose 3D mask lies mostly
inside a larger query's mask, measured by intersection over mask IoM_ij = |M_i & M_j| / |M_i|.
3D masks use the un-normalised affinity A(q, g) > threshold, so masks of different queries can
overlap (an argmax partition never would, and IoM would always be 0). Co-mask duplicate: two
queries that have each won a part of one object (their 3D masks no longer overlap) but are drawn
inside the same 2D mask in most frames that see both. Queries matched to two different 2D masks
of one frame in several frames are distinct objects and never duplicates of each other (a box's
query lies inside the 3D mask of the table it stands on). "Visible" means the query owns (p > 0.5) at
least a small mask in the frame; the field logs how many queries each rule drops.
"""
from __future__ import annotations

import torch


def iom_matrix(masks: torch.Tensor) -> torch.Tensor:
    """IoM [Q, Q] from 3D masks [N, Q] bool: IoM[i, j] = |M_i & M_j| / |M_i| (0 for empty M_i)."""
    m = masks.float()
    inter = m.T @ m                                     # [Q, Q]
    size = m.sum(0)
    return inter / size.clamp_min(1.0).unsqueeze(1) * (size > 0).float().unsqueeze(1)


def duplicate_queries(masks: torch.Tensor, threshold: float,
                      distinct: torch.Tensor | None = None) -> torch.Tensor:
    """Queries to drop as duplicates: [Q] bool.

    Smallest masks first: a query is a duplicate when IoM with a larger, still-kept query exceeds
    `threshold` (PanopticConfig.iom_threshold); the larger one is kept. Empty masks are duplicates
    of nothing (handled as useless).
    distinct [Q, Q] bool (optional): pairs known to be different objects (e.g. both matched to
    different 2D masks of one frame, repeatedly) are never duplicates of each other: a bottle's
    query lies inside the Gaussian of the shelf it stands on, so its 3D mask is inside the shelf's.
    """
    q = masks.shape[1]
    drop = torch.zeros(q, dtype=torch.bool)
    if q < 2:
        return drop
    iom = iom_matrix(masks).cpu()
    size = masks.sum(0).cpu()
    order = torch.argsort(size, stable=True)            # ascending
    for rank, i in enumerate(order.tolist()):
        if size[i] == 0:
            continue
        larger = order[rank + 1:]
        larger = larger[~drop[larger]]
        if distinct is not None:
            larger = larger[~distinct[i, larger].cpu()]
        if larger.numel() and bool((iom[i, larger] > threshold).any()):
            drop[i] = True
    return drop


def useless_queries(matched: torch.Tensor, visible: torch.Tensor, min_rate: float,
                    min_visible: int = 3) -> torch.Tensor:
    """Queries to drop as useless: [Q] bool.

    matched [Q]: frames in which the query was matched to a 2D mask; visible [Q]: frames in which it
    was seen (owned a mask-sized region). Queries seen at least `min_visible` times whose match rate
    is below `min_rate` (PanopticConfig.min_match_rate) are useless; so are queries never matched
    although seen.
    """
    matched = matched.float()
    visible = visible.float()
    rate = matched / visible.clamp_min(1.0)
    return ((visible >= min_visible) & (rate < min_rate)) | ((visible >= min_visible) & (matched == 0))


def co_mask_duplicates(same: torch.Tensor, apart: torch.Tensor, support: torch.Tensor,
                       min_frames: int = 3) -> torch.Tensor:
    """Queries to drop as pieces of one object split between queries: [Q] bool.

    same / apart [Q, Q]: frames in which both queries were seen with their rendered pixels inside
    the same 2D mask / inside two different masks; support [Q]: how often each was matched. Two
    queries that share a mask more often than not (and in at least `min_frames` frames) draw one
    object; the less supported one is dropped. This sees splits that the 3D IoM cannot: once two
    queries have each won their part of an object, their 3D masks no longer overlap.
    """
    q = same.shape[0]
    drop = torch.zeros(q, dtype=torch.bool)
    if q < 2:
        return drop
    together = (same > apart) & (same >= min_frames)
    together.fill_diagonal_(False)
    order = torch.argsort(support, stable=True)          # least supported first
    for rank, i in enumerate(order.tolist()):
        stronger = order[rank + 1:]
        stronger = stronger[~drop[stronger]]
        if stronger.numel() and bool(together[i, stronger].any()):
            drop[i] = True
    return drop
