"""Geometry work proportional to the scene (issue #20, geometry side): surfel spacing by viewing
distance with large planar stuff coarser and a total cap, and geometry steps that stop at a loss
plateau, against the rule before (one spacing at the median depth for all, no cap, every step run),
on the demo scene and on a far-wall capture, measured in one run with the runs interleaved.

The far-wall capture breaks the median-depth rule as a real lab capture did (a table filmed from
0.5-0.8 m against walls 2.5-4 m away: the median depth is the table's, so the far walls got the
table's spacing): `far_wall_capture` is the generator's tabletop layout with the hand-held orbit
moved close to the table and the walls moved out.

    python benchmarks/budget.py                    # demo scene + far-wall capture, before / after
    python benchmarks/budget.py --scenes far --no-append

Reports surfels (prior / trained, on things / stuff: benchmarks/surfels.py's GT assignment),
geometry steps, train wall and CPU seconds (after / before ratio), scene F1 / Chamfer, Chamfer and
F1 near things (GT thing surfaces only) and the object F-score of `psimap eval` (objects extracted as
`psimap export` does). Section `surfels/budget` of benchmarks/RESULTS.md.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import markdown_table, save_plot, write_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench_out" / "budget"
# The rule before issue #20's geometry work, as TrainConfig settings.
BEFORE = {"distance_spacing": False, "max_surfels": 0, "plateau_window": 0}
# ... and after: spacing by viewing distance (opt-in), the cap and the plateau rule (defaults).
AFTER = {"distance_spacing": True}
# Far-wall capture: camera 0.5-0.8 m from the table centre at 1.0-1.2 m, walls 2.5-4 m from it.
FAR_WALL = {"CAMERA_DISTANCE": (0.5, 0.8), "CAMERA_HEIGHT": (1.0, 1.2), "WALL_DISTANCE": (2.5, 4.0)}


@contextlib.contextmanager
def _far_walls():
    from psimap.data import synthetic

    old = {k: getattr(synthetic, k) for k in FAR_WALL}
    try:
        for k, v in FAR_WALL.items():
            setattr(synthetic, k, v)
        yield
    finally:
        for k, v in old.items():
            setattr(synthetic, k, v)


def far_wall_capture(out, seed: int = 0, *, frames: int = 20, width: int = 640, height: int = 480,
                     n_objects: int | None = None) -> Path:
    """A tabletop scene filmed close against far walls (FAR_WALL), written to `out` (kept if there)."""
    from psimap.data.synthetic import generate

    out = Path(out)
    if not (out / "transforms.json").exists():
        with _far_walls():
            generate(out, seed, frames=frames, width=width, height=height, layout="tabletop",
                     n_objects=n_objects, progress=False)
    return out


def demo_scene(out, seed: int = 0) -> Path:
    """The scene `psimap demo` trains on (the generator's defaults: 60 frames, 160x120 room)."""
    from psimap.data.synthetic import generate

    out = Path(out)
    if not (out / "transforms.json").exists():
        generate(out, seed, progress=False)
    return out


def near_things(mesh, data: Path, threshold: float = 0.01) -> dict:
    """Geometry at the things: the predicted mesh's faces within 3 cm of a GT thing surface against
    the GT thing surfaces (instance > 0) seen by the cameras, F1 at `threshold` (1 cm)."""
    from psimap.data import load
    from psimap.metrics.evaluate import cameras_of
    from psimap.metrics.geometry import geometry_metrics, raycasting_scene
    from surfels import gt_surface_labels

    gmesh, inst, _, _ = gt_surface_labels(data)
    things = gmesh.submesh([np.flatnonzero(inst > 0)], append=True)
    rs = raycasting_scene(np.asarray(things.vertices), np.asarray(things.faces))
    import open3d as o3d

    d = rs.compute_distance(o3d.core.Tensor(np.asarray(mesh.triangles_center, np.float32))).numpy()
    crop = mesh.submesh([np.flatnonzero(d < 0.03)], append=True)
    m = geometry_metrics(crop, things, threshold=threshold, cameras=cameras_of(load(data)),
                         max_samples=100_000, seed=0)
    return {"chamfer_cm": m["chamfer_l1"] * 100, "f1": m["f1"], "accuracy_cm": m["accuracy"] * 100,
            "completeness_cm": m["completeness"] * 100}


def prior_counts(data: Path) -> dict:
    """{rule: (initial surfels, what the spacing asked for, seconds)} of the prior alone (no training)."""
    from psimap.data import load
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import init_from_prior, prepare_frames, target_spacing

    seq = load(data)
    out = {}
    for v in ("before", "after"):
        cfg = TrainConfig(**(BEFORE if v == "before" else AFTER))
        t = time.perf_counter()
        fr, _, _, _ = prepare_frames(seq, cfg, log=lambda m: None)
        spacing = target_spacing(fr, cfg.spacing_pixels)
        _, _, info = init_from_prior(fr, cfg, spacing, list(seq.classes), log=lambda m: print("   ", m, flush=True))
        out[v] = (info["n_init"], info["n_needed"], time.perf_counter() - t)
    return out


def run_one(label: str, data: Path, variant: str) -> dict:
    """Train (default settings, or BEFORE's) on `data`, evaluate; the run record (kept as JSON)."""
    from psimap.metrics.evaluate import evaluate
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import train
    from surfels import gt_surface_labels, surfels_per_instance

    cfg = TrainConfig(**(BEFORE if variant == "before" else AFTER))
    prior = {}

    def snapshot(step, params, elapsed):
        if not prior:
            prior["means"] = params["means"].detach().numpy().copy()

    load0 = os.getloadavg()[0]
    scene = train(str(data), cfg, callback=snapshot, log=lambda s: print("   ", s, flush=True), progress=False)
    ckpt = OUT / f"{label}_{variant}.ckpt"
    scene.save(ckpt, overwrite=True)
    ev = evaluate(ckpt, data, samples=100_000)
    gt = gt_surface_labels(data)
    near = near_things(scene.mesh(), data)
    m = scene.metrics
    on = {k: surfels_per_instance(v, gt) for k, v in (("prior", prior["means"]),
                                                       ("trained", scene.surfels["means"].numpy()))}
    rec = {"scene": label, "variant": variant, "n_prior": int(len(prior["means"])), "n_needed": m.get("n_needed"),
           "n_trained": len(scene), "budget": m["budget"], "geometry_steps": m.get("geometry_steps", m["steps"]),
           "stop": m.get("geometry_stop", "cap"), "plateau_checks": m.get("plateau_checks", []),
           "train_s": m["seconds"], "train_cpu_s": m["cpu_seconds"],
           "panoptic_s": m.get("panoptic_seconds"),
           "things_prior": sum(c for k, c in on["prior"].items() if k > 0),
           "things_trained": sum(c for k, c in on["trained"].items() if k > 0),
           "f1": ev["geometry"]["f1"], "chamfer_cm": ev["geometry"]["chamfer_l1"] * 100,
           "pq": ev.get("panoptic", {}).get("pq"), "near_things": near,
           "load": [load0, os.getloadavg()[0]]}
    (OUT / f"{label}_{variant}.json").write_text(json.dumps(rec, indent=1))
    print(json.dumps({k: v for k, v in rec.items() if k != "plateau_checks"}), flush=True)
    return rec


def table(runs: dict) -> tuple[str, list]:
    rows, heads = [], []
    for label in dict.fromkeys(k[0] for k in runs):
        b, a = runs.get((label, "before")), runs.get((label, "after"))
        for v, r in (("before", b), ("after", a)):
            if r is None:
                continue
            ratio = "" if not (a and b) or v == "before" else f" ({a['train_s'] / b['train_s']:.2f}x)"
            cpu_ratio = "" if not (a and b) or v == "before" else f" ({a['train_cpu_s'] / b['train_cpu_s']:.2f}x)"
            rows.append([label, v, r["n_prior"], r["n_trained"], r["things_prior"], r["things_trained"],
                         f"{r['geometry_steps']} ({r['stop']})", f"{r['train_s']:.1f}{ratio}", f"{r['train_cpu_s']:.1f}{cpu_ratio}",
                         f"{r['f1']:.4f}", f"{r['chamfer_cm']:.3f}", f"{r['near_things']['f1']:.4f}",
                         f"{r['near_things']['chamfer_cm']:.3f}", "-" if r["pq"] is None else f"{r['pq']:.3f}",
                         f"{r['load'][0]:.1f} / {r['load'][1]:.1f}"])
        if a and b:
            heads.append((f"{label}: surfels, train CPU s, F1, PQ before -> after",
                          f"{b['n_trained']} -> {a['n_trained']}, {b['train_cpu_s']:.0f} -> {a['train_cpu_s']:.0f} s "
                          f"({a['train_cpu_s'] / b['train_cpu_s']:.2f}x), {b['f1']:.3f} -> {a['f1']:.3f}, "
                          f"{b['pq']:.3f} -> {a['pq']:.3f}"))
    t = markdown_table(["scene", "rule", "surfels prior", "surfels trained", "on things prior", "on things trained",
                        "geometry steps (stop)", "train wall s (after / before)", "train CPU s (after / before)", "F1@5cm",
                        "Chamfer-L1 (cm)", "things F1@1cm", "things Chamfer (cm)", "PQ", "load start / end"], rows)
    return t, heads


def plot(runs: dict):
    """Surfels and train seconds before / after per scene (bars), F1 on top."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = list(dict.fromkeys(k[0] for k in runs))
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    x = np.arange(len(labels))
    for k, v in enumerate(("before", "after")):
        rs = [runs.get((lab, v)) for lab in labels]
        for ax, key, title in ((axes[0], "n_trained", "trained surfels"), (axes[1], "train_s", "train wall s")):
            vals = [r[key] if r else 0 for r in rs]
            bars = ax.bar(x + (k - 0.5) * 0.38, vals, 0.38, color=f"C{k}", label=v)
            for bar, r in zip(bars, rs):
                if r:
                    ax.annotate(f"F1 {r['f1']:.3f}", (bar.get_x() + bar.get_width() / 2, bar.get_height()),
                                ha="center", va="bottom", fontsize=7)
            ax.set(xticks=x, xticklabels=labels, title=title)
            ax.set_yscale("log")
    axes[0].legend()
    fig.tight_layout()
    return fig


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["demo", "far"], choices=["demo", "far"])
    ap.add_argument("--far-size", default="10x96x72",
                    help="FRAMESxWxH of the far-wall capture (the rule before trains ~(W / 320)^2 x 520k "
                         "surfels on it: keep it small)")
    ap.add_argument("--no-append", action="store_true")
    ap.add_argument("--reuse", action="store_true", help="take runs kept in bench_out/budget instead of training")
    ap.add_argument("--prior-only", default="", metavar="FxWxH",
                    help="only the prior's surfel counts (no training) of far-wall captures of these "
                         "sizes (comma list), before / after: section surfels/budget-prior")
    args = ap.parse_args(argv)
    OUT.mkdir(parents=True, exist_ok=True)
    if args.prior_only:
        rows = []
        for size in args.prior_only.split(","):
            f, w, h = (int(v) for v in size.split("x"))
            data = far_wall_capture(OUT / f"far_{size}", 0, frames=f, width=w, height=h)
            c = prior_counts(data)
            rows.append([f"far-wall ({f} frames {w}x{h})", c["before"][0], c["after"][0],
                         f"{c['after'][0] / c['before'][0]:.3f}", f"{c['before'][2]:.1f} / {c['after'][2]:.1f}"])
        body = markdown_table(["capture", "initial surfels before", "after", "after / before",
                               "prior seconds before / after"], rows) + (
            "\n\nThe prior alone (SOGMM fit and initial surfels, no training; training width 320 px). The "
            "budget is budget_factor (1.5) x the initial surfels.")
        print(body)
        if not args.no_append:
            write_section("surfels/budget-prior", "Surfels by viewing distance: the prior on a far-wall capture",
                          body, headlines=[(f"{r[0]}: initial surfels before -> after", f"{r[1]} -> {r[2]}")
                                           for r in rows])
        return
    runs, reused = {}, []
    t0 = time.perf_counter()
    load0 = os.getloadavg()
    for s in args.scenes:
        if s == "demo":
            label, data = "demo (60 frames 160x120)", demo_scene(OUT / "demo_scene")
        else:
            f, w, h = (int(v) for v in args.far_size.split("x"))
            label, data = f"far-wall ({f} frames {w}x{h})", far_wall_capture(OUT / f"far_{args.far_size}", 0,
                                                                           frames=f, width=w, height=h)
        for v in ("before", "after"):          # interleaved: the same load for both rules
            kept = OUT / f"{label}_{v}.json"
            if args.reuse and kept.exists():
                runs[(label, v)] = json.loads(kept.read_text())
                reused.append(kept.name)
                continue
            print(f"[{label} {v}]", flush=True)
            runs[(label, v)] = run_one(label, data, v)
    t, heads = table(runs)
    note = (f"Default `psimap train` (panoptic phase on) with the rule before (`TrainConfig({', '.join(f'{k}={v!r}' for k, v in BEFORE.items())})`) "
            f"and after (defaults), interleaved per scene in one run of {time.perf_counter() - t0:.0f} s; load average "
            f"{' / '.join(f'{v:.1f}' for v in load0)} at the start on 2 shared cores: the load rose from ~10 to ~22 during the run, so compare CPU seconds (training is single-threaded), not wall. "
            "Surfels on things: within 5 cm of a GT thing surface (benchmarks/surfels.py). Things F1 / Chamfer: the "
            "scene mesh within 3 cm of GT thing surfaces against the seen GT thing surfaces, F1 at 1 cm.")
    if reused:
        note += " Runs reused from an earlier invocation (bench_out/budget): " + ", ".join(reused) + "."
    body = t + "\n\n" + note
    print(body)
    if not args.no_append:
        write_section("surfels/budget", "Surfels by viewing distance, a total cap, geometry steps to a plateau",
                      body, headlines=heads, plot=save_plot(plot(runs), "surfels_budget"))


if __name__ == "__main__":
    main()
