"""Stages 2-3 of SPEC.md on a CUDA device, forward only: torch binning, then the blend kernel of
`psimap/render/csrc_cuda/blend_fwd.cu` (one thread block per tile, one thread per pixel).

The kernel is compiled on first use with torch's extension builder (needs the CUDA toolkit's nvcc
and ninja beside a CUDA build of torch; the build is cached under torch's extensions folder). It has
no backward: renders that need gradients stay on the torch reference (`psimap.render.rasterize`
dispatches), and so does anything it does not cover (float64, more channels or a larger topk than
it holds in registers: `supported`). PSIMAP_CUDA_VERBOSE=1 shows the compiler's output.
"""
from __future__ import annotations

import os
import sys
import threading
from pathlib import Path

import torch

from psimap.render.binning import bin_surfels
from psimap.render.output import RenderOutput
from psimap.render.project import Projected

SOURCES = Path(__file__).resolve().parent / "csrc_cuda"
EXTENSION_NAME = "psimap_render_cuda"
# Development hook (the CUDA kernel's mutation runs): build from another copy of csrc_cuda, under
# its own extension name so that builds of several copies do not replace each other.
SOURCES_ENV = "PSIMAP_CUDA_SOURCES"
# Mirrors csrc_cuda/blend.h (kMaxChannelsAll, kMaxTopK), checked again by the bindings.
MAX_CHANNELS_ALL = 64
MAX_TOPK = 32

_lock = threading.Lock()
_extension = None
_load_error: str | None = None


def load_extension():
    """The compiled module (built once per process, the first time; cached on disk by torch).
    Raises RuntimeError with the reason when it cannot be built or there is no CUDA device."""
    global _extension, _load_error
    with _lock:
        if _extension is not None:
            return _extension
        if _load_error is not None:
            raise RuntimeError(_load_error)
        try:
            if not torch.cuda.is_available():
                raise RuntimeError("no CUDA device (torch.cuda.is_available() is False)")
            from torch.utils.cpp_extension import load

            sources, name = SOURCES, EXTENSION_NAME
            if os.environ.get(SOURCES_ENV):
                sources = Path(os.environ[SOURCES_ENV]).resolve()
                name = f"{EXTENSION_NAME}_{sources.name}"
            _say_if_building(name)
            _extension = load(name=name, sources=[str(sources / "bindings.cpp"), str(sources / "blend_fwd.cu")],
                              extra_cflags=["-O3"], extra_cuda_cflags=["-O3", "-lineinfo"],
                              verbose=os.environ.get("PSIMAP_CUDA_VERBOSE", "") not in ("", "0"))
        except Exception as exc:   # no toolkit, no compiler, no device: the caller falls back
            _load_error = f"the CUDA renderer could not be built: {type(exc).__name__}: {exc}".splitlines()[0]
            raise RuntimeError(_load_error) from exc
        return _extension


def _say_if_building(name: str) -> None:
    """One line on stderr when the module is not in torch's build cache yet: the compile takes
    ~25-60 s, and a render that waits that long without a word looks hung."""
    try:
        from torch.utils.cpp_extension import _get_build_directory   # private: may move

        folder = Path(_get_build_directory(name, verbose=False))
        built = any(folder.glob(f"{name}*.so")) or any(folder.glob(f"{name}*.pyd"))
    except Exception:
        return
    if not built:
        print(f"psimap: compiling the CUDA renderer once (~30 s; cached in {folder})", file=sys.stderr, flush=True)


def available() -> bool:
    """Whether the CUDA blend kernel can run here (a device, and the extension builds)."""
    try:
        load_extension()
    except RuntimeError:
        return False
    return True


def supported(dtype: torch.dtype, channels: int, topk: int | None) -> bool:
    """Whether the kernel covers these inputs (float32; C channels in registers when blending all,
    topk <= MAX_TOPK)."""
    if dtype != torch.float32:
        return False
    if channels == 0:
        return True
    return topk <= MAX_TOPK if topk is not None else channels <= MAX_CHANNELS_ALL


def rasterize_cuda(proj: Projected, opacities: torch.Tensor, colors: torch.Tensor,
                   features: torch.Tensor | None, width: int, height: int,
                   topk: int | None = None, tiles: str = "precise", near: float = 0.2,
                   far: float = 1000.0, background: torch.Tensor | None = None) -> RenderOutput:
    """Stages 2-3 of SPEC.md on the CUDA device of `colors`, without gradients.

    proj: stage-1 output for N surfels; opacities [N], colors [N, 3], features [N, C] or None,
    background [3] or None. Returns a RenderOutput (stats["backend"] = "cuda")."""
    n = colors.shape[0]
    if features is None:
        features = colors.new_zeros(n, 0)
    C = int(features.shape[1])
    if colors.device.type != "cuda":
        raise ValueError(f"rasterize_cuda: the tensors are on {colors.device}, not a CUDA device")
    if not supported(colors.dtype, C, topk):
        raise ValueError(f"rasterize_cuda: {colors.dtype} with C = {C}, topk = {topk} is beyond the CUDA "
                         f"kernel (float32; C <= {MAX_CHANNELS_ALL} blending all, topk <= {MAX_TOPK})")
    ext = load_extension()
    box = proj.box_precise if tiles == "precise" else proj.box_circle
    with torch.no_grad():
        bins = bin_surfels(box, proj.depth_key, width, height)
        f32 = [t.detach().float().contiguous() for t in (proj.T, proj.center, proj.depth_key, proj.normal_c,
                                                         opacities, colors, features)]
        bg = [0.0, 0.0, 0.0] if background is None else [float(v) for v in background.detach().cpu()]
        box32 = box.to(torch.int32).contiguous()
        rgb, alpha, depth, median, normal, distortion, feats, evaluated = ext.blend_forward(
            bins.offsets.to(torch.int32), bins.surfel_ids.to(torch.int32), box32, bins.tiles_x, bins.tiles_y,
            width, height, *f32, 0 if topk is None else int(topk), float(near), float(far), bg)
        # A non-empty box (clipped to the image) touches at least one tile: the rest are culled.
        binned = ((box32[:, 2] > box32[:, 0]) & (box32[:, 3] > box32[:, 1])).sum()
        longest = bins.counts.max() if bins.counts.numel() else binned.new_zeros(())
        longest, binned, evaluated = torch.stack([longest, binned, evaluated[0]]).tolist()   # one host sync
    n_tiles = bins.tiles_x * bins.tiles_y
    n_pairs = int(bins.surfel_ids.numel())
    stats = {
        "tile_pairs": n_pairs,
        "pairs_per_tile": n_pairs / max(n_tiles, 1),
        "max_pairs_per_tile": longest,
        "evaluated": evaluated,
        "culled": n - binned,
        "backend": "cuda",
        "tiles": tiles,
    }
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, median_depth=median, normal=normal,
                        distortion=distortion, features=feats, stats=stats)
