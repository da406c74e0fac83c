"""What every training loop does with a NaN / inf loss or gradient: skip that update, count it, and
stop with one clear error when it keeps happening.

One bad frame (a degenerate view, a mask the matcher cannot use) must not poison the map; a
persistent one is an error, raised before anything is written. The geometry loop
(`psimap.train.trainer`) and the panoptic loop (`psimap.panoptic.fit`) both use this.
"""
from __future__ import annotations

from psimap import PsimapError


class Diverged(PsimapError):
    """A loss term or gradient became NaN / inf for too many consecutive steps."""


def backward_if_finite(terms: dict, params: dict) -> str | None:
    """Backpropagate the sum of `terms` ({name: scalar tensor}) when every term is finite.

    Returns what was not finite, "loss term 'NAME'" (nothing was backpropagated) or "gradient of
    NAME" (the first of `params` {name: leaf tensor} whose gradient holds NaN / inf), else None.
    """
    import torch

    bad = next((name for name, v in terms.items() if not bool(torch.isfinite(v).all())), None)
    if bad is not None:
        return f"loss term '{bad}'"
    sum(terms.values()).backward()
    # a NaN or inf anywhere makes the sum NaN or inf: one pass, no [N, ...] bool temporary (a
    # finite gradient whose sum overflows float32, |sum| > 3e38, is refused too)
    return next((f"gradient of {name}" for name, p in params.items()
                 if p.grad is not None and not bool(torch.isfinite(p.grad.sum()))), None)


class NonFiniteGuard:
    """Counts skipped updates; raises Diverged after `limit` consecutive ones."""

    def __init__(self, limit: int = 10):
        self.limit = limit
        self.streak = 0
        self.skipped = 0

    def ok(self) -> None:
        self.streak = 0

    def skip(self, what: str, where: str) -> None:
        self.streak += 1
        self.skipped += 1
        if self.streak >= self.limit:
            raise Diverged(f"{where}: {what} was NaN/inf for {self.streak} consecutive steps; "
                           f"nothing was written")
