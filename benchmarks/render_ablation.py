"""The paper's Table "ablation_speed" on this CPU, with the native renderer, plus native vs reference.

Synthetic surfel room (benchmarks/render.py's generator) at 640x480, C = 32 feature channels.
Rows: Baseline (circle tiles, full blending) / + Precise tile / + Top-K / Full (precise + Top-K):
time per frame (forward, and forward+backward), FPS, RN-Total (tile-surfel pairs), RN/Tile, and the
feature error against full blending. Then native vs the torch reference on the Full configuration,
forward and forward+backward, in the same run, and the per-stage split of a native frame (the
profile that says what bounds it). Appends to benchmarks/RESULTS.md.

    python benchmarks/render_ablation.py              # 60k surfels, 640x480, C = 32, K = 8
    python benchmarks/render_ablation.py --quick      # small smoke run
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import append_results, markdown_table  # noqa: E402
from render import intrinsics, look_at_viewmat, room_surfels  # noqa: E402

from psimap.render import project_surfels, rasterize  # noqa: E402


def timed(fn, repeats: int, cpu: list | None = None):
    """Median wall time (s) of `repeats` calls after one warm-up; returns (seconds, last result).
    The median process CPU time (all threads) is appended to `cpu` when given: the machine is
    shared, and CPU time shows how much of the wall time was waiting for a core."""
    out = fn()
    times, cpus = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        times.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    if cpu is not None:
        cpu.append(float(np.median(cpus)))
    return float(np.median(times)), out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--surfels", type=int, default=60000)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--channels", type=int, default=32)
    ap.add_argument("--topk", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="small smoke run")
    args = ap.parse_args(argv)
    if args.quick:
        args.surfels, args.width, args.height, args.repeats = 5000, 160, 120, 2
    from psimap.render import native

    W, H, C = args.width, args.height, args.channels
    src = room_surfels(args.surfels, C, seed=0)
    viewmat = look_at_viewmat([-2.2, -2.0, 1.6], [1.0, 1.8, 0.8])
    K = intrinsics(W, H)
    threads = native.get_num_threads()

    def render(tiles, topk, backend="native", leaves=src):
        return rasterize(*leaves[:5], viewmat, K, W, H, features=leaves[5], topk=topk, tiles=tiles,
                         backend=backend)

    def fwd_bwd(tiles, topk, backend="native"):
        leaves = [t.clone().requires_grad_(True) for t in src]
        out = render(tiles, topk, backend, leaves)
        loss = out.rgb.sum() + out.depth.sum() + out.features.sum() + out.distortion.sum()
        loss.backward()
        return out

    with torch.no_grad():
        full_blend = render("precise", None).features
    rows_cfg = [("Baseline (circle, full blending)", "circle", None),
                ("+ Precise tile", "precise", None),
                (f"+ Top-K (K={args.topk})", "circle", args.topk),
                ("Full (precise + Top-K)", "precise", args.topk)]
    from psimap.render.native import rasterize_native

    with torch.no_grad():
        proj = project_surfels(*src[:4], viewmat, K, W, H)
    rows, raster_ms = [], {}
    for name, tiles, topk in rows_cfg:
        cpu = []
        with torch.no_grad():
            # Stages 2-3 (binning + blending), what the rows differ in; projection is common.
            t_r, out = timed(lambda: rasterize_native(proj, src[3], src[4], src[5], W, H, topk, tiles),
                             args.repeats, cpu)
            t_f, _ = timed(lambda: render(tiles, topk), args.repeats)
        t_fb, _ = timed(lambda: fwd_bwd(tiles, topk), max(1, args.repeats // 2))
        err = float((out.features - full_blend).abs().mean() / full_blend.abs().mean())
        raster_ms[name] = 1e3 * t_r
        rows.append([name, 1e3 * t_r, 1e3 * cpu[0], 1e3 * t_f, 1.0 / t_f, 1e3 * t_fb,
                     out.stats["tile_pairs"], out.stats["pairs_per_tile"], err])
    header = ["config", "raster ms (wall)", "raster ms (CPU)", "frame ms", "FPS", "fwd+bwd ms",
              "RN-Total", "RN/Tile", "feature rel. err vs full blending"]
    table = markdown_table(header, rows)

    # Native vs reference on the Full configuration, same scene, same run.
    with torch.no_grad():
        t_nf, _ = timed(lambda: render("precise", args.topk), args.repeats)
        t_rf, _ = timed(lambda: render("precise", args.topk, "reference"), 1)
    t_nfb, _ = timed(lambda: fwd_bwd("precise", args.topk), max(1, args.repeats // 2))
    t_rfb, _ = timed(lambda: fwd_bwd("precise", args.topk, "reference"), 1)
    cmp_rows = [["forward", 1e3 * t_rf, 1e3 * t_nf, t_rf / t_nf],
                ["forward+backward", 1e3 * t_rfb, 1e3 * t_nfb, t_rfb / t_nfb]]
    cmp_table = markdown_table(["pass (Full config)", "reference ms", "native ms", "speed-up"], cmp_rows)

    # Profile of one native Full frame by stage (projection in torch, binning, blending in C++).
    from psimap.render import _native

    with torch.no_grad():
        t_proj, proj = timed(lambda: project_surfels(*src[:4], viewmat, K, W, H), args.repeats)
        box = proj.box_precise.numpy().astype(np.int32)
        binned = (proj.valid.numpy() & (box[:, 2] > box[:, 0]) & (box[:, 3] > box[:, 1])).astype(np.uint8)
        key = proj.depth_key.numpy().astype(np.float32)
        t_bin, _ = timed(lambda: _native.bin_tiles(box, binned, key, W, H), args.repeats)
    t_raster = t_nf - t_proj - t_bin

    pairs = {r[0]: r[6] for r in rows}
    base, prec = rows_cfg[0][0], rows_cfg[1][0]
    fewer = 1 - pairs[prec] / pairs[base]
    full_speedup = raster_ms[base] / raster_ms[rows_cfg[3][0]]
    ratios = (f"Targets: native >= 10x reference fwd+bwd: **{t_rfb / t_nfb:.1f}x**; Full >= 2x Baseline "
              f"(feature rendering, stages 2-3 forward): **{full_speedup:.2f}x**; precise tiles >= 35% fewer pairs: "
              f"**{100 * fewer:.1f}%** fewer.")
    load = os.getloadavg()[0]
    notes = (f"Load average {load:.1f} on {os.cpu_count()} cores while measuring (shared machine). "
             f"raster = stages 2-3 (native binning + blending); frame = projection + raster. "
             f"{args.surfels} surfels (synthetic room), {W}x{H}, C = {C}, K = {args.topk}, "
             f"{threads} OpenMP threads, torch {torch.__version__} with {torch.get_num_threads()} threads; "
             f"median of {args.repeats} runs (reference: 1 run).\n\n{cmp_table}\n\n{ratios}\n\n"
             f"Profile of a native Full forward frame ({1e3 * t_nf:.1f} ms): projection (torch) "
             f"{1e3 * t_proj:.1f} ms, binning + depth sort (C++) {1e3 * t_bin:.1f} ms, blending + "
             f"Python glue {1e3 * t_raster:.1f} ms.")
    title = "Renderer ablation (paper Table ablation_speed), native CPU kernels"
    if args.quick:       # smoke run: print, do not record
        print(f"## {title}\n\n{table}\n\n{notes}")
    else:
        append_results(title, table, notes, command="python benchmarks/render_ablation.py")
    return 0


if __name__ == "__main__":
    sys.exit(main())
