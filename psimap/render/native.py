"""Native CPU backend of the renderer: stages 1-3 of SPEC.md in C++ (psimap/render/csrc).

The extension `psimap.render._native` takes and returns contiguous float32 / int32 numpy buffers;
this module wraps it in two `torch.autograd.Function`s: `project_surfels` (stage 1, the C++ twin of
psimap/render/project.py's torch reference of the same name) and the rasterizer, whose backward
returns gradients with respect to the stage-1 outputs (T, center, depth_key, normal_c) and
opacities / colors / features; autograd chains those through the projection's backward into
means / quats / scales.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from psimap.render import _native
from psimap.render.output import RenderOutput
from psimap.render.project import Projected

# Tests set this: every output buffer is filled with NaN (-1 for ints, 255 for flags) before the kernels run, so a
# pixel or surfel the kernels forget to write shows up instead of passing as stale memory.
POISON_OUTPUTS = False
MAX_TOPK = _native.MAX_TOPK


def set_num_threads(n: int) -> None:
    """OpenMP threads used by the native kernels (binning, forward, backward)."""
    _native.set_num_threads(int(n))


def get_num_threads() -> int:
    return int(_native.get_num_threads())


def pixel_kernels() -> str:
    """Instruction set of the SIMD pixel kernels in use: "avx512" (16 pixels per vector), "avx2" (8)
    or "baseline" (4: SSE2 / NEON); the widest this CPU runs, chosen at import (docs/renderer.md)."""
    return str(_native.pixel_kernels())


def _empty(shape, dtype=np.float32) -> np.ndarray:
    if POISON_OUTPUTS:
        if np.issubdtype(dtype, np.integer):
            return np.full(shape, np.iinfo(dtype).max if np.iinfo(dtype).min == 0 else -1, dtype=dtype)
        return np.full(shape, np.nan, dtype=dtype)
    return np.empty(shape, dtype=dtype)


def _f32(t: torch.Tensor) -> np.ndarray:
    """Contiguous float32 numpy view (copy only when dtype/layout require it)."""
    return np.ascontiguousarray(t.detach().to(torch.float32).cpu().numpy())


class _ProjectNative(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, frame):
        # means [N,3], quats [N,4], scales [N,2], opacities [N] -> T [N,3,3], center [N,2],
        # depth_key [N], normal_c [N,3] (differentiable) + valid [N], box_precise / box_circle [N,4].
        dtype = means.dtype
        suffix = "f64" if dtype == torch.float64 else "f32"
        np_dtype = np.float64 if suffix == "f64" else np.float32
        arrays = [np.ascontiguousarray(t.detach().to(dtype).numpy()) for t in (means, quats, scales, opacities)]
        n = arrays[3].shape[0]
        T, center, key = _empty((n, 3, 3), np_dtype), _empty((n, 2), np_dtype), _empty((n,), np_dtype)
        normal = _empty((n, 3), np_dtype)
        valid, flip = _empty((n,), np.uint8), _empty((n,), np.uint8)
        box_p, box_c = _empty((n, 4), np.int32), _empty((n, 4), np.int32)
        ctx.set_materialize_grads(False)   # unused outputs' gradients arrive as None
        getattr(_native, "project_forward_" + suffix)(*arrays, *frame, T, center, key, normal, valid, flip,
                                                      box_p, box_c)
        ctx.frame, ctx.arrays, ctx.masks, ctx.suffix, ctx.dtype = frame, arrays, (valid, flip), suffix, dtype
        valid_t = torch.from_numpy(valid.view(np.bool_))
        ctx.mark_non_differentiable(valid_t)
        return (torch.from_numpy(T), torch.from_numpy(center), torch.from_numpy(key),
                torch.from_numpy(normal), valid_t, torch.from_numpy(box_p), torch.from_numpy(box_c))

    @staticmethod
    def backward(ctx, g_T, g_center, g_key, g_normal, _valid, _box_p, _box_c):
        arrays = ctx.arrays
        n = arrays[3].shape[0]
        np_dtype = arrays[0].dtype
        as_np = lambda g, shape: (np.zeros(shape, np_dtype) if g is None  # noqa: E731
                                  else np.ascontiguousarray(g.detach().to(ctx.dtype).numpy()))
        grads_in = [as_np(g_T, (n, 3, 3)), as_np(g_center, (n, 2)), as_np(g_key, (n,)), as_np(g_normal, (n, 3))]
        g_means, g_quats, g_scales = _empty((n, 3), np_dtype), _empty((n, 4), np_dtype), _empty((n, 2), np_dtype)
        getattr(_native, "project_backward_" + ctx.suffix)(*arrays, *ctx.frame, *ctx.masks, *grads_in,
                                                           g_means, g_quats, g_scales)
        return torch.from_numpy(g_means), torch.from_numpy(g_quats), torch.from_numpy(g_scales), None, None


def project_surfels(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                    opacities: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor,
                    width: int, height: int, near: float = 0.2, far: float = 1000.0) -> Projected:
    """Stage 1 of SPEC.md in C++: the native twin of psimap.render.project.project_surfels (the
    readable torch reference, which tests hold this one to), differentiable in means / quats /
    scales. means: [N, 3], quats: [N, 4] (w, x, y, z), scales: [N, 2], opacities: [N] on the CPU,
    float32 or float64; viewmat: [4, 4] world-to-camera (OpenCV), K: [3, 3], both without
    gradients (camera gradients need the torch reference). Non-finite surfels are culled, never NaN."""
    if means.device.type != "cpu":
        raise ValueError(f"project_surfels: the native backend runs on CPU tensors, got {means.device}")
    if viewmat.requires_grad or K.requires_grad:
        raise ValueError("project_surfels: the native projection has no camera gradients; "
                         "use psimap.render.project.project_surfels for a differentiable camera")
    dtype = means.dtype if means.dtype in (torch.float32, torch.float64) else torch.float32
    frame = (np.ascontiguousarray(viewmat.detach().to(torch.float64).cpu().numpy()),
             np.ascontiguousarray(K.detach().to(torch.float64).cpu().numpy()),
             int(width), int(height), float(near), float(far))
    T, center, key, normal, valid, box_p, box_c = _ProjectNative.apply(
        means.to(dtype), quats.to(dtype), scales.to(dtype), opacities.to(dtype), frame)
    return Projected(T=T, center=center, depth_key=key, normal_c=normal, valid=valid,
                     box_precise=box_p, box_circle=box_c)


@dataclass
class _Plan:
    """Everything the forward and backward share besides the differentiable tensors."""

    box: np.ndarray          # [N, 4] int32 pixel boxes the surfels were binned with
    offsets: np.ndarray      # [tiles + 1] int32
    ids: np.ndarray          # [pairs] int32
    width: int
    height: int
    topk: int                # 0 = blend features over every surfel
    exact_footprint: bool    # precise tiles: cull 4x4 pixel blocks by the surfel's footprint too
    near: float
    far: float
    background: np.ndarray   # [3] float32
    evaluated: int = 0


def _kernel_args(plan: _Plan, arrays: list[np.ndarray], channels: int) -> tuple:
    T, center, depth_key, normal, opac, colors, feats = arrays
    return (T, center, depth_key, normal, opac, colors, feats, channels, plan.box, plan.offsets, plan.ids,
            plan.width, plan.height, plan.topk, plan.exact_footprint, plan.near, plan.far, plan.background)


class _RasterizeNative(torch.autograd.Function):
    @staticmethod
    def forward(ctx, T, center, depth_key, normal_c, opacities, colors, features, plan: _Plan):
        # T [N,3,3], center [N,2], depth_key [N], normal_c [N,3], opacities [N], colors [N,3],
        # features [N,C] -> rgb [H,W,3], alpha, depth, median [H,W], normal [H,W,3], distortion,
        # features [H,W,C].
        H, W, C, K = plan.height, plan.width, features.shape[1], plan.topk
        # Outputs the loss does not use come back as None (the backward passes zeros to the
        # kernel) instead of torch allocating and filling a zero image for each.
        ctx.set_materialize_grads(False)
        arrays = [_f32(t) for t in (T, center, depth_key, normal_c, opacities, colors, features)]
        rgb, alpha, depth = _empty((H, W, 3)), _empty((H, W)), _empty((H, W))
        median, normal, dist = _empty((H, W)), _empty((H, W, 3)), _empty((H, W))
        feat = _empty((H, W, C))
        t_final, dist_sums = _empty((H, W)), _empty((H, W, 3), np.float64)
        n_last, median_pos = _empty((H, W), np.int32), _empty((H, W), np.int32)
        topk_pos = _empty((H, W, K), np.int32)
        plan.evaluated = int(_native.rasterize_forward(
            *_kernel_args(plan, arrays, C), rgb, alpha, depth, median, normal, dist, feat,
            t_final, n_last, median_pos, dist_sums, topk_pos, np.empty(0, np.float32)))
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


def _make_plan(proj: Projected, width: int, height: int, topk: int | None, tiles: str, near: float,
               far: float, background: torch.Tensor | None, force_topk: bool = False):
    """Bins the surfels into tiles; returns (_Plan, binned [N] bool, most surfels in one tile)."""
    box = (proj.box_precise if tiles == "precise" else proj.box_circle).detach().cpu()
    box_np = np.ascontiguousarray(box.numpy().astype(np.int32, copy=False))
    binned = (proj.valid.detach().cpu().numpy() & (box_np[:, 2] > box_np[:, 0])
              & (box_np[:, 3] > box_np[:, 1]))
    offsets, ids = _native.bin_tiles(box_np, binned.astype(np.uint8), _f32(proj.depth_key), int(width),
                                     int(height))
    counts = np.diff(offsets)
    max_pairs = int(counts.max()) if counts.size else 0
    # Top-K over at least as many surfels as any tile holds selects them all: blend every one.
    k = 0 if (topk is None or (topk >= max_pairs and not force_topk)) else int(topk)
    if k > MAX_TOPK:
        raise ValueError(f"rasterize: the native backend supports topk <= {MAX_TOPK} "
                         f"(got {topk}); use backend='reference' or a smaller topk")
    bg = (np.zeros(3, np.float32) if background is None
          else np.ascontiguousarray(background.detach().to(torch.float32).cpu().numpy().reshape(3)))
    plan = _Plan(box=box_np, offsets=offsets, ids=ids, width=int(width), height=int(height), topk=k,
                 exact_footprint=tiles == "precise", near=float(near), far=float(far), background=bg)
    return plan, binned, max_pairs


@torch.no_grad()
def topk_weights(proj: Projected, opacities: torch.Tensor, width: int, height: int, topk: int,
                 tiles: str = "precise", near: float = 0.2,
                 far: float = 1000.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Which surfels a Top-K feature render blends at each pixel, and with what weight: (ids
    [H, W, topk] int64 surfel indices, -1 padded; weights [H, W, topk] float32 w = alpha T, 0
    padded; alpha [H, W]). For fixed geometry, `rasterize(..., features=f, topk=topk).features`
    equals `(weights[..., None] * f[ids.clamp_min(0)]).sum(-2)` up to float rounding: a panoptic
    step on frozen geometry gathers instead of rasterizing (psimap.panoptic.fit)."""
    n = int(opacities.shape[0])
    if not 1 <= topk <= MAX_TOPK:
        raise ValueError(f"topk_weights: topk must be in 1..{MAX_TOPK}, got {topk}")
    plan, _, _ = _make_plan(proj, width, height, topk, tiles, near, far, None, force_topk=True)
    H, W, K = plan.height, plan.width, plan.topk
    arrays = [_f32(proj.T), _f32(proj.center), _f32(proj.depth_key), _f32(proj.normal_c), _f32(opacities),
              np.zeros((n, 3), np.float32), np.zeros((n, 1), np.float32)]
    out = [_empty((H, W, 3)), _empty((H, W)), _empty((H, W)), _empty((H, W)), _empty((H, W, 3)),
           _empty((H, W)), _empty((H, W, 1)), _empty((H, W)), _empty((H, W), np.int32),
           _empty((H, W), np.int32), _empty((H, W, 3), np.float64)]
    pos, w = _empty((H, W, K), np.int32), _empty((H, W, K))
    _native.rasterize_forward(*_kernel_args(plan, arrays, 1), *out, pos, w)
    # tile-list position -> surfel index, through the slice of the bins of the pixel's tile
    tile = _native.TILE
    tiles_x = (W + tile - 1) // tile
    ty, tx = np.arange(H) // tile, np.arange(W) // tile
    start = plan.offsets[:-1][ty[:, None] * tiles_x + tx[None, :]].astype(np.int64)      # [H, W]
    if plan.ids.size == 0:
        return torch.full((H, W, K), -1, dtype=torch.int64), torch.from_numpy(w), torch.from_numpy(out[1])
    # one gather of every slot, the empty ones (pos -1) pointed at entry 0 and then set to -1:
    # half the time of a boolean-mask gather and scatter
    flat = start[:, :, None] + pos
    np.maximum(flat, 0, out=flat)
    ids = plan.ids.take(flat).astype(np.int64)
    ids[pos < 0] = -1
    return torch.from_numpy(ids), torch.from_numpy(w), torch.from_numpy(out[1])


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
    plan, binned, max_pairs = _make_plan(proj, width, height, topk if C > 0 else None, tiles, near, far,
                                         background)
    offsets, ids = plan.offsets, plan.ids
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


def _check_field_inputs(name: str, dot: torch.Tensor, terms: torch.Tensor, coef: torch.Tensor) -> None:
    """The field kernels' shared inputs: dot [V, Q] float32, terms [V, K] and coef [Q, K] float64."""
    if dot.dtype != torch.float32 or terms.dtype != torch.float64 or coef.dtype != torch.float64 \
            or dot.dim() != 2 or terms.dim() != 2 or coef.dim() != 2 or terms.shape[0] != dot.shape[0] \
            or coef.shape[0] != dot.shape[1] or terms.shape[1] != coef.shape[1]:
        raise ValueError(f"{name}: dot [V, Q] float32, terms [V, K] and coef [Q, K] float64")


class _FieldDistribution(torch.autograd.Function):
    """The panoptic field's per-surfel instance distribution, fused (csrc/field_lanes.inl);
    psimap.panoptic.queries.instance_distribution_reference is the torch form it is held to."""

    @staticmethod
    def forward(ctx, dot, terms, coef, p_thing, temperature):
        v, q = dot.shape
        k = terms.shape[1]
        dot_np = np.ascontiguousarray(dot.detach().numpy())
        terms_np = np.ascontiguousarray(terms.detach().numpy())
        coef_t = np.ascontiguousarray(coef.detach().numpy().T)
        pt_np = np.zeros(0, np.float32) if p_thing is None else np.ascontiguousarray(p_thing.detach().numpy())
        out, soft = _empty((v, q)), _empty((v, q))
        _native.field_distribution_forward(dot_np, terms_np, coef_t, pt_np, v, q, k, float(temperature), out, soft)
        ctx.arrays = (dot_np, terms_np, coef_t, pt_np, soft)
        ctx.temperature = float(temperature)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, v_out):
        dot_np, terms_np, coef_t, pt_np, soft = ctx.arrays
        v, q = soft.shape
        k = terms_np.shape[1]
        v_dot, v_coef_t = _empty((v, q)), _empty((k, q), np.float64)
        v_pt = _empty((v,)) if pt_np.size else np.zeros(0, np.float32)
        _native.field_distribution_backward(dot_np, terms_np, coef_t, pt_np, soft, _f32(v_out), v, q, k,
                                            ctx.temperature, v_dot, v_coef_t, v_pt)
        return (torch.from_numpy(v_dot), None, torch.from_numpy(v_coef_t.T),
                torch.from_numpy(v_pt) if pt_np.size else None, None)


def instance_distribution(dot: torch.Tensor, terms: torch.Tensor, coef: torch.Tensor, p_thing: torch.Tensor | None,
                          temperature: float) -> torch.Tensor:
    """softmax_q(sigmoid(dot) exp(-min(m2, 160) / 2) / temperature) * p_thing: [V, Q] float32, with
    m2 = terms @ coef.T in float64 (never built: each row's distances are summed on the kernel's
    lanes); differentiable in dot [V, Q] float32, coef [Q, K] float64 (the queries' coefficients)
    and p_thing [V] float32 (None: 1); terms [V, K] float64 (the surfels' monomials) are constants.
    CPU tensors, on the calling thread (csrc/bindings.cpp says why)."""
    _check_field_inputs("instance_distribution", dot, terms, coef)
    if p_thing is not None and (p_thing.dtype != torch.float32 or p_thing.shape != dot.shape[:1]):
        raise ValueError("instance_distribution: p_thing [V] float32")
    return _FieldDistribution.apply(dot, terms, coef, p_thing, float(temperature))


def instance_affinity(dot: torch.Tensor, terms: torch.Tensor, coef: torch.Tensor) -> torch.Tensor:
    """sigmoid(dot) exp(-min(m2, 160) / 2): [V, Q] float32, m2 = terms @ coef.T in float64 summed on
    the lanes (csrc/field_lanes.inl, the distribution kernel's affinity before its softmax); dot
    [V, Q] float32, terms [V, K] and coef [Q, K] float64. No gradient (the scene-wide labels and
    adjustments read it). On the calling thread."""
    _check_field_inputs("instance_affinity", dot, terms, coef)
    v, q = dot.shape
    k = terms.shape[1]
    out = _empty((v, q))
    _native.field_affinity(np.ascontiguousarray(dot.detach().numpy()), np.ascontiguousarray(terms.detach().numpy()),
                           np.ascontiguousarray(coef.detach().numpy().T), v, q, k, out)
    return torch.from_numpy(out)


def match_sums(x: torch.Tensor, codes: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
    """The Hungarian matching's per-mask sums [5, M, Q] float64 over x [P, Q] float32 (a view's
    rendered query probabilities, pixel-major) clamped to [lo, hi]: x, log x and log(1 - x) on each
    mask, x and log(1 - x) on its window; codes [M, P] uint8 (0: outside mask m's window, 1: in it,
    2: on the mask). psimap.panoptic.matching.match_sums_reference is the torch form (csrc/match_lanes.inl).
    On the calling thread."""
    if x.dtype != torch.float32 or codes.dtype != torch.uint8 or x.dim() != 2 or codes.dim() != 2 \
            or codes.shape[1] != x.shape[0]:
        raise ValueError("match_sums: x [P, Q] float32 and codes [M, P] uint8")
    p, q = x.shape
    m = codes.shape[0]
    sums = _empty((5, m, q), np.float64)
    _native.match_sums(np.ascontiguousarray(x.detach().numpy()), np.ascontiguousarray(codes.numpy()),
                       p, q, m, float(lo), float(hi), sums)
    return torch.from_numpy(sums)


def blend_rows(A, f: torch.Tensor) -> torch.Tensor:
    """A @ f [R, C] for a scipy CSR matrix A [R, V] float32 (a frozen blend, psimap.panoptic.fit) and
    f [V, C] float32: the sums scipy makes, in the same order (bit for bit), the features on the
    kernel's lanes (csrc/blend_lanes.inl). On the calling thread."""
    r, v = A.shape
    data = np.asarray(A.data)
    x = np.ascontiguousarray(f.detach().numpy())
    if data.dtype != np.float32 or x.dtype != np.float32 or x.ndim != 2 or x.shape[0] != v:
        raise ValueError("blend_rows: A float32 CSR [R, V] and f float32 [V, C]")
    out = _empty((r, x.shape[1]))
    _native.blend_rows(np.asarray(A.indptr, dtype=np.int64), np.asarray(A.indices, dtype=np.int32), data, x,
                       r, v, x.shape[1], out)
    return torch.from_numpy(out)


def depth_test(points: np.ndarray, c2w: np.ndarray, K: np.ndarray, depth: np.ndarray, tolerance: float,
               surface: bool, state: np.ndarray) -> int:
    """One camera's depth test of world points [Q, 3] float64 (c2w [4, 4] OpenCV, K [3, 3], depth [H,
    W] float64, 0 / non-finite: no return): sets state [Q] uint8 to 1 where it is 0 and the camera sees
    the point in front of its depth by more than `tolerance` (surface False) or within it (True);
    returns the number set. psimap.completion.freespace's known_free_reference and
    seen_on_surface_reference are the numpy forms (csrc/depth_test.cpp). On the calling thread."""
    depth = np.ascontiguousarray(depth, dtype=np.float64)
    if depth.ndim != 2 or state.dtype != np.uint8 or not state.flags.c_contiguous:
        raise ValueError("depth_test: depth [H, W] and state [Q] contiguous uint8")
    h, w = depth.shape
    return int(_native.depth_test(np.ascontiguousarray(points, dtype=np.float64),
                                  np.ascontiguousarray(c2w, dtype=np.float64),
                                  np.ascontiguousarray(K, dtype=np.float64), w, h, depth, float(tolerance),
                                  int(bool(surface)), state))
