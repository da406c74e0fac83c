"""Adaptive density control: clone / split under-fitted surfels, prune useless ones, within a budget.

Surfel parameters live in a dict of leaf tensors (means [N,3], quats [N,4], log_scales [N,2],
opacity_logit [N], color_logit [N,3]), each its own Adam parameter group; changing N rewrites the
tensors and the optimiser's moment buffers together (kept rows carry their moments, new rows start
at zero).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from psimap.transforms import quat_to_rotmat_torch


@dataclass
class GradStats:
    """Running mean of each surfel's screen-space positional gradient (NDC units, as 3DGS / 2DGS)
    over the views it was in."""

    total: torch.Tensor      # [N]
    count: torch.Tensor      # [N]

    @classmethod
    def zeros(cls, n: int) -> "GradStats":
        return cls(torch.zeros(n), torch.zeros(n))

    def mean(self) -> torch.Tensor:
        return self.total / self.count.clamp_min(1)


def accumulate(stats: GradStats, grad_means, means, viewmat, K, width: int, height: int) -> None:
    """Add one view's screen-space gradient magnitude in NDC units.

    grad_means [N,3] dL/dmu (world); means [N,3]; viewmat [4,4] world-to-camera; K [3,3] pixels.
    Moving a surfel by one pixel along x moves it z / fx metres parallel to the image plane, so
    dL/du = dL/dx_cam * z / fx; NDC spans the image with 2 units, u = (x_ndc + 1) W / 2, so
    dL/dx_ndc = dL/du * W / 2 (and H / 2 for y). This is the quantity 3DGS / 2DGS threshold (2e-4);
    in pixel units the same threshold would be W / 2 times stricter and hardly ever trigger.
    """
    with torch.no_grad():
        R = viewmat[:3, :3]
        g_cam = grad_means @ R.T                                   # [N, 3] camera-frame gradient
        z = (means @ R[2] + viewmat[2, 3]).clamp_min(1e-6)
        gx = g_cam[:, 0] * z / float(K[0, 0]) * (0.5 * width)
        gy = g_cam[:, 1] * z / float(K[1, 1]) * (0.5 * height)
        g_ndc = torch.sqrt(gx * gx + gy * gy)
        seen = (grad_means.abs().sum(1) > 0) & (means @ R[2] + viewmat[2, 3] > 0)
        stats.total += torch.where(seen, g_ndc, torch.zeros_like(g_ndc))
        stats.count += seen.float()


def _rebuild(params: dict, optimizer, keep, extra: dict) -> None:
    """Replace each parameter by cat(p[keep], extra[name]) and carry the Adam moments along."""
    for group in optimizer.param_groups:
        old = group["params"][0]
        name = group["name"]
        new_rows = extra[name].detach()
        new = torch.cat([old.detach()[keep], new_rows]).requires_grad_(True)
        st = optimizer.state.pop(old, None)
        if st:
            for k in ("exp_avg", "exp_avg_sq"):
                st[k] = torch.cat([st[k][keep], torch.zeros_like(new_rows)])
            optimizer.state[new] = st
        group["params"][0] = new
        params[name] = new


def densify_and_prune(params: dict, optimizer, stats: GradStats, *, grad_threshold: float,
                      large_scale: float, prune_opacity: float, max_scale: float, budget: int,
                      generator: torch.Generator, first: torch.Tensor | None = None) -> dict:
    """One round of density control; returns counts {"cloned", "split", "pruned", "surfels"}.

    Clone surfels with mean view-space gradient > grad_threshold and max scale <= large_scale;
    split (2 children sampled on the surfel, scales / 1.6) those larger. Prune opacity <
    prune_opacity or max scale > max_scale. Growth stops at `budget` surfels (highest-gradient
    candidates first; with `first` [N] bool, those surfels' candidates before all others, so a
    budget that binds goes to them); above budget the least opaque surfels go.
    """
    with torch.no_grad():
        n = params["means"].shape[0]
        opacity = torch.sigmoid(params["opacity_logit"])
        scales = params["log_scales"].exp()
        smax = scales.max(1).values
        prune = (opacity < prune_opacity) | (smax > max_scale) | ~torch.isfinite(params["means"]).all(1)
        g = stats.mean()
        cand = (g > grad_threshold) & ~prune
        order = torch.argsort(-g[cand], stable=True)
        if first is not None:
            order = order[torch.argsort((~first[cand][order]).to(torch.int8), stable=True)]
        cand_idx = torch.nonzero(cand).squeeze(1)[order]
        room = max(0, budget - (n - int(prune.sum())))
        cand_idx = cand_idx[:room]
        big = smax[cand_idx] > large_scale
        clone_idx, split_idx = cand_idx[~big], cand_idx[big]

        extra = {k: [] for k in params}
        for k, v in params.items():                     # clones: exact copies (gradient moves them apart)
            extra[k].append(v[clone_idx])
        if len(split_idx):
            R = quat_to_rotmat_torch(params["quats"][split_idx])
            s = scales[split_idx]
            for _ in range(2):
                uv = torch.randn(len(split_idx), 2, generator=generator) * s
                pos = params["means"][split_idx] + (R[:, :, :2] @ uv[:, :, None])[..., 0]
                extra["means"].append(pos)
                extra["log_scales"].append(torch.log(s / 1.6))
                for k in ("quats", "opacity_logit", "color_logit"):
                    extra[k].append(params[k][split_idx])
        extra = {k: torch.cat(v) for k, v in extra.items()}
        drop = prune.clone()
        drop[split_idx] = True                          # parents replaced by their children
        keep = torch.nonzero(~drop).squeeze(1)
        _rebuild(params, optimizer, keep, extra)
        over = params["means"].shape[0] - budget
        pruned_budget = 0
        if over > 0:
            op = torch.sigmoid(params["opacity_logit"])
            order = torch.argsort(op, stable=True)
            keep2 = torch.sort(order[over:]).values
            _rebuild(params, optimizer, keep2, {k: v[:0] for k, v in params.items()})
            pruned_budget = over
        return {"cloned": int(len(clone_idx)), "split": int(len(split_idx)),
                "pruned": int(prune.sum()) + pruned_budget, "surfels": int(params["means"].shape[0])}
