"""Surfels where the objects are (issue 17 item 2): how many surfels each ground-truth thing gets
after the SOGMM prior and after training, against its surface area, beside the scene-level
geometry (F1@5cm, Chamfer-L1), PQ and training CPU seconds, measured in one run per scene.

A surfel belongs to the GT instance whose surface (gt/mesh.ply, per-face instance ids) is nearest,
when that surface is within ASSIGN_TOLERANCE; instance 0 is stuff (floor, walls, ceiling). Density
is surfels per m^2 of GT surface. "before" trains with `TrainConfig(thing_detail=False)` (the prior
and density control blind to the masks, as before issue 17), "after" with the defaults.

    python benchmarks/surfels.py                                  # seeds 0 1 at 160x120, seed 0 at 320x240
    python benchmarks/surfels.py --scenes 60x160x120:0 --variants after --no-append

Each run is also kept as bench_out/surfels/<scene>_<variant>.json; --reuse takes a run from there
instead of training again (the section says which runs were reused).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import markdown_table, save_plot, write_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench_out" / "surfels"
# Things with less GT surface than this are the "small things" (objects a hand moves, not furniture).
SMALL_THING_AREA = 0.25
# A surfel farther than this from every GT surface is a floater: counted in the total, not per object.
ASSIGN_TOLERANCE = 0.05


def gt_surface_labels(data: Path):
    """gt/mesh.ply as a trimesh, its per-face instance ids [F], per-instance GT area {id: m^2}
    (id 0 = stuff) and {id: name} from gt/instances.json."""
    import trimesh

    mesh = trimesh.load(data / "gt" / "mesh.ply", process=False)
    inst = np.asarray(mesh.metadata["_ply_raw"]["face"]["data"]["instance"]).astype(np.int64)
    area = mesh.area_faces
    areas = {int(i): float(area[inst == i].sum()) for i in np.unique(inst)}
    names = {int(o["id"]): o["name"] for o in json.loads((data / "gt" / "instances.json").read_text())}
    names[0] = "stuff"
    return mesh, inst, areas, names


def surfels_per_instance(means: np.ndarray, gt) -> dict:
    """{instance id: surfels}, with -1 = floaters (no GT surface within ASSIGN_TOLERANCE): each
    surfel takes the instance of the GT triangle closest to it (exact point-to-triangle query)."""
    import open3d as o3d

    mesh, inst, _, _ = gt
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                     o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    q = o3d.core.Tensor(np.asarray(means, np.float32))
    hit = rs.compute_closest_points(q)
    d = np.linalg.norm(hit["points"].numpy() - np.asarray(means, np.float32), axis=1)
    lab = np.where(d <= ASSIGN_TOLERANCE, inst[hit["primitive_ids"].numpy().astype(np.int64)], -1)
    ids, counts = np.unique(lab, return_counts=True)
    return {int(i): int(c) for i, c in zip(ids, counts)}


def run_one(frames: int, width: int, height: int, seed: int, variant: str, iters: int) -> dict:
    """Generate (if needed), train, evaluate one scene with one variant; returns the run record."""
    from psimap.data.synthetic import generate
    from psimap.metrics.evaluate import evaluate
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import train

    scene_tag = f"{frames}x{width}x{height}_s{seed}"
    data = ROOT / "bench_out" / f"surfels_scene_{scene_tag}"
    if not (data / "transforms.json").exists():
        generate(data, seed, frames=frames, width=width, height=height, progress=False)
    gt = gt_surface_labels(data)
    prior = {}

    def snapshot(step, params, elapsed):
        if not prior:                       # after the first step: the prior's surfels, one step on
            prior["means"] = params["means"].detach().numpy().copy()

    kw = {"seed": seed}
    if iters:
        kw["iters"] = iters
    if variant == "before" and "thing_detail" in TrainConfig.__dataclass_fields__:
        kw["thing_detail"] = False
    cfg = TrainConfig(**kw)
    load0 = os.getloadavg()[0]
    scene = train(str(data), cfg, callback=snapshot, log=lambda s: print("   ", s, flush=True))
    ckpt = OUT / f"{scene_tag}_{variant}.ckpt"
    scene.save(ckpt, overwrite=True)
    t = time.perf_counter()
    ev = evaluate(ckpt, data, samples=100_000)
    t_eval = time.perf_counter() - t
    _, _, areas, names = gt
    rec = {"scene": scene_tag, "variant": variant, "frames": frames, "width": width, "height": height,
           "seed": seed, "areas": areas, "names": names,
           "prior": surfels_per_instance(prior["means"], gt),
           "trained": surfels_per_instance(scene.surfels["means"].numpy(), gt),
           "n_prior": int(len(prior["means"])), "n_trained": len(scene), "sogmm_K": scene.metrics["sogmm_K"],
           "budget": scene.metrics["budget"], "train_s": scene.metrics["seconds"],
           "train_cpu_s": scene.metrics["cpu_seconds"], "eval_s": t_eval,
           "f1": ev["geometry"]["f1"], "chamfer_cm": ev["geometry"]["chamfer_l1"] * 100,
           "pq": ev.get("panoptic", {}).get("pq"), "load": [load0, os.getloadavg()[0]]}
    (OUT / f"{scene_tag}_{variant}.json").write_text(json.dumps(rec, indent=1))
    print(json.dumps({k: v for k, v in rec.items() if k not in ("areas", "names", "prior", "trained")}),
          flush=True)
    return rec


def density(rec: dict, key: str) -> tuple[float, float]:
    """Surfels per m^2 of GT surface on things and on stuff."""
    counts, areas = rec[key], {int(k): v for k, v in rec["areas"].items()}
    counts = {int(k): v for k, v in counts.items()}
    thing_area = sum(a for i, a in areas.items() if i > 0)
    things = sum(c for i, c in counts.items() if i > 0)
    return things / max(thing_area, 1e-9), counts.get(0, 0) / max(areas.get(0, 0.0), 1e-9)


def tables(runs: dict) -> tuple[str, str]:
    """Per-thing table (prior and trained surfels, before / after) and the per-scene summary."""
    rows, summary = [], []
    for scene in dict.fromkeys(s for s, _ in runs):
        b, a = runs.get((scene, "before")), runs.get((scene, "after"))
        ref = a or b
        areas = {int(k): v for k, v in ref["areas"].items()}
        names = {int(k): v for k, v in ref["names"].items()}

        def n(rec, key, i):
            return "-" if rec is None else int({int(k): v for k, v in rec[key].items()}.get(i, 0))

        for i in sorted(k for k in areas if k > 0):
            rows.append([scene, i, names.get(i, "?"), f"{areas[i] * 1e4:.0f}", n(b, "prior", i), n(a, "prior", i),
                         n(b, "trained", i), n(a, "trained", i)])
        for v, rec in (("before", b), ("after", a)):
            if rec is None:
                continue
            dt_p, ds_p = density(rec, "prior")
            dt, ds = density(rec, "trained")
            things = sum(c for k, c in rec["trained"].items() if int(k) > 0)
            small = sum(c for k, c in rec["trained"].items() if 0 < areas.get(int(k), 1e9) < SMALL_THING_AREA)
            summary.append([scene, v, rec["sogmm_K"], rec["n_prior"], rec["n_trained"], things, small,
                            f"{dt_p:.0f} / {ds_p:.0f}", f"{dt:.0f} / {ds:.0f}", f"{rec['f1']:.4f}",
                            f"{rec['chamfer_cm']:.3f}", "-" if rec["pq"] is None else f"{rec['pq']:.3f}",
                            f"{rec['train_cpu_s']:.1f}", f"{rec['train_s']:.1f}",
                            f"{rec['load'][0]:.1f} / {rec['load'][1]:.1f}"])
    t1 = markdown_table(["scene", "GT id", "thing", "GT area (cm²)", "prior before", "prior after",
                         "trained before", "trained after"], rows)
    t2 = markdown_table(["scene", "variant", "SOGMM K", "surfels prior", "surfels trained", "on things",
                         f"on small things (< {SMALL_THING_AREA} m²)",
                         "density prior things / stuff (1/m²)", "density trained things / stuff (1/m²)",
                         "F1@5cm", "Chamfer-L1 (cm)", "PQ", "train CPU (s)", "train wall (s)",
                         "load start / end"], summary)
    return t1, t2


def plot(runs: dict):
    """Trained surfels per thing against its GT area, before and after (log-log)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.5))
    for k, v in enumerate(("before", "after")):
        xs, ys = [], []
        for (scene, var), rec in runs.items():
            if var != v:
                continue
            counts = {int(i): c for i, c in rec["trained"].items()}
            for i, a in rec["areas"].items():
                if int(i) > 0:
                    xs.append(a * 1e4)
                    ys.append(max(counts.get(int(i), 0), 0.8))
        ax.scatter(xs, ys, color=f"C{k}", marker="os"[k], label=v, alpha=0.75)
    ax.set(xscale="log", yscale="log", xlabel="GT surface area of the thing (cm²)",
           ylabel="trained surfels on it", title="surfels per thing vs its area")
    ax.axhline(30, color="grey", lw=0.8, ls=":")
    ax.legend()
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    return fig


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["60x160x120:0", "60x160x120:1", "60x320x240:0"],
                    help="FRAMESxWxH:SEED per scene")
    ap.add_argument("--variants", nargs="+", default=["before", "after"], choices=["before", "after"])
    ap.add_argument("--iters", type=int, default=0, help="training iterations (0 = config default)")
    ap.add_argument("--reuse", action="store_true", help="take runs already in bench_out/surfels")
    ap.add_argument("--no-append", action="store_true", help="print tables only")
    args = ap.parse_args(argv)
    OUT.mkdir(parents=True, exist_ok=True)
    runs, reused = {}, []
    for spec in args.scenes:
        size, seed = spec.split(":")
        f, w, h = (int(x) for x in size.split("x"))
        for v in args.variants:
            path = OUT / f"{f}x{w}x{h}_s{seed}_{v}.json"
            if args.reuse and path.exists():
                runs[(f"{f}x{w}x{h}_s{seed}", v)] = json.loads(path.read_text())
                reused.append(path.name)
                continue
            print(f"[{spec} {v}]", flush=True)
            runs[(f"{f}x{w}x{h}_s{seed}", v)] = run_one(f, w, h, int(seed), v, args.iters)
    t1, t2 = tables(runs)
    notes = ["Surfels are assigned to the GT instance of the nearest GT surface point within "
             f"{ASSIGN_TOLERANCE * 100:.0f} cm ('prior' = the initial surfels, after one step; 'trained' = "
             "after density control and the final prune). Density = surfels / GT surface area (things: all "
             "GT instances; stuff: floor, walls, ceiling). Default `psimap train` settings (panoptic phase on); "
             "F1 / Chamfer / PQ from `psimap eval`. Training is single-threaded, so CPU seconds compare "
             "across load; wall seconds do not (2 shared cores)."]
    if reused:
        notes.append("Runs reused from earlier invocations (bench_out/surfels): " + ", ".join(reused) + ".")
    body = t2 + "\n\n" + t1 + "\n\n" + "\n\n".join(notes)
    if args.no_append:
        print(body)
        return
    heads = []
    for (scene, v), rec in runs.items():
        if v == "after" and (scene, "before") in runs:
            b = runs[(scene, "before")]
            th = [sum(c for k, c in r["trained"].items() if int(k) > 0) for r in (b, rec)]
            heads.append((f"surfels on things / total, {scene} (before -> after)",
                          f"{th[0]} / {b['n_trained']} -> {th[1]} / {rec['n_trained']}"))
    write_section("surfels", "Surfels where the objects are: per-thing allocation before / after", body,
                  headlines=heads, plot=save_plot(plot(runs), "surfels"))


if __name__ == "__main__":
    main()
