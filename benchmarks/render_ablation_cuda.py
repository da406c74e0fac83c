"""The paper's Table "ablation_speed" with the CUDA forward kernel (psimap/render/csrc_cuda).

Same scene and rows as benchmarks/render_ablation.py (synthetic surfel room, 640x480, C = 32,
K = 8; Baseline = circle tiles + full blending, Full = precise tiles + Top-K), timed with CUDA
events, median of many calls after warm-up, in three scopes: the blend kernel alone (stage 3,
bins made beforehand), stages 2-3 (torch binning + the kernel + the stats) and the whole frame
(`rasterize(backend="cuda")`: the torch projection too). Beside each row: the feature error
against full blending, and the kernel's largest deviation from the float32 torch reference on
the same device (must be float rounding). A second, larger scene shows where tile work
dominates. Without a CUDA device it prints a line and exits 0 (make bench runs every benchmark).

    python benchmarks/render_ablation_cuda.py            # 60k and 600k surfels, 640x480
    python benchmarks/render_ablation_cuda.py --quick    # small smoke run, prints only
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import markdown_table, save_plot, write_section  # noqa: E402
from render import intrinsics, look_at_viewmat, room_surfels  # noqa: E402

from psimap.render import project_surfels, rasterize  # noqa: E402


def cuda_ms(fn, repeats: int) -> float:
    """Median milliseconds of `repeats` calls (CUDA events around each, after 3 warm-ups)."""
    for _ in range(3):
        fn()
    torch.cuda.synchronize()
    times = []
    for _ in range(repeats):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record()
        fn()
        b.record()
        b.synchronize()
        times.append(a.elapsed_time(b))
    return float(np.median(times))


def ablation(n_surfels: int, W: int, H: int, C: int, topk: int, repeats: int, with_reference: bool):
    """Rows of the four configurations on one scene."""
    from psimap.render import cuda
    from psimap.render.binning import bin_surfels
    from psimap.render.reference import rasterize_reference

    ext = cuda.load_extension()
    src = [t.cuda() for t in room_surfels(n_surfels, C, seed=0)]
    viewmat = look_at_viewmat([-2.2, -2.0, 1.6], [1.0, 1.8, 0.8]).cuda()
    K = intrinsics(W, H).cuda()
    means, quats, scales, opac, colors, feats = src
    with torch.no_grad():
        proj = project_surfels(means, quats, scales, opac, viewmat, K, W, H)
        full_blend = cuda.rasterize_cuda(proj, opac, colors, feats, W, H, None, "precise").features
    configs = [("Baseline (circle, full blending)", "circle", None),
               ("+ Precise tile", "precise", None),
               (f"+ Top-K (K={topk})", "circle", topk),
               ("Full (precise + Top-K)", "precise", topk),
               # The floor under every row: the same walk without features (rgb, depth, normal, ...).
               ("circle, no features", "circle", "none"),
               ("precise, no features", "precise", "none")]
    f32 = [t.contiguous() for t in (proj.T, proj.center, proj.depth_key, proj.normal_c, opac, colors, feats)]
    rows = []
    no_feats = feats[:, :0].contiguous()
    for name, tiles, k in configs:
        f = no_feats if k == "none" else feats
        k = None if k == "none" else k
        f32[-1] = f
        with torch.no_grad():
            box = proj.box_precise if tiles == "precise" else proj.box_circle
            bins = bin_surfels(box, proj.depth_key, W, H)
            offsets, ids = bins.offsets.to(torch.int32), bins.surfel_ids.to(torch.int32)
            box32 = box.to(torch.int32).contiguous()
            kernel = cuda_ms(lambda: ext.blend_forward(offsets, ids, box32, bins.tiles_x, bins.tiles_y, W, H, *f32,
                                                       k or 0, 0.2, 1000.0, [0.0, 0.0, 0.0]), repeats)
            binning = cuda_ms(lambda: bin_surfels(box, proj.depth_key, W, H), repeats)
            stages = cuda_ms(lambda: cuda.rasterize_cuda(proj, opac, colors, f, W, H, k, tiles), repeats)
            frame = cuda_ms(lambda: rasterize(means, quats, scales, opac, colors, viewmat, K, W, H, features=f,
                                              topk=k, tiles=tiles, backend="cuda"), repeats)
            out = cuda.rasterize_cuda(proj, opac, colors, f, W, H, k, tiles)
            err = (float((out.features - full_blend).abs().mean() / full_blend.abs().mean()) if f.shape[1]
                   else float("nan"))
            ref_ms = dev = float("nan")
            if with_reference:
                ref_ms = cuda_ms(lambda: rasterize_reference(proj, opac, colors, f, W, H, topk=k, tiles=tiles), 3)
                ref = rasterize_reference(proj, opac, colors, f, W, H, topk=k, tiles=tiles)
                dev = max(float((getattr(out, o) - getattr(ref, o)).abs().max())
                          for o in ("rgb", "alpha", "depth", "normal", "features") if getattr(ref, o).numel())
        rows.append([name, kernel, binning, stages, frame, 1e3 / frame, out.stats["tile_pairs"],
                     out.stats["pairs_per_tile"], out.stats["evaluated"], err, ref_ms, dev])
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--surfels", type=int, nargs="+", default=[60000, 600000])
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--channels", type=int, default=32)
    ap.add_argument("--topk", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--quick", action="store_true", help="small smoke run")
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("render_ablation_cuda: no CUDA device here; skipped (nothing written)")
        return 0
    if args.quick:
        args.surfels, args.width, args.height, args.repeats = [5000], 160, 120, 5
    W, H, C = args.width, args.height, args.channels
    header = ["config", "kernel ms (stage 3)", "binning ms (torch)", "stages 2-3 ms", "frame ms", "FPS (frame)",
              "RN-Total", "RN/Tile", "pixel evals", "feature rel. err vs full", "torch reference ms (2-3)",
              "max |kernel - reference|"]
    tables, ratios, plot_rows, heads = [], [], {}, []
    for i, n in enumerate(args.surfels):
        rows = ablation(n, W, H, C, args.topk, args.repeats, with_reference=(i == 0))
        base, full = rows[0], rows[3]
        r = (base[1] / full[1], base[3] / full[3], base[4] / full[4])
        ratios.append(f"{n} surfels: Full / Baseline **{r[0]:.2f}x** kernel (stage 3), {r[1]:.2f}x stages 2-3, "
                      f"{r[2]:.2f}x whole frame")
        tables.append(f"**{n} surfels** (synthetic room), {W}x{H}, C = {C}, K = {args.topk}\n\n"
                      + markdown_table(header, rows))
        plot_rows[n] = rows
        heads.append((f"CUDA Full vs Baseline, {n} surfels, kernel / stages 2-3 (target >= 2x)",
                      f"{r[0]:.2f}x / {r[1]:.2f}x"))
    dev = torch.cuda.get_device_properties(0)
    notes = (f"{dev.name} ({dev.multi_processor_count} SMs), torch {torch.__version__}, CUDA events, median of "
             f"{args.repeats} calls after 3 warm-ups (torch reference: 3). kernel = `blend_forward` alone on bins "
             f"made beforehand; stages 2-3 = `rasterize_cuda` (torch binning + kernel + stats); frame = "
             f"`rasterize(backend='cuda')` with the torch projection. max |kernel - reference| = the largest "
             f"difference of rgb / alpha / depth / normal / features from the float32 torch reference on the same "
             f"device and projection.\n\n" + "\n\n".join(ratios))
    body = "\n\n".join(tables) + "\n\n" + notes
    title = "Renderer ablation on a GPU: the CUDA forward kernel"
    if args.quick:
        print(f"## {title}\n\n{body}")
        return 0
    write_section("render_ablation_cuda", title, body, plot=save_plot(plot(plot_rows), "render_ablation_cuda"),
                  headlines=heads)
    return 0


def plot(plot_rows: dict):
    """Per scene: kernel and stages 2-3 time per configuration, with the feature error beside."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(plot_rows), figsize=(6 * len(plot_rows), 3.8), squeeze=False)
    for ax, (n, rows) in zip(axes[0], plot_rows.items()):
        x = np.arange(len(rows))
        ax.bar(x - 0.27, [r[1] for r in rows], 0.27, color="C0", label="kernel (stage 3)")
        ax.bar(x, [r[3] for r in rows], 0.27, color="C2", label="stages 2-3")
        ax.set_ylabel("ms per frame")
        ax2 = ax.twinx()
        ax2.bar(x + 0.27, [100 * r[9] for r in rows], 0.27, color="C1", label="feature error %")
        ax2.set_ylabel("feature rel. error vs full (%)", color="C1")
        ax.set_xticks(x, [r[0].replace(" (", "\n(").replace(", no", "\nno") for r in rows], fontsize=7)
        ax.set_title(f"CUDA renderer ablation, {n} surfels")
        ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    return fig


if __name__ == "__main__":
    sys.exit(main())
