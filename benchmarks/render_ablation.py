"""The paper's Table "ablation_speed" on this CPU, with the native renderer, plus native vs reference.

Synthetic surfel room (benchmarks/render.py's generator) at 640x480, C = 32 feature channels.
Rows: Baseline (circle tiles, full blending) / + Precise tile / + Top-K / Full (precise + Top-K):
time per frame (forward, and forward+backward), FPS, RN-Total (tile-surfel pairs), RN/Tile, and the
feature error against full blending. Then native vs the torch reference on the Full configuration,
forward and forward+backward, in the same run, and the per-stage split of a native frame (the
profile that says what bounds it, fwd + bwd). Writes its section of benchmarks/RESULTS.md and its plot
(benchmarks/plots/render_ablation.png); a --quick smoke run only prints.

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
from _results import markdown_table, save_plot, write_section  # noqa: E402
from render import intrinsics, look_at_viewmat, room_surfels  # noqa: E402

from psimap.render import project_surfels, rasterize  # noqa: E402


def timed(fn, repeats: int):
    """Median wall and process-CPU time (s, all threads) of `repeats` calls after one warm-up;
    returns (wall, cpu, last result). The machine is shared: CPU time is what the work costs,
    wall time also counts waiting for a core."""
    out = fn()
    walls, cpus = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return float(np.median(walls)), float(np.median(cpus)), out


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
    rows, raster_cpu = [], {}
    for name, tiles, topk in rows_cfg:
        with torch.no_grad():
            # Stages 2-3 (binning + blending), what the rows differ in; projection is common.
            w_r, c_r, out = timed(lambda: rasterize_native(proj, src[3], src[4], src[5], W, H, topk, tiles),
                                  args.repeats)
        w_fb, c_fb, _ = timed(lambda: fwd_bwd(tiles, topk), max(1, args.repeats // 2))
        err = float((out.features - full_blend).abs().mean() / full_blend.abs().mean())
        raster_cpu[name] = c_r
        rows.append([name, 1e3 * w_r, 1e3 * c_r, threads / c_r, 1e3 * w_fb, 1e3 * c_fb,
                     out.stats["tile_pairs"], out.stats["pairs_per_tile"], out.stats["evaluated"], err])
    header = ["config", "raster ms (wall)", "raster ms (CPU)", "FPS (CPU-bound)", "frame fwd+bwd ms (wall)",
              "frame fwd+bwd ms (CPU)", "RN-Total", "RN/Tile", "pixel evals", "feature rel. err vs full"]
    table = markdown_table(header, rows)

    # Native vs reference on the Full configuration (whole frame incl. projection), same run.
    with torch.no_grad():
        nf = timed(lambda: render("precise", args.topk), args.repeats)
        rf = timed(lambda: render("precise", args.topk, "reference"), 1)
    nfb = timed(lambda: fwd_bwd("precise", args.topk), max(1, args.repeats // 2))
    rfb = timed(lambda: fwd_bwd("precise", args.topk, "reference"), 1)
    cmp_rows = [["forward", 1e3 * rf[0], 1e3 * nf[0], rf[0] / nf[0], 1e3 * rf[1], 1e3 * nf[1], rf[1] / nf[1]],
                ["forward+backward", 1e3 * rfb[0], 1e3 * nfb[0], rfb[0] / nfb[0], 1e3 * rfb[1], 1e3 * nfb[1],
                 rfb[1] / nfb[1]]]
    cmp_table = markdown_table(["pass (Full config)", "reference ms (wall)", "native ms (wall)", "speed-up (wall)",
                                "reference ms (CPU)", "native ms (CPU)", "speed-up (CPU)"], cmp_rows)

    # Profile of one native Full frame (forward + backward) by stage: torch.profiler's self time of
    # each autograd node (elapsed time on the CPU, so inflated on a loaded machine like the wall
    # columns); "other" = the torch glue between them: losses, clones, copies.
    from torch.profiler import ProfilerActivity, profile

    from psimap.render.project import project_surfels as project_torch

    with torch.no_grad():
        _, c_proj_torch, _ = timed(lambda: project_torch(*src[:4], viewmat, K, W, H), args.repeats)
    stage_names = {"_ProjectNative": "projection (C++)", "_RasterizeNative": "binning + blending (C++)",
                   "_RasterizeNativeBackward": "blending backward (C++)",
                   "_ProjectNativeBackward": "projection backward (C++)"}
    stages = {v: 0.0 for v in stage_names.values()}
    fwd_bwd("precise", args.topk)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(args.repeats):
            fwd_bwd("precise", args.topk)
    total = 0.0
    for ev in prof.key_averages():
        total += ev.self_cpu_time_total
        if ev.key in stage_names:
            stages[stage_names[ev.key]] += ev.self_cpu_time_total
    stages = {k: v / 1e3 / args.repeats for k, v in stages.items()}             # ms per frame
    stages["other (torch glue, loss)"] = total / 1e3 / args.repeats - sum(stages.values())
    c_full = raster_cpu[rows_cfg[3][0]]

    pairs = {r[0]: r[6] for r in rows}
    base, prec = rows_cfg[0][0], rows_cfg[1][0]
    fewer = 1 - pairs[prec] / pairs[base]
    full_speedup = raster_cpu[base] / c_full
    frame_cpu = {r[0]: r[5] for r in rows}
    frame_speedup = frame_cpu[base] / frame_cpu[rows_cfg[3][0]]
    ratios = (f"Targets: native >= 10x reference fwd+bwd: **{rfb[1] / nfb[1]:.1f}x** (CPU time; "
              f"{rfb[0] / nfb[0]:.1f}x wall); Full >= 2x Baseline (feature rendering, stages 2-3, CPU time): "
              f"**{full_speedup:.2f}x** (whole frame forward + backward: {frame_speedup:.2f}x); "
              f"precise tiles >= 35% fewer pairs: **{100 * fewer:.1f}%** fewer.")
    load = os.getloadavg()[0]
    profile_line = ", ".join(f"{k} {v:.1f} ms" for k, v in stages.items())
    notes = (f"Load average {load:.1f} on {os.cpu_count()} cores while measuring (shared machine, so "
             f"wall times are inflated; CPU time = all threads' process time). raster = stages 2-3 "
             f"(native binning + blending, projection excluded); FPS (CPU-bound) = threads / raster CPU s. "
             f"{args.surfels} surfels (synthetic room), {W}x{H}, C = {C}, K = {args.topk}, "
             f"{threads} OpenMP threads, {native.pixel_kernels()} pixel kernels, torch {torch.__version__} with "
             f"{torch.get_num_threads()} threads; "
             f"median of {args.repeats} runs (reference: 1 run).\n\n{cmp_table}\n\n{ratios}\n\n"
             f"Profile (ms per frame, torch.profiler self time: elapsed, not CPU) of a native Full frame, "
             f"forward + backward: {profile_line}. "
             f"The torch projection (psimap/render/project.py, the reference) takes {1e3 * c_proj_torch:.1f} ms "
             f"forward alone on the same surfels.")
    title = "Renderer ablation (paper Table ablation_speed), native CPU kernels"
    if args.quick:       # smoke run: print, do not record
        print(f"## {title}\n\n{table}\n\n{notes}")
        return 0
    write_section("render_ablation", title, f"{table}\n\n{notes}", plot=save_plot(plot(rows), "render_ablation"),
                  headlines=[("native vs torch reference, fwd+bwd, Full config (target >= 10x)",
                              f"{rfb[1] / nfb[1]:.1f}x CPU ({rfb[0] / nfb[0]:.1f}x wall)"),
                             ("Full vs Baseline, stages 2-3 forward, CPU (target >= 2x)",
                              f"{full_speedup:.2f}x (frame fwd+bwd {frame_speedup:.2f}x)"),
                             ("precise tiles (target >= 35 % fewer pairs)", f"{100 * fewer:.1f} % fewer")])
    return 0


def plot(rows):
    """Raster CPU time beside the feature error it costs, one bar pair per configuration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.6))
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r[2] for r in rows], 0.4, color="C0", label="raster CPU ms")
    ax.set_ylabel("raster CPU ms (stages 2-3)", color="C0")
    ax2 = ax.twinx()
    ax2.bar(x + 0.2, [100 * r[9] for r in rows], 0.4, color="C1", label="feature error %")
    ax2.set_ylabel("feature rel. error vs full (%)", color="C1")
    ax.set_xticks(x, [r[0].replace(" (", "\n(") for r in rows], fontsize=8)
    ax.set_title("Renderer ablation: speed vs error")
    fig.tight_layout()
    return fig


if __name__ == "__main__":
    sys.exit(main())
