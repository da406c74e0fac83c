"""A warm start for the panoptic field: the frames' 2D labels lifted onto the frozen surfels by vote.

Each labelled view votes, for every surfel whose centre it sees (the view's depth at the centre's
pixel agrees with the centre's depth), the class its semantic map gives that pixel. The field's
semantic logits then start at the log of the smoothed vote shares instead of zero, so the
cross-entropy steps refine a labelling that is already the multi-view majority rather than discover
it from a uniform start (and P(thing | g), which scales every surfel's instance distribution, starts
near 0 on walls and floors). The steps, not the vote, still decide: a surfel the votes got wrong is
corrected by the rendered loss as before.
"""
from __future__ import annotations

import torch

# which surfel centres a view sees: the cross-view test of the query initialisation's mask association
from psimap.panoptic.associate import seen_pixels


def lifted_class_votes(means: torch.Tensor, views, columns: list, n_classes: int) -> torch.Tensor:
    """Votes [N, S] float (S = n_classes): per surfel and class column, how many views see the
    surfel's centre on a pixel of that class. views: Views (depth, K, viewmat); columns: per view its
    pixels' class columns [H * W] long in [-1, S) (-1 void: no vote), or None (the view does not
    vote)."""
    n, s = int(means.shape[0]), int(n_classes)
    votes = torch.zeros(n * s, dtype=torch.float32)
    if s == 0:
        return votes.reshape(n, 0)
    for fr, cols in zip(views, columns):
        if cols is None:
            continue
        idx, pix = seen_pixels(means, fr.depth, fr.K, fr.viewmat)
        c = cols[pix]
        ok = c >= 0
        votes.index_add_(0, idx[ok] * s + c[ok], torch.ones(int(ok.sum())))
    return votes.reshape(n, s)


def vote_logits(votes: torch.Tensor, prior: float = 1.0) -> torch.Tensor:
    """Initial logits [N, S] from votes [N, S]: the log of the vote shares smoothed by `prior`
    pseudo-votes per class, log((c + prior) / (n + S prior)); a surfel no view saw gets all zeros
    (uniform, the field's own start)."""
    s = votes.shape[1]
    if s == 0:
        return votes.clone()
    total = votes.sum(-1, keepdim=True)
    logits = torch.log((votes + prior) / (total + s * prior))
    return torch.where(total > 0, logits, torch.zeros_like(logits))
