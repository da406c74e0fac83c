"""Object benchmark (issue #17): are the things of a capture found, detailed and dynamic?

Generated tabletop captures (`psimap generate --layout tabletop`: a table in a room with 4-8 things
on it, large balls and apple-sized ones among them, plus two of the real YCB scans from
../shared/data/ycb when present, with their real masses), 15 % label noise, run the way a user
runs psimap, each step a subprocess timed in wall and CPU seconds:

    psimap train DATA --out scene.ckpt
    psimap export scene.ckpt --format mjcf --out export      (the settle check decides the roles)
    psimap eval export DATA --json                           (object level, docs/metrics.md)
    psimap eval scene.ckpt DATA --json                       (scene geometry and PQ)

Per size: things found, found movable things dynamic, mean object F-score at 1 cm and 2.5 cm
against the complete GT object (missed = 0), scene F1 / Chamfer / PQ, surfels (all and on things),
train / export seconds. A plot of F-score against object size.

    python benchmarks/objects.py                                 # 160x120, 320x240 (3 seeds), 640x480 (1 seed)
    python benchmarks/objects.py --sizes 320x240 --seeds 0 --no-write    # one run, print only
    python benchmarks/objects.py --keep DIR --no-write; ... --from-rows DIR/rows.json   # run elsewhere, write later
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import markdown_table, save_plot, write_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
YCB = ROOT.parent / "shared" / "data" / "ycb"
KEY = "objects"
YCB_NAMES = ("mustard_bottle", "bowl", "cracker_box", "mug", "banana", "power_drill")
PSIMAP = str(Path(sys.executable).with_name("psimap"))
# frames per capture by image size: a phone capture of a tabletop is a few dozen frames; the big
# images get fewer (the real captures: 10-21 frames at 640x480)
FRAMES = {(160, 120): 48, (320, 240): 48, (640, 480): 24}
DEFAULT_RUNS = [((320, 240), (0, 1, 2)), ((160, 120), (0, 1, 2)), ((640, 480), (0,))]   # the targets' size first


def ycb_objects(seed: int, count: int = 2) -> list:
    """(name, mesh, mass_kg) of `count` YCB scans picked by seed, with the mass in their MuJoCo xml;
    [] without ../shared."""
    if not YCB.is_dir():
        return []
    import re

    import trimesh

    names = [YCB_NAMES[(count * seed + k) % len(YCB_NAMES)] for k in range(count)]
    out = []
    for n in names:
        mass = float(re.search(r'<inertial[^>]*\bmass="([0-9.eE+-]+)"', (YCB / f"{n}.xml").read_text()).group(1))
        out.append((n, trimesh.load(YCB / n / "textured.obj", force="mesh", process=False), mass))
    return out


def run(cmd: list[str], log: Path) -> tuple[float, float]:
    """Run a psimap command; (wall s, CPU s of the child). A failure raises with the log's tail."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    with open(log, "ab") as f:
        f.write(("$ " + " ".join(cmd) + "\n").encode())
        f.flush()
        p = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env={**os.environ, "TQDM_DISABLE": "1"})
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if p.returncode not in (0, 2):      # 2: the export's outcome line (too few dynamic) - measured, not fatal
        tail = log.read_text(errors="replace").splitlines()[-8:]
        raise RuntimeError(f"{' '.join(cmd[:2])} exited {p.returncode}:\n" + "\n".join(tail))
    return wall, cpu


def eval_json(args: list[str], log: Path) -> dict:
    out = subprocess.run([PSIMAP, "eval", *args, "--json"], capture_output=True, text=True,
                         env={**os.environ, "TQDM_DISABLE": "1"})
    with open(log, "a") as f:
        f.write(f"$ psimap eval {' '.join(args)} --json\n{out.stderr[-2000:]}\n")
    if out.returncode != 0:
        raise RuntimeError(f"psimap eval {' '.join(args)} exited {out.returncode}: {out.stderr.strip()[-500:]}")
    return json.loads(out.stdout)


def one_capture(work: Path, size: tuple[int, int], seed: int, frames: int, iters: int) -> dict:
    from psimap.data.synthetic import generate

    w, h = size
    data, ckpt, export = work / "data", work / "scene.ckpt", work / "export"
    log = work / "log.txt"
    t0 = time.perf_counter()
    generate(data, seed=seed, frames=frames, width=w, height=h, label_noise=0.15, layout="tabletop", progress=False,
             extra_objects=ycb_objects(seed))
    gen_s = time.perf_counter() - t0
    train = [PSIMAP, "train", str(data), "--out", str(ckpt), "--seed", str(seed)]
    if iters:
        train += ["--iters", str(iters)]
    train_wall, train_cpu = run(train, log)
    export_wall, export_cpu = run([PSIMAP, "export", str(ckpt), "--format", "mjcf", "--out", str(export)], log)
    objects = eval_json([str(export), str(data)], log)["objects"]
    scene = eval_json([str(ckpt), str(data)], log)
    report = json.loads((export / "report.json").read_text())
    surfels_of = {o["name"]: int(o.get("surfels", 0)) for o in report["objects"]}
    surfels_things = sum(surfels_of.values())
    from psimap.scene import load_scene

    n_surfels = int(len(load_scene(ckpt).surfels["means"]))
    return {"size": f"{w}x{h}", "seed": seed, "frames": frames, "generate_s": gen_s,
            "train_wall_s": train_wall, "train_cpu_s": train_cpu, "export_wall_s": export_wall,
            "export_cpu_s": export_cpu, "objects": objects, "geometry": scene.get("geometry", {}),
            "panoptic": scene.get("panoptic", {}), "surfels": n_surfels, "surfels_on_things": surfels_things, "surfels_of": surfels_of}


def summarize(rows: list[dict]) -> dict:
    """Pooled over the captures: every GT thing counts once (psimap eval's own rules per capture)."""
    per = [o for r in rows for o in r["objects"]["per_object"]]
    found = [o for o in per if o["found"]]
    movable = [o for o in found if o["role"] in ("dynamic", "static") and not o["static_class"]]
    mass = [abs(o["mass_error"]) for o in found if o.get("mass_error") is not None]
    mean = lambda xs: float(np.mean(xs)) if len(xs) else float("nan")      # noqa: E731
    return {
        "captures": len(rows), "things": len(per), "found": mean([o["found"] for o in per]),
        "dynamic": mean([o["role"] == "dynamic" for o in movable]), "movable": len(movable),
        "f1cm": mean([o["fscore_10mm"] for o in per]), "f25cm": mean([o["fscore_25mm"] for o in per]),
        "f1cm_things": mean([o["fscore_10mm"] for o in per if not o["static_class"] and o["class"] != "table"]),
        "mass_error": float(np.median(mass)) if mass else float("nan"), "n_mass": len(mass),
        "false_objects": sum(r["objects"]["summary"]["n_false_objects"] for r in rows),
        "scene_f1": mean([r["geometry"].get("f1", np.nan) for r in rows]),
        "chamfer_cm": mean([r["geometry"].get("chamfer_l1", np.nan) for r in rows]) * 100,
        "pq": mean([r["panoptic"].get("pq", np.nan) for r in rows]),
        "train_wall_s": mean([r["train_wall_s"] for r in rows]),
        "train_cpu_s": mean([r["train_cpu_s"] for r in rows]),
        "export_wall_s": mean([r["export_wall_s"] for r in rows]),
        "export_cpu_s": mean([r["export_cpu_s"] for r in rows]),
        "surfels": mean([r["surfels"] for r in rows]),
        "surfels_on_things": mean([r["surfels_on_things"] for r in rows]),
    }


def plot(rows: list[dict]):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    sizes = sorted({r["size"] for r in rows}, key=lambda s: int(s.split("x")[0]))
    for ax, key, label in ((axes[0], "fscore_10mm", "F-score @ 1 cm"), (axes[1], "fscore_25mm", "F-score @ 2.5 cm")):
        for k, size in enumerate(sizes):
            per = [o for r in rows if r["size"] == size for o in r["objects"]["per_object"]]
            x = np.array([o["size_m"] for o in per])
            y = np.array([o[key] for o in per])
            found = np.array([bool(o["found"]) for o in per])
            c = f"C{k}"
            ax.scatter(x[found], y[found], s=18, color=c, label=size)
            ax.scatter(x[~found], y[~found], s=30, color=c, marker="x")
        ax.set_xscale("log")
        ticks = [0.1, 0.2, 0.5, 1.0, 2.0]
        ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("GT object size (bounding-box diagonal, m)")
        ax.set_title(label)
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("F-score vs the complete GT object (x: missed)")
    axes[0].legend(title="capture")
    fig.tight_layout()
    path = save_plot(fig, KEY)
    plt.close(fig)
    return path


def tables(rows: list[dict]) -> tuple[str, list]:
    sizes = sorted({r["size"] for r in rows}, key=lambda s: int(s.split("x")[0]))
    head = ["capture", "seeds", "GT things", "found", "dynamic (of found movable)", "F@1cm", "F@2.5cm",
            "F@1cm w/o furniture", "median mass error", "false objects", "scene F1@5cm", "Chamfer (cm)", "PQ",
            "surfels (on things)", "train s wall (CPU)", "export s wall (CPU)"]
    body, headlines = [], []
    for size in sizes:
        rs = [r for r in rows if r["size"] == size]
        s = summarize(rs)
        body.append([size, ",".join(str(r["seed"]) for r in rs), s["things"], f"{s['found'] * 100:.0f} %",
                     f"{s['dynamic'] * 100:.0f} % of {s['movable']}", f"{s['f1cm']:.3f}", f"{s['f25cm']:.3f}",
                     f"{s['f1cm_things']:.3f}", f"{s['mass_error'] * 100:.0f} % ({s['n_mass']})",
                     s["false_objects"], f"{s['scene_f1']:.4f}", f"{s['chamfer_cm']:.2f}", f"{s['pq']:.3f}",
                     f"{s['surfels']:.0f} ({s['surfels_on_things']:.0f})",
                     f"{s['train_wall_s']:.0f} ({s['train_cpu_s']:.0f})",
                     f"{s['export_wall_s']:.0f} ({s['export_cpu_s']:.0f})"])
        if size == "320x240" or len(sizes) == 1:
            headlines = [(f"found / dynamic, {size}", f"{s['found'] * 100:.0f} % / {s['dynamic'] * 100:.0f} %"),
                         (f"object F@1cm / F@2.5cm, {size}", f"{s['f1cm']:.3f} / {s['f25cm']:.3f}")]
    text = markdown_table(head, body)
    per_head = ["capture", "seed", "GT thing", "size (m)", "found", "F@1cm", "F@2.5cm",
                "observed within 1 cm", "surfels", "role", "why not dynamic", "mass kg (GT)"]
    per_rows = []
    for r in rows:
        for o in r["objects"]["per_object"]:
            mass = "" if o.get("mass_kg") is None else f"{o['mass_kg']:.3f}"
            if o.get("gt_mass_kg") is not None:
                mass += f" ({o['gt_mass_kg']:.3f})"
            obs = o.get("observed_completeness_10mm")
            per_rows.append([r["size"], r["seed"], f"{o['name']} {o['id']}", f"{o['size_m']:.2f}",
                             "yes" if o["found"] else "no", f"{o['fscore_10mm']:.2f}", f"{o['fscore_25mm']:.2f}",
                             "" if obs is None else f"{obs:.2f}", r["surfels_of"].get(o.get("prediction"), ""),
                             o.get("role", ""), (o.get("reason") or "")[:60] if o.get("role") != "dynamic" else "",
                             mass])
    text += "\n\nPer object:\n\n" + markdown_table(per_head, per_rows)
    return text, headlines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", nargs="*", default=None, help="WxH captures (default: 160x120 320x240 640x480)")
    ap.add_argument("--seeds", nargs="*", type=int, default=None, help="seeds (default 0 1 2; 640x480 seed 0)")
    ap.add_argument("--frames", type=int, default=0, help="frames per capture (0 = by size)")
    ap.add_argument("--iters", type=int, default=0, help="training iterations (0 = psimap's default)")
    ap.add_argument("--keep", default="", help="keep the work folders under this folder")
    ap.add_argument("--no-write", action="store_true", help="print only; leave RESULTS.md alone")
    ap.add_argument("--from-rows", default="", help="write the section from a rows.json an earlier run kept "
                                                     "(--keep DIR: DIR/rows.json) instead of running")
    a = ap.parse_args(argv)
    if a.from_rows:
        report(json.loads(Path(a.from_rows).read_text()), write=not a.no_write)
        return 0
    runs = DEFAULT_RUNS
    if a.sizes or a.seeds:
        sizes = [tuple(int(v) for v in s.split("x")) for s in (a.sizes or ["320x240"])]
        runs = [(s, tuple(a.seeds if a.seeds is not None else (0, 1, 2))) for s in sizes]
    rows = []
    base = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="psimap-objects-"))
    for size, seeds in runs:
        for seed in seeds:
            work = base / f"{size[0]}x{size[1]}_seed{seed}"
            work.mkdir(parents=True, exist_ok=True)
            frames = a.frames or FRAMES.get(size, 48)
            r = one_capture(work, size, seed, frames, a.iters)
            s = summarize([r])
            print(f"{r['size']} seed {seed}: found {s['found'] * 100:.0f} %, dynamic {s['dynamic'] * 100:.0f} %, "
                  f"F@1cm {s['f1cm']:.3f}, F@2.5cm {s['f25cm']:.3f}, scene F1 {s['scene_f1']:.4f}, "
                  f"PQ {s['pq']:.3f}, train {r['train_wall_s']:.0f} s, export {r['export_wall_s']:.0f} s",
                  flush=True)
            rows.append(r)
            (base / "rows.json").write_text(json.dumps(rows, indent=1, default=float))
        # each finished size is written at once: a long run stopped later keeps what it measured
        report(rows, write=not a.no_write)
    return 0


def report(rows: list[dict], write: bool) -> None:
    text, headlines = tables(rows)
    if write:
        write_section(KEY, "Objects: found, detailed, dynamic (generated tabletops, 15 % label noise)",
                      text, headlines=headlines, plot=plot(rows))
    else:
        print(text)


if __name__ == "__main__":
    sys.exit(main())
