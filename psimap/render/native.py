"""Native CPU backend of the renderer: stages 2-3 of SPEC.md in C++ (psimap/render/csrc).

The extension `psimap.render._native` takes and returns contiguous float32 / int32 numpy buffers;
this module wraps it in a `torch.autograd.Function` whose backward returns gradients with respect
to the stage-1 outputs (T, center, depth_key, normal_c) and opacities / colors / features, which
torch autograd then chains through `project_surfels` into means / quats / scales.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from psimap.render import _native
from psimap.render.output import RenderOutput
from psimap.render.project import Projected

# Tests set this: every output buffer is filled with NaN (-1 for ints) before the kernels run, so a
# pixel or surfel the kernels forget to write shows up instead of passing as stale memory.
POISON_OUTPUTS = False
MAX_TOPK = _native.MAX_TOPK


def set_num_threads(n: int) -> None:
    """OpenMP threads used by the native kernels (binning, forward, backward)."""
    _native.set_num_threads(int(n))


def get_num_threads() -> int:
    return int(_native.get_num_threads())


def _empty(shape, dtype=np.float32) -> np.ndarray:
    if POISON_OUTPUTS:
        return np.full(shape, -1 if np.issubdtype(dtype, np.integer) else np.nan, dtype=dtype)
    return np.empty(shape, dtype=dtype)


def _f32(t: torch.Tensor) -> np.ndarray:
    """Contiguous float32 numpy view (copy only when dtype/layout require it)."""
    return np.ascontiguousarray(t.detach().to(torch.float32).cpu().numpy())


@dataclass
class _Plan:
    """Everything the forward and backward share besides the differentiable tensors."""

    box: np.ndarray          # [N, 4] int32 pixel boxes the surfels were binned with
    offsets: np.ndarray      # [tiles + 1] int32
    ids: np.ndarray          # [pairs] int32
    width: int
    height: int
    topk: int                # 0 = blend features over every surfel
    near: float
    far: float
    background: np.ndarray   # [3] float32
    evaluated: int = 0


def _kernel_args(plan: _Plan, arrays: list[np.ndarray], channels: int) -> tuple:
    T, center, depth_key, normal, opac, colors, feats = arrays
    return (T, center, depth_key, normal, opac, colors, feats, channels, plan.box, plan.offsets, plan.ids,
            plan.width, plan.height, plan.topk, plan.near, plan.far, plan.background)


class _RasterizeNative(torch.autograd.Function):
    @staticmethod
    def forward(ctx, T, center, depth_key, normal_c, opacities, colors, features, plan: _Plan):
        # T [N,3,3], center [N,2], depth_key [N], normal_c [N,3], opacities [N], colors [N,3],
        # features [N,C] -> rgb [H,W,3], alpha, depth, median [H,W], normal [H,W,3], distortion,
        # features [H,W,C].
        H, W, C, K = plan.height, plan.width, features.shape[1], plan.topk
        arrays = [_f32(t) for t in (T, center, depth_key, normal_c, opacities, colors, features)]
        rgb, alpha, depth = _empty((H, W, 3)), _empty((H, W)), _empty((H, W))
        median, normal, dist = _empty((H, W)), _empty((H, W, 3)), _empty((H, W))
        feat = _empty((H, W, C))
        t_final, dist_sums = _empty((H, W)), _empty((H, W, 3), np.float64)
        n_last, median_pos = _empty((H, W), np.int32), _empty((H, W), np.int32)
        topk_pos = _empty((H, W, K), np.int32)
        plan.evaluated = int(_native.rasterize_forward(
            *_kernel_args(plan, arrays, C), rgb, alpha, depth, median, normal, dist, feat,
            t_final, n_last, median_pos, dist_sums, topk_pos))
        ctx.plan = plan
        ctx.arrays = arrays
        # depth is copied: the caller may modify the returned tensor in place.
        ctx.saved = (depth.copy(), t_final, n_last, median_pos, dist_sums, topk_pos)
        ctx.dtypes = [t.dtype for t in (T, center, depth_key, normal_c, opacities, colors, features)]
        dtype = colors.dtype
        return tuple(torch.from_numpy(a).to(dtype) for a in (rgb, alpha, depth, median, normal, dist, feat))

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth, g_median, g_normal, g_dist, g_feat):
        plan, arrays = ctx.plan, ctx.arrays
        H, W = plan.height, plan.width
        C = arrays[6].shape[1]
        N = arrays[4].shape[0]
        shapes = [(H, W, 3), (H, W), (H, W), (H, W), (H, W, 3), (H, W), (H, W, C)]
        grads_out = [np.zeros(s, np.float32) if g is None else _f32(g)
                     for g, s in zip((g_rgb, g_alpha, g_depth, g_median, g_normal, g_dist, g_feat), shapes)]
        gT, g_center, g_key = _empty((N, 3, 3)), _empty((N, 2)), _empty((N,))
        g_norm, g_opac, g_col, g_f = _empty((N, 3)), _empty((N,)), _empty((N, 3)), _empty((N, C))
        _native.rasterize_backward(*_kernel_args(plan, arrays, C), *ctx.saved, *grads_out,
                                   gT, g_center, g_key, g_norm, g_opac, g_col, g_f)
        grads = [torch.from_numpy(g).to(dt) for g, dt in
                 zip((gT, g_center, g_key, g_norm, g_opac, g_col, g_f), ctx.dtypes)]
        grads = [g if need else None for g, need in zip(grads, ctx.needs_input_grad[:7])]
        return (*grads, None)


def rasterize_native(proj: Projected, opacities: torch.Tensor, colors: torch.Tensor,
                     features: torch.Tensor | None, width: int, height: int, topk: int | None = None,
                     tiles: str = "precise", near: float = 0.2, far: float = 1000.0,
                     background: torch.Tensor | None = None) -> RenderOutput:
    """Stages 2-3 of SPEC.md in C++. proj: stage-1 output for N surfels; opacities [N],
    colors [N, 3], features [N, C] or None, background [3] or None. Returns a RenderOutput whose
    tensors are differentiable (through the native backward)."""
    if colors.device.type != "cpu":
        raise ValueError(f"rasterize: the native backend runs on CPU tensors, got {colors.device}; "
                         f"use backend='reference' or 'auto'")
    n = colors.shape[0]
    if features is None:
        features = colors.new_zeros(n, 0)
    C = int(features.shape[1])
    box = (proj.box_precise if tiles == "precise" else proj.box_circle).detach().cpu()
    box_np = np.ascontiguousarray(box.numpy().astype(np.int32, copy=False))
    binned = (proj.valid.detach().cpu().numpy() & (box_np[:, 2] > box_np[:, 0])
              & (box_np[:, 3] > box_np[:, 1]))
    offsets, ids = _native.bin_tiles(box_np, binned.astype(np.uint8), _f32(proj.depth_key), int(width),
                                     int(height))
    counts = np.diff(offsets)
    max_pairs = int(counts.max()) if counts.size else 0
    # Top-K over at least as many surfels as any tile holds selects them all: blend every one.
    k = 0 if (topk is None or C == 0 or topk >= max_pairs) else int(topk)
    if k > MAX_TOPK:
        raise ValueError(f"rasterize: the native backend supports topk <= {MAX_TOPK} "
                         f"(got {topk}); use backend='reference' or a smaller topk")
    bg = (np.zeros(3, np.float32) if background is None
          else np.ascontiguousarray(background.detach().to(torch.float32).cpu().numpy().reshape(3)))
    plan = _Plan(box=box_np, offsets=offsets, ids=ids, width=int(width), height=int(height), topk=k,
                 near=float(near), far=float(far), background=bg)
    outs = _RasterizeNative.apply(proj.T, proj.center, proj.depth_key, proj.normal_c,
                                  opacities, colors, features, plan)
    rgb, alpha, depth, median, normal, dist, feat = outs
    n_tiles = max(len(offsets) - 1, 1)
    stats = {
        "tile_pairs": int(ids.shape[0]),
        "pairs_per_tile": int(ids.shape[0]) / n_tiles,
        "max_pairs_per_tile": max_pairs,
        # Actual work: (pixel, surfel) pairs inside the surfel's box, until the pixel's T < 1e-4.
        "evaluated": plan.evaluated,
        "culled": int(n - int(binned.sum())),
        "backend": "native",
        "tiles": tiles,
    }
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, median_depth=median, normal=normal,
                        distortion=dist, features=feat, stats=stats)
