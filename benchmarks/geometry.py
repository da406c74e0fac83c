"""Geometry benchmark (issue 5): psimap vs TSDF of the raw noisy depth vs training without the SOGMM
prior, on synthetic scenes with exact ground truth, plus the real 7-Scenes chess frames.

Reports accuracy, completeness, Chamfer-L1, F1@5 cm, time and surfel count in one run; plots CPU
time vs Chamfer per method (and, with curves, iterations and TSDF voxel size vs F1 / time). Each
mode has its section of benchmarks/RESULTS.md: `geometry` (default sensor), `geometry/noise-x3`,
`geometry/dropout-0.9` (depth quality), `geometry/chess`, `geometry/default-train`; --quick and
--no-append only print.

    python benchmarks/geometry.py                 # demo size + two other sizes + chess
    python benchmarks/geometry.py --quick         # small scene only, few iterations
    python benchmarks/geometry.py --sizes 60x160x120 --seeds 0 1 2 --no-chess --no-curves
                                                  # per-seed rows + mean ± std over seeds
    python benchmarks/geometry.py --sizes 60x160x120 --seeds 0 1 --depth-noise 3 --no-chess --no-curves
                                                  # a noisier sensor (std x3); --depth-dropout 0.75: sparser
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import markdown_table, save_plot, write_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench_out"
CHESS = ROOT.parent / "shared" / "data" / "7scenes-chess"


RAW, PSIMAP, NO_PRIOR = "TSDF of raw depth", "psimap (SOGMM prior)", "2DGS losses, no prior"
METRIC_COLS = ("accuracy (cm)", "completeness (cm)", "Chamfer-L1 (cm)", "F1@5cm", "wall (s)", "CPU (s)",
               "surfels")


def _row(label, seed, method, m, wall, cpu, surfels) -> dict:
    """One result: scene label, seed, method, metrics (cm), wall / CPU seconds (train + mesh; raw
    TSDF: fusion), surfel count (None for the raw TSDF)."""
    if m is None:          # the method produced no mesh (e.g. TSDF of very sparse depth): no metrics
        m = {"accuracy": None, "completeness": None, "chamfer_l1": None, "f1": None}

    def cm(v):
        return None if v is None else v * 100

    return {"scene": label, "seed": seed, "method": method, "accuracy (cm)": cm(m["accuracy"]),
            "completeness (cm)": cm(m["completeness"]), "Chamfer-L1 (cm)": cm(m["chamfer_l1"]),
            "F1@5cm": m["f1"], "wall (s)": wall, "CPU (s)": cpu, "surfels": surfels}


def per_seed_table(rows) -> str:
    return markdown_table(["scene", "seed", "method", *METRIC_COLS],
                          [[r["scene"], r["seed"], r["method"]] +
                           [("-" if r[c] is None else r[c]) for c in METRIC_COLS] for r in rows])


def mean_table(rows) -> tuple[str, dict]:
    """Mean +- std over seeds per (scene, method); also returns {(scene, method): {col: mean}}."""
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["scene"], r["method"]), []).append(r)
    out, means = [], {}
    for (scene, method), rs in groups.items():
        cells, means[(scene, method)] = [], {}
        for c in METRIC_COLS:
            v = np.array([r[c] for r in rs if r[c] is not None], dtype=float)
            if v.size == 0:
                cells.append("-")
                continue
            means[(scene, method)][c] = float(v.mean())
            prec = 4 if c == "F1@5cm" else (0 if c in ("surfels",) else 3 if "(cm)" in c else 1)
            cells.append(f"{v.mean():.{prec}f} ± {v.std(ddof=1) if v.size > 1 else 0.0:.{prec}f}")
        # seeds whose method gave no mesh are left out of its mean: say how many remain
        n_mesh = sum(r["F1@5cm"] is not None for r in rs)
        out.append([scene, len(rs) if n_mesh == len(rs) else f"{len(rs)} ({n_mesh} with a mesh)", method] + cells)
    return markdown_table(["scene", "seeds", "method", *METRIC_COLS], out), means


def verdict(means) -> list[str]:
    """Per scene: does psimap's mean Chamfer / F1 beat both baselines."""
    lines = []
    for scene in dict.fromkeys(k[0] for k in means):
        p, r, n = (means.get((scene, k), {}) for k in (PSIMAP, RAW, NO_PRIOR))
        if not (p and r and n) or "F1@5cm" not in p:
            continue
        # a baseline without a mesh on some seed has no mean: it counts as beaten
        for b in (r, n):
            b.setdefault("Chamfer-L1 (cm)", float("inf"))
            b.setdefault("F1@5cm", 0.0)
        ch = p["Chamfer-L1 (cm)"] < min(r["Chamfer-L1 (cm)"], n["Chamfer-L1 (cm)"])
        f1 = p["F1@5cm"] > max(r["F1@5cm"], n["F1@5cm"])
        lines.append(f"{scene}: psimap mean Chamfer-L1 {p['Chamfer-L1 (cm)']:.3f} cm vs raw TSDF "
                     f"{r['Chamfer-L1 (cm)']:.3f} / no prior {n['Chamfer-L1 (cm)']:.3f} "
                     f"({'better than both' if ch else 'NOT better than both'}); F1 {p['F1@5cm']:.4f} vs "
                     f"{r['F1@5cm']:.4f} / {n['F1@5cm']:.4f} ({'better than both' if f1 else 'NOT better than both'}).")
    return lines


def _geo(mesh, data, samples):
    """Geometry metrics of `mesh`, or None when it has no faces (printed, the run goes on)."""
    from psimap.metrics.evaluate import evaluate_geometry

    if mesh is None or len(mesh.faces) == 0:
        print("    the mesh is empty: no metrics", flush=True)
        return None
    return evaluate_geometry(mesh, data, samples=samples)


def fuse_scene(depths, Ks, c2ws, **kw):
    """fuse_tsdf with the whole-scene cleaning Scene.mesh uses (the baselines mesh like psimap)."""
    from psimap.geometry.tsdf import SCENE_KEEP_FRACTION, SCENE_MIN_COMPONENT_VOXELS, fuse_tsdf

    return fuse_tsdf(depths, Ks, c2ws, keep_fraction=SCENE_KEEP_FRACTION,
                     min_component_voxels=SCENE_MIN_COMPONENT_VOXELS, **kw)


def raw_tsdf(data, voxel=None):
    """TSDF of the observed (noisy) depth and colour of every frame."""
    from psimap.data import load
    seq = load(data)
    fr = [seq[i] for i in range(len(seq))]
    t, c = time.perf_counter(), time.process_time()
    mesh = fuse_scene([f.depth for f in fr], [f.K for f in fr], [f.c2w for f in fr],
                      colors=[f.rgb for f in fr], voxel_size=voxel)
    return mesh, time.perf_counter() - t, time.process_time() - c


def depth_tag(noise: float, dropout: float | None) -> str:
    """Scene-label suffix / folder tag of a depth-quality setting ('' = the default sensor)."""
    parts = ([f"depth noise x{noise:g}"] if noise != 1.0 else []) + (
        [f"depth dropout {dropout:g}"] if dropout is not None else [])
    return ", ".join(parts)


def run_size(label, frames, width, height, iters, seed, samples, curves: bool, rows, curve_data,
             depth_noise: float = 1.0, depth_dropout: float | None = None, methods=(RAW, PSIMAP, NO_PRIOR)):
    import torch

    from psimap.data.synthetic import generate
    from psimap.data.synthetic_noise import DepthNoise
    from psimap.scene import Scene
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import surfel_values, train

    tag = "" if not depth_tag(depth_noise, depth_dropout) else (
        f"_n{depth_noise:g}" + ("" if depth_dropout is None else f"_d{depth_dropout:g}"))
    data = OUT / f"geometry_scene_{frames}x{width}x{height}_s{seed}{tag}"
    # the default sensor stays `True` so the default scenes are the generator's own defaults
    sensor = DepthNoise.degraded(depth_noise, depth_dropout) if tag else True
    t = time.perf_counter()
    generate(data, seed, frames=frames, width=width, height=height, depth_noise=sensor, progress=False)
    print(f"[{label}] generated {data} in {time.perf_counter() - t:.1f} s", flush=True)

    if RAW in methods:
        mesh, secs, cpu = raw_tsdf(data)
        m = _geo(mesh, data, samples)
        rows.append(_row(label, seed, RAW, m, secs, cpu, None))
        print(rows[-1], flush=True)

    for name, prior in ((PSIMAP, True), (NO_PRIOR, False)):
        if name not in methods:
            continue
        snaps = {}
        marks = set(np.unique(np.linspace(iters / 5, iters, 5).round().astype(int)).tolist()) if (
            curves and prior) else set()

        def cb(step, params, elapsed):
            if step in marks:
                snaps[step] = (surfel_values(params), elapsed)

        cfg = TrainConfig(iters=iters, seed=seed, use_prior=prior, panoptic=False)   # geometry only
        t = time.perf_counter()
        scene = train(str(data), cfg, callback=cb, log=lambda s: print("   ", s, flush=True))
        t_train = time.perf_counter() - t
        t = time.perf_counter()
        c = time.process_time()
        mesh = scene.mesh()
        t_mesh, c_mesh = time.perf_counter() - t, time.process_time() - c
        m = _geo(mesh, data, samples)
        rows.append(_row(label, seed, name, m, t_train + t_mesh,
                         scene.metrics["cpu_seconds"] + c_mesh, len(scene)))
        print(rows[-1], f"(train {t_train:.1f} s, mesh {t_mesh:.1f} s)", flush=True)
        curve_data.setdefault("densify", []).append((f"{label}, seed {seed}", name, scene.metrics.get("densify", [])))
        if curves and prior:
            it_curve = []
            for step in sorted(snaps):
                sv, elapsed = snaps[step]
                sc = Scene(sv, cameras=scene.cameras)
                mm = _geo(sc.mesh(), data, samples)
                it_curve.append((step, elapsed, mm["f1"], mm["chamfer_l1"]))
            curve_data["iters"] = it_curve
            base = mesh.metadata["tsdf"]["voxel_size"]
            vox_curve = []
            depths = scene.rendered_depths()
            for f in (0.5, 0.75, 1.0, 1.5, 2.0):
                t = time.perf_counter()
                vm = fuse_scene(depths[0], depths[2], depths[3], colors=depths[1], voxel_size=base * f)
                tv = time.perf_counter() - t
                mm = _geo(vm, data, samples)
                vox_curve.append((base * f, tv, mm["f1"], mm["chamfer_l1"]))
            curve_data["voxel"] = vox_curve
            torch.save({"iters": it_curve, "voxel": vox_curve}, OUT / "geometry_curves.pt")


def plot(rows, curve_data):
    """CPU seconds vs Chamfer-L1 of every (scene, seed, method) row, then the iteration and TSDF
    voxel curves when measured: one figure, one panel each (not yet saved)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = [(key, xlabel) for key, xlabel in (("iters", "training iterations"), ("voxel", "TSDF voxel size (m)"))
              if curve_data.get(key)]
    fig, axes = plt.subplots(1, 1 + len(curves), figsize=(5.5 * (1 + len(curves)), 4), squeeze=False)
    ax = axes[0, 0]
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    for k, method in enumerate((RAW, PSIMAP, NO_PRIOR)):
        for j, scene in enumerate(scenes):
            pts = [(r["CPU (s)"], r["Chamfer-L1 (cm)"]) for r in rows
                   if r["method"] == method and r["scene"] == scene and r["Chamfer-L1 (cm)"] is not None]
            if pts:
                ax.scatter(*zip(*pts), color=f"C{k}", marker="os^Dv"[j % 5],
                           label=method if j == 0 else None)
    ax.set(xscale="log", xlabel="CPU s (training + meshing; raw TSDF: fusion)", ylabel="Chamfer-L1 (cm)",
           title="speed vs error, per scene and seed")
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())     # minor labels overlap on a log axis
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    for ax, (key, xlabel) in zip(axes[0, 1:], curves):
        c = curve_data[key]
        x = [r[0] for r in c]
        ax.plot(x, [r[2] for r in c], "o-", color="C0")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("F1 @ 5 cm", color="C0")
        ax2 = ax.twinx()
        ax2.plot(x, [r[1] for r in c], "s--", color="C1")
        ax2.set_ylabel("time (s)", color="C1")
        ax.set_title(f"psimap: {xlabel} vs F1 and time")
    fig.tight_layout()
    return fig


def section_key(noise: float, dropout: float | None) -> str:
    """'geometry' for the default sensor, else e.g. 'geometry/noise-x3', 'geometry/dropout-0.9'."""
    parts = ([f"noise-x{noise:g}"] if noise != 1.0 else []) + ([f"dropout-{dropout:g}"] if dropout is not None else [])
    return "/".join(["geometry", "-".join(parts)]) if parts else "geometry"


def headlines(rows, means) -> list[tuple[str, str]]:
    """Per scene: psimap's Chamfer-L1 / F1 beside both baselines' (means over seeds when several)."""
    out = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        seeds = sorted({r["seed"] for r in rows if r["scene"] == scene})
        vals = {}
        for m in (PSIMAP, RAW, NO_PRIOR):
            if (scene, m) in means:
                vals[m] = means[(scene, m)]
            else:
                r = next((r for r in rows if r["scene"] == scene and r["method"] == m), None)
                vals[m] = r and {c: r[c] for c in ("Chamfer-L1 (cm)", "F1@5cm") if r[c] is not None}

        def cell(m):
            v = vals.get(m)
            if not v or v.get("Chamfer-L1 (cm)", float("inf")) == float("inf"):
                return "no mesh"
            return f"{v['Chamfer-L1 (cm)']:.3f} cm / {v['F1@5cm']:.4f}"

        if vals.get(PSIMAP) is None:
            continue
        base = "; ".join(f"{name} {cell(m)}" for name, m in (("raw TSDF", RAW), ("no prior", NO_PRIOR))
                         if any(r["method"] == m and r["scene"] == scene for r in rows))
        label = f"{scene}: psimap Chamfer-L1 / F1@5cm" + (f" (mean of seeds {', '.join(map(str, seeds))})"
                                                          if len(seeds) > 1 else f" (seed {seeds[0]})")
        out.append((label, cell(PSIMAP) + (f" (vs {base})" if base else "")))
    return out


def run_chess(iters, seed, n_frames, rows):
    """Real frames: psimap mesh vs the raw-depth TSDF mesh (no ground truth exists)."""
    from psimap.data import load
    from psimap.data.frames import FrameSequence
    from psimap.metrics.geometry import geometry_metrics
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import train

    seq = load(CHESS)
    idx = np.linspace(0, len(seq) - 1, min(n_frames, len(seq))).round().astype(int)
    sub = FrameSequence(loader=lambda i: seq[int(idx[i])], count=len(idx), classes=seq.classes,
                        root=str(CHESS))
    frames = [sub[i] for i in range(len(sub))]
    t = time.perf_counter()
    raw = fuse_scene([f.depth for f in frames], [f.K for f in frames], [f.c2w for f in frames],
                    colors=[f.rgb for f in frames])
    t_raw = time.perf_counter() - t
    t = time.perf_counter()
    scene = train(sub, TrainConfig(iters=iters, seed=seed, panoptic=False), log=lambda s: print("   ", s, flush=True))
    t_train = time.perf_counter() - t
    t = time.perf_counter()
    mesh = scene.mesh()
    t_mesh = time.perf_counter() - t
    m = geometry_metrics(mesh, raw, threshold=0.05, max_samples=100_000, seed=0)
    rows.append([f"chess ({len(frames)} frames, {frames[0].width}x{frames[0].height})", iters,
                 m["accuracy"] * 100, m["completeness"] * 100, m["chamfer_l1"] * 100, m["f1"],
                 t_raw, t_train, t_mesh, len(scene)])
    print(rows[-1], flush=True)


def run_default(frames, width, height, seed, samples):
    """The default `psimap train` (geometry + panoptic phase, TrainConfig defaults) on one scene:
    wall and CPU time, surfels, and the mesh's F1 / Chamfer."""
    import os

    from psimap.data.synthetic import generate
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import train

    data = OUT / f"geometry_scene_{frames}x{width}x{height}_s{seed}"
    if not (data / "transforms.json").exists():
        generate(data, seed, frames=frames, width=width, height=height, progress=False)
    load0 = os.getloadavg()[0]
    scene = train(str(data), TrainConfig(seed=seed), log=lambda s: print("   ", s, flush=True))
    m = _geo(scene.mesh(), data, samples)
    met = scene.metrics
    row = [f"{frames} frames {width}x{height}", met["steps"], TrainConfig().panoptic_iters,
           met["seconds"], met["cpu_seconds"], len(scene), m["f1"], m["chamfer_l1"] * 100,
           f"{load0:.1f} / {os.getloadavg()[0]:.1f}"]
    table = markdown_table(["scene", "geometry steps", "panoptic steps", "wall (s)", "CPU (s)", "surfels",
                            "F1@5cm", "Chamfer-L1 (cm)", "load avg start / end"], [row])
    return table, row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small scene, few iterations, no chess")
    ap.add_argument("--iters", type=int, default=0, help="training iterations (0 = config default)")
    ap.add_argument("--sizes", default="", help="comma list FRAMESxWxH (default: demo size and two others; none = skip)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seeds", type=int, nargs="+", default=None,
                    help="several scene / training seeds: per-seed rows plus a mean ± std table")
    ap.add_argument("--depth-noise", type=float, default=1.0,
                    help="scale the synthetic depth sensor's noise std (1 = the generator default)")
    ap.add_argument("--depth-dropout", type=float, default=None,
                    help="random per-pixel depth dropout rate (default: the sensor's 0.005); e.g. 0.75 "
                         "keeps a quarter of the pixels")
    ap.add_argument("--methods", default="raw,psimap,noprior",
                    help="comma list of raw, psimap, noprior: which methods to run (a baseline whose "
                         "code did not change need not be re-run)")
    ap.add_argument("--samples", type=int, default=100_000, help="max points sampled per mesh")
    ap.add_argument("--chess-frames", type=int, default=60)
    ap.add_argument("--no-chess", action="store_true")
    ap.add_argument("--no-curves", action="store_true", help="skip the iteration and voxel curves")
    ap.add_argument("--no-append", action="store_true", help="print tables only")
    ap.add_argument("--default-train", action="store_true",
                    help="only time the default training (panoptic phase included) at the first size")
    args = ap.parse_args(argv)
    import os

    from psimap.train.config import TrainConfig

    OUT.mkdir(exist_ok=True)
    iters = args.iters or (150 if args.quick else TrainConfig().iters)
    sizes = args.sizes or ("20x80x60" if args.quick else "60x160x120,30x80x60,60x240x180")
    if args.default_train:
        OUT.mkdir(exist_ok=True)
        f, w, h = (int(v) for v in (args.sizes or "60x160x120").split(",")[0].split("x"))
        table, row = run_default(f, w, h, args.seed, args.samples)
        note = ("Default `psimap train` settings (TrainConfig defaults, panoptic phase on); target <= 3 min "
                "on this 2-core machine. CPU = process time (training is single-threaded, so on an idle "
                "machine wall ~ CPU); the machine was shared with other jobs.")
        print(table)
        if not (args.no_append or args.quick):
            write_section("geometry/default-train", "Geometry: default demo-size training time",
                          table + "\n\n" + note,
                          headlines=[("default `psimap train`, demo scene, geometry + panoptic (target <= 180 s)",
                                      f"{row[4]:.1f} s CPU, {row[3]:.1f} s wall")])
        return
    seeds = args.seeds if args.seeds else [args.seed]
    names = {"raw": RAW, "psimap": PSIMAP, "noprior": NO_PRIOR}
    try:
        methods = tuple(names[m.strip()] for m in args.methods.split(",") if m.strip())
    except KeyError as e:
        ap.error(f"unknown method {e}; use raw, psimap, noprior")
    rows, curves = [], {}
    load_start = os.getloadavg()
    for k, s in enumerate([] if sizes == "none" else sizes.split(",")):
        f, w, h = (int(v) for v in s.split("x"))
        quality = depth_tag(args.depth_noise, args.depth_dropout)
        for j, seed in enumerate(seeds):
            run_size(f"{f} frames {w}x{h}" + (f", {quality}" if quality else ""), f, w, h, iters, seed,
                     args.samples, k == 0 and j == 0 and not args.no_curves, rows, curves,
                     args.depth_noise, args.depth_dropout, methods)
    table = per_seed_table(rows)
    mtable, means = mean_table(rows) if len(seeds) > 1 else ("", {})
    load_end = os.getloadavg()
    notes = [f"{iters} training iterations, seed(s) {', '.join(map(str, seeds))}; scenes from "
             f"`psimap.data.synthetic.generate(seed"
             f"{'' if not depth_tag(args.depth_noise, args.depth_dropout) else f', depth_noise=DepthNoise.degraded({args.depth_noise:g}, {args.depth_dropout})'})`; wall / CPU = training + mesh extraction (raw TSDF: "
             f"fusion only; panoptic phase off; CPU = process time); F1 at 5 cm, completeness on camera-seen "
             f"GT (docs/metrics.md). Load average (1 / 5 / 15 min) at the start "
             f"{' / '.join(f'{v:.1f}' for v in load_start)}, at the end "
             f"{' / '.join(f'{v:.1f}' for v in load_end)} on 2 shared cores: wall times are noisy, "
             f"compare CPU seconds."]
    if mtable:
        notes.append("Mean ± std (sample std) over the seeds:\n\n" + mtable)
        notes.extend(verdict(means))
    if curves.get("iters"):
        notes.append("Iterations vs F1 / time (first scene): " + ", ".join(
            f"{s}: F1 {f1:.3f} @ {t:.0f} s" for s, t, f1, _ in curves["iters"]) + " (plot below)")
    if curves.get("voxel"):
        notes.append("TSDF voxel vs F1 / time: " + ", ".join(
            f"{v * 100:.1f} cm: F1 {f1:.3f} in {t:.1f} s" for v, t, f1, _ in curves["voxel"]) + " (plot below)")
    for label, name, rounds in curves.get("densify", []):
        notes.append(f"Density control, {label}, {name} (step: cloned / split / pruned -> surfels): " + ", ".join(
            f"{r['step']}: {r['cloned']} / {r['split']} / {r['pruned']} -> {r['surfels']}" for r in rounds))
    chess_rows = []
    if not (args.quick or args.no_chess) and CHESS.exists():
        run_chess(iters, seeds[0], args.chess_frames, chess_rows)
    record = not (args.no_append or args.quick)
    if rows and not record:
        print(table)
        print("\n".join(notes))
    elif rows:
        quality = depth_tag(args.depth_noise, args.depth_dropout)
        write_section(section_key(args.depth_noise, args.depth_dropout),
                      "Geometry: psimap vs raw-depth TSDF vs no-prior training" + (f" ({quality})" if quality else ""),
                      table + "\n\n" + "\n\n".join(notes), headlines=headlines(rows, means),
                      plot=save_plot(plot(rows, curves), section_key(args.depth_noise, args.depth_dropout)))
    if chess_rows:
        t2 = markdown_table(["frames", "iters", "accuracy vs raw TSDF (cm)", "completeness (cm)",
                             "Chamfer-L1 (cm)", "F1@5cm", "raw TSDF (s)", "train (s)", "mesh (s)",
                             "surfels"], chess_rows)
        note = "Real 7-Scenes chess frames: distances between the psimap mesh and the raw-depth TSDF mesh."
        if not record:
            print(t2)
        else:
            c = chess_rows[0]
            write_section("geometry/chess", "Geometry: 7-Scenes chess, psimap mesh vs raw-depth TSDF",
                          t2 + "\n\n" + note,
                          headlines=[(f"7-Scenes {c[0]}: psimap mesh vs raw-depth TSDF mesh",
                                      f"Chamfer-L1 {c[4]:.3f} cm, F1@5cm {c[5]:.4f}")])


if __name__ == "__main__":
    main()
