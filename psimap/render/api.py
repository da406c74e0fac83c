"""The public entry point `rasterize(...)`: validate inputs, project (stage 1), dispatch a backend."""
from __future__ import annotations

import torch

from psimap import PsimapError
from psimap.render.output import RenderOutput

BACKENDS = ("reference", "native", "cuda", "auto")
TILE_MODES = ("precise", "circle")


def _check(name: str, t, shape: tuple, n: int | None = None) -> None:
    """Raise ValueError unless t is a tensor of `shape` (-1 = N) with only finite values."""
    if not isinstance(t, torch.Tensor):
        raise ValueError(f"rasterize: {name} must be a torch.Tensor, got {type(t).__name__}")
    want = tuple(n if s == -1 else s for s in shape)
    if len(t.shape) != len(want) or any(s is not None and s != a for s, a in zip(want, t.shape)):
        pretty = "[" + ", ".join("N" if s == -1 else ("C" if s is None else str(s)) for s in shape) + "]"
        raise ValueError(f"rasterize: {name} must have shape {pretty} (N = {n}), got {list(t.shape)}")
    if not t.is_floating_point():
        raise ValueError(f"rasterize: {name} must be a floating-point tensor, got {t.dtype}")
    # A finite sum means every value is finite (a NaN or an inf would carry into it) in one
    # pass without temporaries; only when it is not (or it overflowed) is each value looked at.
    if t.numel() and not bool(torch.isfinite(t.sum())) and not bool(torch.isfinite(t).all()):
        bad = int((~torch.isfinite(t)).sum())
        raise ValueError(f"rasterize: {name} contains {bad} NaN/inf value(s)")


def native_available() -> bool:
    """Whether the compiled kernels import (without them backend="auto" renders with torch)."""
    try:
        from psimap.render.native import rasterize_native  # noqa: F401
    except Exception:
        return False
    return True


def _use_cuda(backend: str, device: torch.device, dtype: torch.dtype, channels: int, topk: int | None,
              needs_grad: bool) -> bool:
    """Whether to render with the CUDA kernel: always for backend="cuda" (ValueError where it cannot:
    not a CUDA device, a gradient needed, inputs beyond it; PsimapError when it cannot be built),
    for "auto" (on a CUDA device) when nothing needs a gradient, it covers the inputs and builds."""
    from psimap.render import cuda

    if backend != "cuda":
        return not needs_grad and cuda.supported(dtype, channels, topk) and cuda.available()
    if device.type != "cuda":
        raise ValueError(f"rasterize: backend='cuda' needs the tensors on a CUDA device, got {device}")
    if needs_grad:
        raise ValueError("rasterize: backend='cuda' renders without gradients (forward only); "
                         "use backend='reference' or 'auto', or render under torch.no_grad()")
    if not cuda.supported(dtype, channels, topk):
        raise ValueError(f"rasterize: backend='cuda' takes float32 with C <= {cuda.MAX_CHANNELS_ALL} channels "
                         f"blending all or topk <= {cuda.MAX_TOPK}; got {dtype}, C = {channels}, topk = {topk}")
    try:
        cuda.load_extension()
    except RuntimeError as exc:
        raise PsimapError(f"{exc}; use backend='reference'") from exc
    return True


def project(means, quats, scales, opacities, viewmat, K, width: int, height: int, near: float = 0.2,
            far: float = 1000.0):
    """Stage 1 (psimap.render.project.Projected): the native projection where it is built, the
    tensors are on the CPU and the camera needs no gradient (it has none: a pose being optimised
    needs the torch projection, psimap.render.project.project_surfels, used otherwise)."""
    from psimap.render.project import project_surfels

    if means.device.type == "cpu" and not (viewmat.requires_grad or K.requires_grad) and native_available():
        from psimap.render.native import project_surfels as project_native

        return project_native(means, quats, scales, opacities, viewmat, K, width, height, near, far)
    return project_surfels(means, quats, scales, opacities, viewmat, K, width, height, near, far)


def rasterize(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int,
              features=None, topk: int | None = None, tiles: str = "precise",
              backend: str = "reference", near: float = 0.2, far: float = 1000.0,
              background=None) -> RenderOutput:
    """Render N 2D Gaussian surfels into one camera (math: psimap/render/SPEC.md).

    means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 2] (> 0), opacities [N] in (0, 1),
    colors [N, 3], viewmat [4, 4] world-to-camera (OpenCV), K [3, 3], features [N, C] or None.
    topk: features blend only the K largest-weight surfels per pixel (None = all).
    tiles: "precise" (tight AABB) or "circle" (bounding circle, the baseline).
    backend: "reference" (torch), "native" (C++), "cuda" (the CUDA kernel, forward only: no input may
    need a gradient), "auto" (native on CPU when built; on a CUDA device the CUDA kernel when nothing
    needs a gradient and it covers the inputs, else torch).
    Non-finite inputs or wrong shapes raise ValueError. Everything but backend="cuda" is differentiable.
    """
    if not isinstance(means, torch.Tensor):
        raise ValueError(f"rasterize: means must be a torch.Tensor, got {type(means).__name__}")
    n = means.shape[0] if means.dim() == 2 else None
    _check("means", means, (-1, 3), n)
    dtype, device = means.dtype, means.device
    _check("quats", quats, (-1, 4), n)
    _check("scales", scales, (-1, 2), n)
    _check("opacities", opacities, (-1,), n)
    _check("colors", colors, (-1, 3), n)
    viewmat = torch.as_tensor(viewmat, dtype=dtype, device=device)
    K = torch.as_tensor(K, dtype=dtype, device=device)
    _check("viewmat", viewmat, (4, 4))
    _check("K", K, (3, 3))
    if features is not None:
        _check("features", features, (-1, None), n)
    if background is not None:
        background = torch.as_tensor(background, dtype=dtype, device=device)
        _check("background", background, (3,))
    for name, t in (("quats", quats), ("scales", scales), ("opacities", opacities), ("colors", colors),
                    ("features", features)):
        if t is not None and (t.dtype != dtype or t.device != device):
            raise ValueError(f"rasterize: {name} is {t.dtype} on {t.device} but means is {dtype} on {device}")
    if int(width) != width or int(height) != height or width <= 0 or height <= 0:
        raise ValueError(f"rasterize: width and height must be positive integers, got {width} x {height}")
    width, height = int(width), int(height)
    if not (0 < near < far) or not all(map(lambda v: v == v and abs(v) != float("inf"), (near, far))):
        raise ValueError(f"rasterize: need 0 < near < far (finite), got near={near}, far={far}")
    if topk is not None and (int(topk) != topk or topk < 1):
        raise ValueError(f"rasterize: topk must be a positive integer or None, got {topk}")
    if tiles not in TILE_MODES:
        raise ValueError(f"rasterize: tiles must be one of {TILE_MODES}, got {tiles!r}")
    if backend not in BACKENDS:
        raise ValueError(f"rasterize: backend must be one of {BACKENDS}, got {backend!r}")

    from psimap.render.project import project_surfels

    if backend == "cuda" or (backend == "auto" and device.type == "cuda"):
        needs_grad = torch.is_grad_enabled() and any(
            t is not None and t.requires_grad for t in (means, quats, scales, opacities, colors, viewmat, K,
                                                        features, background))
        if _use_cuda(backend, device, dtype, 0 if features is None else int(features.shape[1]), topk, needs_grad):
            from psimap.render.cuda import rasterize_cuda

            proj = project_surfels(means, quats, scales, opacities, viewmat, K, width, height, near, far)
            return rasterize_cuda(proj, opacities, colors, features, width, height, topk, tiles, near, far,
                                  background)

    use_native = backend == "native" or (backend == "auto" and device.type == "cpu" and native_available())
    if use_native:
        try:
            from psimap.render.native import rasterize_native
        except Exception as exc:   # an unbuilt extension is the user's setup, not a bug
            raise PsimapError(f"native renderer backend is not available ({exc}); "
                              f"reinstall psimap to build it, or use backend='reference'") from exc
        proj = project(means, quats, scales, opacities, viewmat, K, width, height, near, far)
        return rasterize_native(proj, opacities, colors, features, width, height, topk, tiles,
                                near, far, background)
    from psimap.render.reference import rasterize_reference

    proj = project_surfels(means, quats, scales, opacities, viewmat, K, width, height, near, far)
    return rasterize_reference(proj, opacities, colors, features, width, height, topk=topk, tiles=tiles,
                               near=near, far=far, background=background)
