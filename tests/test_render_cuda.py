"""The CUDA forward renderer (psimap/render/cuda.py, psimap/render/csrc_cuda) against the torch
reference, and the dispatch around it.

Oracle and tolerances as tests/test_render_native.py's (its docstring): the reference in float64 on
float32-representable inputs, 1e-5 relative per output element, pixels within BAND of a discrete
cutoff excluded; against the float64 oracle an element may also be off by 2x the float32
reference's own error, the float32 reference run on the same CUDA device (so its stage 1 is the
very projection the kernel reads). The kernel's products may fuse into FMAs, so the geometric
cutoffs (rho3 ~ chi^2, rho2 ~ R_LP^2, z3 ~ near, edge-on) are banded too.

The tests that need a CUDA device skip without one (CI has none); the dispatch tests run anywhere.
"""
from __future__ import annotations

import pytest
import torch

from posed import random_c2w, to_world, viewmat as viewmat_of
from render_cases import (FAR, H, NEAR, OUTPUTS, W, assert_forward_close, boundary_pixels, camera, fresh_seed,
                          hard_scene, random_scene)
from psimap import PsimapError
from psimap.render import cuda, rasterize

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def poison_cuda_cache(width, height, channels):
    """Hand blocks of the outputs' sizes full of NaN back to torch's CUDA caching allocator, so the
    kernel's outputs (torch.empty) likely come out of NaN memory: a pixel left unwritten fails."""
    sizes = [3, 1, 1, 1, 3, 1, channels]
    junk = [torch.full((width * height * c,), float("nan"), device="cuda") for c in sizes if c]
    del junk


def render(scene, viewmat, K, topk, backend, dtype, device, tiles="precise", background=None, width=W,
           height=H):
    t = [x.to(device=device, dtype=dtype) for x in scene]
    bg = None if background is None else background.to(device=device, dtype=dtype)
    if backend == "cuda":
        poison_cuda_cache(width, height, t[5].shape[1])
    with torch.no_grad():
        return rasterize(*t[:5], viewmat.to(device=device, dtype=dtype), K.to(device=device, dtype=dtype),
                         width, height, features=t[5], topk=topk, tiles=tiles, backend=backend, near=NEAR,
                         far=FAR, background=bg)


def compare(scene, viewmat, K, topk, tiles="precise", background=None, msg="", oracle=torch.float64):
    """The kernel against the reference: `oracle` float64 (on the CPU, with the float32 reference on the
    CUDA device as the allowance) or float32 (the reference on the CUDA device itself: for degenerate
    surfels, whose stage-1 quantities depend on the projection's precision). Asserts the forward
    within tolerance off the band and the stats of the float32 reference (same projection, same
    bins). Returns (oracle render, kernel render, band)."""
    band = boundary_pixels(scene, viewmat, K, topk)
    ref32 = render(scene, viewmat, K, topk, "reference", torch.float32, "cuda", tiles, background)
    out = render(scene, viewmat, K, topk, "cuda", torch.float32, "cuda", tiles, background)
    assert out.stats["backend"] == "cuda"
    msg = f"{msg}, banded pixels={int(band.sum())}"
    if oracle == torch.float64:
        ref = render(scene, viewmat, K, topk, "reference", torch.float64, "cpu", tiles, background)
        assert_forward_close(ref, _to_cpu(out), ~band, msg, _to_cpu(ref32))
    else:
        ref = _to_cpu(ref32)
        assert_forward_close(ref, _to_cpu(out), ~band, msg)
    for k in ("tile_pairs", "pairs_per_tile", "max_pairs_per_tile", "culled"):
        assert out.stats[k] == ref32.stats[k], (k, msg)
    # The kernel counts the evaluations it performs (pixels stop early, warps skip surfels whose box
    # misses their 8x4 block), the reference every (pixel, pair).
    assert out.stats["evaluated"] <= ref32.stats["evaluated"], msg
    return ref, out, band


def _to_cpu(out):
    return type(out)(**{k: getattr(out, k).cpu() for k in OUTPUTS}, stats=out.stats)


# ---------------------------------------------------------------- anywhere

def test_supported_covers_float32_within_the_kernels_registers():
    assert cuda.supported(torch.float32, 32, None) and cuda.supported(torch.float32, 64, None)
    assert not cuda.supported(torch.float32, 65, None)            # blending all: C in registers
    assert cuda.supported(torch.float32, 500, 8) and cuda.supported(torch.float32, 500, 32)
    assert not cuda.supported(torch.float32, 5, 33)
    assert cuda.supported(torch.float32, 0, 100)                  # no features: no list kept
    assert not cuda.supported(torch.float64, 3, None)


def test_cuda_backend_refuses_cpu_tensors():
    viewmat, K = camera()
    scene = [t.float() for t in random_scene(10, 1)]
    with pytest.raises(ValueError, match="CUDA device"):
        rasterize(*scene[:5], viewmat.float(), K.float(), W, H, features=scene[5], backend="cuda")


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is present")
def test_without_a_device_auto_stays_on_the_cpu_and_the_reason_is_kept():
    assert not cuda.available()
    with pytest.raises(RuntimeError, match="no CUDA device"):
        cuda.load_extension()
    viewmat, K = camera()
    scene = [t.float() for t in random_scene(10, 1)]
    with torch.no_grad():
        out = rasterize(*scene[:5], viewmat.float(), K.float(), W, H, features=scene[5], backend="auto")
    assert out.stats["backend"] in ("native", "reference")


# ---------------------------------------------------------------- on a CUDA device

@needs_cuda
@pytest.mark.parametrize("topk,tiles,channels", [(None, "precise", 6), (3, "precise", 6), (2, "circle", 6),
                                                 (None, "circle", 40), (8, "precise", 32), (None, "precise", 0),
                                                 (20, "precise", 70)])
def test_cuda_matches_reference_on_random_scene(topk, tiles, channels):
    seed = fresh_seed()
    _, K = camera()
    scene = random_scene(150, seed, channels=channels)
    c2w = random_c2w(seed)
    scene[0], scene[1] = (t.float().double() for t in to_world(c2w, scene[0], scene[1]))
    viewmat = viewmat_of(c2w).float().double()
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    ref, out, band = compare(scene, viewmat, K, topk, tiles, bg, f"seed={seed}, topk={topk}, tiles={tiles}, "
                                                                f"C={channels}")
    assert int(band.sum()) < 0.05 * H * W
    assert float(ref.alpha.max()) > 0.999                           # the 1e-4 stop is exercised
    assert 0 < out.stats["evaluated"]


@needs_cuda
@pytest.mark.parametrize("name", ["edge_on", "tiny_scale", "huge_scale", "opacity_0_and_1", "coincident",
                                  "near_plane", "all_culled", "empty"])
def test_cuda_hard_cases_match_reference(name):
    viewmat, K = camera()
    ref, out, band = compare(hard_scene(name), viewmat, K, 2, msg=f"case={name}", oracle=torch.float32)
    if name in ("huge_scale", "opacity_0_and_1", "coincident"):
        # The others' visible pixels all sit in the band (edge-on, 1e-8 scales, surfels on the near
        # plane) or there are none (all culled, empty).
        assert float(ref.alpha[~band].max()) > 0.3, name               # the comparison covers visible pixels
    for k in OUTPUTS:
        assert bool(torch.isfinite(getattr(out, k)).all()), (name, k)


@needs_cuda
def test_long_tile_lists_run_in_batches_and_pixels_stop_early():
    """More than two shared-memory batches per tile (256 surfels each), opaque enough that most
    pixels stop before the end of their list: the block's early exit and the batch reloads."""
    viewmat, K = camera()
    seed = fresh_seed()
    scene = random_scene(1500, seed, size=(0.3, 0.4), opac=(0.3, 0.9))
    ref, out, _ = compare(scene, viewmat, K, 4, msg=f"seed={seed}")
    assert out.stats["max_pairs_per_tile"] > 600
    assert out.stats["evaluated"] < 0.5 * ref.stats["evaluated"]
    assert float(ref.alpha.min()) > 0.99                             # every pixel is covered, most stop early


@needs_cuda
def test_partial_edge_tiles_are_a_crop_of_a_larger_render():
    """An image whose sides are not multiples of 16 (threads outside it write nothing) renders the
    crop of the same camera's larger image."""
    viewmat, K = camera()
    scene = random_scene(150, fresh_seed())
    full = render(scene, viewmat, K, 3, "cuda", torch.float32, "cuda")
    crop = render(scene, viewmat, K, 3, "cuda", torch.float32, "cuda", width=W - 11, height=H - 5)
    for k in OUTPUTS:
        a, b = getattr(full, k)[: H - 5, : W - 11], getattr(crop, k)
        # Another tile grid bins the same surfels; the per-pixel walk is the same, so equal.
        assert torch.equal(a, b), k


@needs_cuda
def test_auto_picks_the_kernel_only_without_gradients():
    viewmat, K = camera()
    scene = [t.float().cuda() for t in random_scene(40, 2)]
    vm, Kc = viewmat.float().cuda(), K.float().cuda()
    with torch.no_grad():
        assert rasterize(*scene[:5], vm, Kc, W, H, features=scene[5], backend="auto").stats["backend"] == "cuda"
        wide = torch.randn(40, 70, device="cuda")
        assert rasterize(*scene[:5], vm, Kc, W, H, features=wide, backend="auto").stats["backend"] == "reference"
        with pytest.raises(ValueError, match="C <= 64"):
            rasterize(*scene[:5], vm, Kc, W, H, features=wide, backend="cuda")
        s64 = [t.double() for t in scene]
        assert rasterize(*s64[:5], vm.double(), Kc.double(), W, H, backend="auto").stats["backend"] == "reference"
    leaves = [t.clone().requires_grad_(True) for t in scene]
    out = rasterize(*leaves[:5], vm, Kc, W, H, features=leaves[5], backend="auto")
    assert out.stats["backend"] == "reference"
    out.features.sum().backward()
    assert float(leaves[0].grad.abs().max()) > 0
    with pytest.raises(ValueError, match="without gradients"):
        rasterize(*leaves[:5], vm, Kc, W, H, features=leaves[5], backend="cuda")


@needs_cuda
def test_a_build_failure_is_one_clear_error(monkeypatch):
    monkeypatch.setattr(cuda, "_extension", None)
    monkeypatch.setattr(cuda, "_load_error", "the CUDA renderer could not be built: OSError: no nvcc")
    viewmat, K = camera()
    scene = [t.float().cuda() for t in random_scene(10, 1)]
    with torch.no_grad():
        with pytest.raises(PsimapError, match="could not be built.*backend='reference'"):
            rasterize(*scene[:5], viewmat.float().cuda(), K.float().cuda(), W, H, backend="cuda")
        out = rasterize(*scene[:5], viewmat.float().cuda(), K.float().cuda(), W, H, backend="auto")
    assert out.stats["backend"] == "reference"


def _scene_of(scene):
    """A psimap Scene holding random_scene's surfels (features as its semantic channels)."""
    from psimap.scene import Scene

    m, q, s, o, c, f = [t.float() for t in scene]
    return Scene({"means": m, "quats": q, "scales": s, "opacities": o, "colors": c, "semantic": f})


def test_scene_render_on_the_cpu_device_is_the_default_render():
    viewmat, K = camera()
    sc = _scene_of(random_scene(60, 4))
    c2w = torch.linalg.inv(viewmat).numpy()
    a = sc.render(K.numpy(), c2w, W, H, features="semantic")
    b = sc.render(K.numpy(), c2w, W, H, features="semantic", device="cpu")
    assert float(a.alpha.max()) > 0.5
    for k in OUTPUTS:
        assert torch.equal(getattr(a, k), getattr(b, k)), k


@needs_cuda
def test_scene_render_on_a_cuda_device_uses_the_kernel():
    viewmat, K = camera()
    sc = _scene_of(random_scene(60, 4))
    c2w = torch.linalg.inv(viewmat).numpy()
    cpu = sc.render(K.numpy(), c2w, W, H, features="semantic", topk=4, backend="reference")
    gpu = sc.render(K.numpy(), c2w, W, H, features="semantic", topk=4, device="cuda")
    assert gpu.stats["backend"] == "cuda" and gpu.alpha.device.type == "cuda"
    assert sc.surfels["means"].device.type == "cpu"                  # the scene itself stays put
    for k in OUTPUTS:
        a, b = getattr(cpu, k), getattr(gpu, k).cpu()
        # Off the decision bands the two agree to float rounding; allow a few banded pixels.
        close = (a - b).abs() <= 1e-4 * (1 + a.abs())
        assert float(close.float().mean()) > 0.98, k


def test_a_first_build_says_so_on_stderr(tmp_path, monkeypatch, capsys):
    """The one-line notice before a compile (torch's build folder has no module yet), and none when
    the module is there."""
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path))
    cuda._say_if_building("psimap_render_cuda_probe")
    assert "compiling the CUDA renderer once" in capsys.readouterr().err
    (tmp_path / "psimap_render_cuda_probe" / "psimap_render_cuda_probe.so").write_bytes(b"")
    cuda._say_if_building("psimap_render_cuda_probe")
    assert capsys.readouterr().err == ""
