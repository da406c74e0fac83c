"""What every renderer backend returns (psimap.render.native, psimap.render.reference): its own
module, so the backends do not import the dispatcher (psimap.render.api) that imports them."""
from __future__ import annotations

from dataclasses import dataclass, field

import torch


@dataclass
class RenderOutput:
    """Rendered maps of one view (H x W); every tensor is differentiable.

    rgb [H, W, 3], alpha [H, W], depth [H, W] (expected hit depth, normalised by alpha),
    median_depth [H, W], normal [H, W, 3] (camera frame, camera-facing, alpha-weighted sum),
    distortion [H, W], features [H, W, C]; stats: tile_pairs, pairs_per_tile, evaluated, culled, ...
    """

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    median_depth: torch.Tensor
    normal: torch.Tensor
    distortion: torch.Tensor
    features: torch.Tensor
    stats: dict = field(default_factory=dict)
