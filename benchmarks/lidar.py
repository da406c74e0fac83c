"""LiDAR ablation (issue 18): RGB-D only vs RGB-D + LiDAR vs LiDAR + RGB only (no depth images), on
generated scenes with a simulated spinning LiDAR (16 rings from -25 to +15 degrees, 0.5 degree azimuth
step, 1 cm range noise, a sweep every 10 frames from the camera), plus the shared real KITTI sweep
through the prior's input path. Geometry F1@5cm / Chamfer of the trained map's mesh against the exact
ground truth, beside training time, in one run, with the default depth sensor and with one 3x as
noisy (where a depth camera is poor, LiDAR should matter more; the colour + LiDAR run does not depend
on the depth sensor and runs once). Section `lidar` of benchmarks/RESULTS.md.

    python benchmarks/lidar.py                    # 160x120, 60 frames, seeds 0 and 1
    python benchmarks/lidar.py --quick            # one seed, 30 frames, fewer steps; prints only
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import markdown_table, save_plot, write_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench_out" / "lidar"
KITTI = ROOT.parent / "shared" / "data" / "kitti-velodyne" / "000000.bin"
MODES = ("RGB-D", "RGB-D + LiDAR", "RGB + LiDAR (no depth images)")
COLS = ("F1@5cm", "Chamfer-L1 (cm)", "accuracy (cm)", "completeness (cm)", "train (s)", "surfels",
        "range error (cm)")


def without_depth(seq):
    """The same capture with every depth image removed (0 = invalid): LiDAR + colour only."""
    def load(i):
        f = seq[i]
        return dataclasses.replace(f, depth=np.zeros_like(f.depth))

    return dataclasses.replace(seq, loader=load)


def run_mode(mode: str, data: Path, iters: int, seed: int, sensor: str) -> dict:
    from psimap.data import load
    from psimap.metrics.evaluate import evaluate_geometry
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import train

    seq = load(data)
    if mode == MODES[2]:
        seq = without_depth(seq)
    cfg = TrainConfig(iters=iters, seed=seed, panoptic=False, lidar=mode != MODES[0])
    t = time.perf_counter()
    scene = train(seq, cfg, log=lambda s: print("   ", s, flush=True))
    t_train = time.perf_counter() - t
    mesh = scene.mesh()
    m = evaluate_geometry(mesh, data, samples=100_000) if len(mesh.faces) else None
    rng = scene.metrics.get("range_l1_end")
    return {"sensor": sensor, "mode": mode, "seed": seed, "F1@5cm": None if m is None else m["f1"],
            "Chamfer-L1 (cm)": None if m is None else m["chamfer_l1"] * 100,
            "accuracy (cm)": None if m is None else m["accuracy"] * 100,
            "completeness (cm)": None if m is None else m["completeness"] * 100,
            "train (s)": t_train, "surfels": len(scene), "range error (cm)": None if rng is None else rng * 100}


def kitti_row() -> list | None:
    """The real KITTI sweep through the prior's input path: noise estimate, views, SOGMM fit."""
    if not KITTI.exists():
        return None
    from psimap.geometry.depth_noise import estimate_lidar_noise
    from psimap.geometry.points import lidar_points
    from psimap.geometry.sogmm import fit_sogmm
    from psimap.train.lidar import Sweep, lidar_views

    raw = np.fromfile(KITTI, dtype=np.float32).reshape(-1, 4)
    p = lidar_points(raw)
    sweep = Sweep(points=p[:, :3].astype(np.float64), intensity=p[:, 3], origin=np.zeros(3), name="kitti")
    t = time.perf_counter()
    sigma = estimate_lidar_noise(sweep.points, sweep.origin)
    views = lidar_views(sweep)
    fit = fit_sogmm(p, noise=np.full(len(p), sigma or 0.02), voxel=0.05)
    return [f"KITTI 000000 ({len(p)} returns)", f"{(sigma or float('nan')) * 1000:.1f} mm",
            len(views), sum(v.z.numel() for v in views), fit.K, time.perf_counter() - t]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--iters", type=int, default=450)
    args = ap.parse_args(argv)
    if args.quick:
        args.seeds, args.frames, args.iters = args.seeds[:1], 30, 150
    from psimap.data.synthetic import generate
    from psimap.data.synthetic_noise import DepthNoise

    rows = []
    sensors = {"default depth": True, "depth noise x3": DepthNoise.degraded(3.0)}
    for seed in args.seeds:
        for sensor, model in sensors.items():
            data = OUT / f"room_s{seed}_{args.frames}_{sensor.split()[-1]}"
            generate(data, seed=seed, frames=args.frames, lidar=True, depth_noise=model, progress=False,
                     overwrite=True)
            for mode in MODES:
                if mode == MODES[2] and sensor != "default depth":
                    continue                # no depth images: the depth sensor does not matter
                print(f"== seed {seed}, {sensor}: {mode}", flush=True)
                rows.append(run_mode(mode, data, args.iters, seed, sensor))
                print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in rows[-1].items()}, flush=True)
    table = markdown_table(["sensor", "mode", "seed", *COLS],
                           [[r["sensor"], r["mode"], r["seed"]] + ["-" if r[c] is None else r[c] for c in COLS]
                            for r in rows])
    groups = list(dict.fromkeys((r["sensor"], r["mode"]) for r in rows))
    means = {}
    for g in groups:
        rs = [r for r in rows if (r["sensor"], r["mode"]) == g]
        means[g] = {c: float(np.mean([r[c] for r in rs if r[c] is not None] or [np.nan])) for c in COLS}
    mean_table = markdown_table(["sensor", "mode (mean over seeds)", *COLS],
                                [[*g] + [means[g][c] for c in COLS] for g in groups])
    kitti = kitti_row()
    kitti_table = "" if kitti is None else "\n\nReal KITTI sweep through the prior's input path (range noise " \
        "estimated from the sweep, virtual views, SOGMM fit at a 5 cm voxel):\n\n" + markdown_table(
            ["sweep", "range noise", "views", "returns in views", "SOGMM K", "time (s)"], [kitti])
    print(mean_table + kitti_table)
    if args.quick:
        return 0
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for g, c in zip(groups, ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:red")):
        rs = [r for r in rows if (r["sensor"], r["mode"]) == g and r["F1@5cm"] is not None]
        marker = "o" if g[0] == "default depth" else "^"
        label = g[1] if g[1] == MODES[2] else f"{g[1]}, {g[0]}"
        axes[0].scatter([r["train (s)"] for r in rs], [r["F1@5cm"] for r in rs], color=c, marker=marker, label=label)
        axes[1].scatter([r["train (s)"] for r in rs], [r["Chamfer-L1 (cm)"] for r in rs], color=c, marker=marker)
    axes[0].set(xlabel="train time (s)", ylabel="F1@5cm (higher is better)")
    axes[1].set(xlabel="train time (s)", ylabel="Chamfer-L1 cm (lower is better)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    plot = save_plot(fig, "lidar")
    body = (f"Generated rooms, 160x120, {args.frames} frames, a LiDAR sweep every 10 frames, {args.iters} "
            f"geometry steps, no panoptic phase; seeds {args.seeds}; the default depth sensor and one with 3x "
            "its noise std (`DepthNoise.degraded(3)`). 'RGB + LiDAR' trains on the same capture with every "
            "depth image removed. Times are wall seconds on a shared 2-core machine: compare within a "
            "row's run only.\n\n" + mean_table + "\n\nPer seed:\n\n" + table + kitti_table)
    heads = [(f"LiDAR ablation F1@5cm / Chamfer: {g[1]}" + ("" if g[1] == MODES[2] else f", {g[0]}"),
              f"{means[g]['F1@5cm']:.3f} / {means[g]['Chamfer-L1 (cm)']:.2f} cm ({means[g]['train (s)']:.0f} s)")
             for g in groups]
    write_section("lidar", "LiDAR in training: ablation", body, headlines=heads, plot=plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
