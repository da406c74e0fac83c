"""End-to-end benchmark: where a capture's time goes, from frames to a checked simulation scene,
beside the quality the run reaches (issue #20).

Three generated captures (psimap.data.synthetic, exact ground truth):
  demo      the scene `psimap demo` trains: a 160x120, 60-frame room;
  tabletop  a 640x480, 10-frame hand-held orbit around a table with things on it;
  room      a 320x240, 48-frame room.
and a real one, when ../shared/data holds it (a user's capture: no masks, no ground truth):
  chess     20 of the 7-Scenes chess Kinect frames (640x480, every 7th), labelled by
            `psimap segment` (its seconds are printed, not a stage: a capture with masks skips it).
Each is trained (TrainConfig defaults), exported (`--format all`, MuJoCo settle check) and
evaluated (geometry F1 / Chamfer-L1 and PQ of the checkpoint, object F-score and dynamic things of
the export; for chess only what needs no ground truth: the objects exported, the dynamic ones). Stage times are wall, user and system seconds of this process (and its children),
exclusive: a stage nested in another (completion inside extraction) is counted once, in itself.
  prior       the SOGMM prior (trainer.init_from_prior)
  geometry    the geometry steps and everything else of `train` (frames loaded, density control)
  panoptic    the panoptic steps (trainer.panoptic_phase)
  extraction  gravity, instance meshes, environment, repair, decimation, texture
  completion  shape completion (psimap.completion.complete)
  collision   collision geometry (exporters.collision.collision_geometry)
  writers     meshes/, collision/, MJCF, USD, glTF and their validation
  check       the settle check(s)
The stages are timed by wrapping those functions in this process: nothing in psimap is
instrumented for it, so the same script times any commit's code (--code).

Every run is kept in benchmarks/end_to_end_runs.json by label and capture (a re-run replaces its
own rows), and the RESULTS.md section shows every label side by side: run `--label before` on the
old code and `--label after` on the new one to get the before/after table.

    python benchmarks/end_to_end.py                              # all three, label "current"
    python benchmarks/end_to_end.py --captures tabletop --label after
    python benchmarks/end_to_end.py --label before --code /tmp/main_src   # a `git archive` of main
    python benchmarks/end_to_end.py --report-only                # rebuild the section from the runs
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


def _use_tree(argv: list[str]) -> None:
    """In a --child run with --code TREE: import TREE's psimap, not the installed one. Done before
    anything imports psimap (_results does): once the installed package is in sys.modules, its
    submodules keep loading from the working tree while its native module is no longer found, and
    the child timed this tree's code on the torch renderer instead of TREE's."""
    if "--child" in argv and "--code" in argv:
        tree = Path(argv[argv.index("--code") + 1]).resolve()
        # drop the editable install's finder, put the tree first
        sys.meta_path[:] = [f for f in sys.meta_path if not type(f).__module__.startswith("_editable")]
        sys.path.insert(0, str(tree))


_use_tree(sys.argv)
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import markdown_table, save_plot, write_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RUNS = Path(__file__).with_name("end_to_end_runs.json")
KEY = "end_to_end"
CAPTURES = {
    "demo": dict(layout="room", width=160, height=120, frames=60, seed=0),
    "tabletop": dict(layout="tabletop", width=640, height=480, frames=10, seed=0),
    "room": dict(layout="room", width=320, height=240, frames=48, seed=0),
    "chess": dict(layout="7scenes-chess", width=640, height=480, frames=20, seed=0),
}
CHESS = ROOT.parent / "shared" / "data" / "7scenes-chess"
CHESS_EVERY = 7             # frames 0, 7, ... 133: the sequence's whole sweep of the room
STAGES = ("prior", "geometry", "panoptic", "extraction", "completion", "collision", "writers", "check")
TRAIN_STAGES = ("prior", "geometry", "panoptic")


# --------------------------------------------------------------------------------------------------
# stage clock: exclusive wall / user / system seconds of wrapped functions


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo), or the platform's processor string: rows measured on
    different CPUs compare only within one (a session's machine may differ from the last one's)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.processor() or "unknown CPU"


def _usage() -> tuple[float, float, float]:
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.perf_counter(), s.ru_utime + c.ru_utime, s.ru_stime + c.ru_stime


class StageClock:
    """Accumulates exclusive (wall, user, sys) per stage: entering a stage pauses the one around it."""

    def __init__(self):
        self.times = {s: [0.0, 0.0, 0.0] for s in STAGES}
        self.stack: list[str] = []
        self.mark = _usage()

    def _charge(self):
        now = _usage()
        if self.stack:
            acc = self.times[self.stack[-1]]
            for i in range(3):
                acc[i] += now[i] - self.mark[i]
        self.mark = now

    def wrap(self, stage: str, fn):
        def timed(*a, **kw):
            self._charge()
            self.stack.append(stage)
            try:
                return fn(*a, **kw)
            finally:
                self._charge()
                self.stack.pop()
        return timed

    def patch(self, module, name: str, stage: str):
        setattr(module, name, self.wrap(stage, getattr(module, name)))


def instrument(clock: StageClock) -> None:
    """Wrap the pipeline's stage functions where their callers look them up (module globals, or
    modules imported inside the calling function)."""
    import psimap.completion as completion
    import psimap.exporters.collision as collision
    import psimap.exporters.formats as formats
    import psimap.exporters.pipeline as pipeline
    import psimap.train.trainer as trainer

    clock.patch(trainer, "train", "geometry")
    clock.patch(trainer, "init_from_prior", "prior")
    clock.patch(trainer, "panoptic_phase", "panoptic")
    clock.patch(pipeline, "export_scene", "extraction")
    clock.patch(completion, "complete", "completion")
    clock.patch(collision, "collision_geometry", "collision")
    clock.patch(pipeline, "_write_meshes", "writers")
    clock.patch(pipeline, "settle_check", "check")
    if hasattr(pipeline, "newton_settle_check"):
        clock.patch(pipeline, "newton_settle_check", "check")
    load = formats.load
    formats.load = lambda ref: clock.wrap("writers", load(ref))


# --------------------------------------------------------------------------------------------------
# one capture (run in a fresh process: its own memory, imports and, with --code, its own psimap)


def run_capture(name: str, work: Path) -> dict:
    from psimap.checkpoint import save_checkpoint
    from psimap.data.synthetic import generate
    from psimap.exporters.pipeline import export_scene
    from psimap.metrics.evaluate import evaluate
    from psimap.scene import load_scene
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import train

    spec = CAPTURES[name]
    data, ckpt, export = work / "data", work / "scene.ckpt", work / "export"
    real = name == "chess"
    segment_s = None
    if real:
        segment_s = copy_chess(data, spec["frames"])
    else:
        generate(data, seed=spec["seed"], frames=spec["frames"], width=spec["width"], height=spec["height"],
                 layout=spec["layout"], overwrite=True)
    clock = StageClock()
    instrument(clock)
    import psimap.exporters.pipeline as pipeline
    import psimap.train.trainer as trainer

    t0 = _usage()
    scene = trainer.train(data, TrainConfig(seed=spec["seed"]), progress=False, log=print)
    t1 = _usage()
    save_checkpoint(ckpt, scene.state(), overwrite=True)
    t2 = _usage()
    report = pipeline.export_scene(load_scene(ckpt), export, "all", overwrite=True)
    t3 = _usage()
    m = scene.metrics
    row = {
        "capture": name, **spec,
        "stages": {s: dict(zip(("wall", "user", "sys"), v)) for s, v in clock.times.items()},
        "train": dict(zip(("wall", "user", "sys"), (t1[i] - t0[i] for i in range(3)))),
        "export": dict(zip(("wall", "user", "sys"), (t3[i] - t2[i] for i in range(3)))),
        "panoptic_steps": m.get("panoptic_steps"), "geometry_steps": m.get("steps"),
        "surfels": m.get("surfels"), "queries": m.get("queries_final"), "instances": m.get("instances"),
        "check_passed": bool(report.get("check", {}).get("passed", False)),
    }
    res = evaluate(ckpt, data)
    # the map's fit to its own frames (psimap/metrics/fit.py): the one quality figure a real capture has
    row["fit_depth_cm"] = res["fit"]["depth_mae_cm"]
    row["fit_psnr_db"] = res["fit"]["psnr_db"]
    if real:        # no ground truth: what the export made of the instances
        objs = [o for o in report.get("objects", []) if not o.get("skipped")]
        return row | {"segment_s": segment_s, "f1": None, "chamfer_cm": None, "pq": None, "pq_thing": None,
                      "object_f": None, "found": len(objs), "gt_things": None,
                      "dynamic": sum(1 for o in objs if not o.get("static")), "movable": len(objs)}
    obj = evaluate(export, data)["objects"]["summary"]
    return row | {
        "f1": res["geometry"]["f1"], "chamfer_cm": 100 * res["geometry"]["chamfer_l1"],
        "pq": res["panoptic"]["pq"], "pq_thing": res["panoptic"]["pq_thing"],
        "object_f": obj["mean_fscore_25mm"], "found": obj["n_found"], "gt_things": obj["n_gt_things"],
        "dynamic": obj["n_dynamic"], "movable": obj["n_movable_found"],
    }


def copy_chess(data: Path, frames: int) -> float:
    """`frames` of the shared 7-Scenes chess frames (every CHESS_EVERY-th) copied to `data` and
    labelled by `psimap segment`, as a user without masks would; returns the segmenter's seconds."""
    import shutil

    from psimap.segment.capture import segment_capture

    data.mkdir(parents=True, exist_ok=True)
    shutil.copy2(CHESS / "camera-intrinsics.txt", data)
    for i in range(0, frames * CHESS_EVERY, CHESS_EVERY):
        for p in CHESS.glob(f"frame-{i:06d}.*"):
            shutil.copy2(p, data / p.name)
    t = time.perf_counter()
    # force: a re-run with the same --work labels its own copy again (it stopped at the labels of
    # the run before)
    segment_capture(data, preview=None, progress=False, force=True)
    return time.perf_counter() - t


def child_main(a) -> None:
    import psimap

    if a.code and not Path(psimap.__file__).resolve().is_relative_to(Path(a.code).resolve()):
        sys.exit(f"error: --code {a.code}: psimap was imported from {psimap.__file__}")
    import torch

    torch.manual_seed(0)
    row = run_capture(a.child, Path(a.work))
    Path(a.work, "row.json").write_text(json.dumps(row))


# --------------------------------------------------------------------------------------------------
# report


def load_runs() -> list[dict]:
    return json.loads(RUNS.read_text()) if RUNS.exists() else []


def save_runs(rows: list[dict]) -> None:
    from psimap.io_utils import write_text_atomic

    write_text_atomic(RUNS, json.dumps(rows, indent=1) + "\n")


def panoptic_share(r: dict) -> float:
    train = sum(r["stages"][s]["wall"] for s in TRAIN_STAGES)
    return r["stages"]["panoptic"]["wall"] / train if train else float("nan")


def _num(v, spec: str) -> str:
    """A quality figure, or n/a where the capture has no ground truth for it (the real one)."""
    return "n/a" if v is None else format(v, spec)


def report(rows: list[dict], write: bool = True) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    order = {c: i for i, c in enumerate(CAPTURES)}
    labels = list(dict.fromkeys(r["label"] for r in rows))
    rows = sorted(rows, key=lambda r: (order.get(r["capture"], 9), labels.index(r["label"])))
    header = (["capture", "label"] + [f"{s} s" for s in STAGES]
              + ["train s", "export s", "panoptic share", "panoptic steps", "F1@5cm", "Chamfer cm", "PQ",
                 "object F@2.5cm", "found", "dynamic", "fit: depth cm / PSNR dB"])
    table = []
    for r in rows:
        st = r["stages"]
        table.append([r["capture"], r["label"]] + [f"{st[s]['wall']:.1f}" for s in STAGES]
                     + [f"{sum(st[s]['wall'] for s in TRAIN_STAGES):.1f}",
                        f"{sum(st[s]['wall'] for s in STAGES[3:]):.1f}", f"{100 * panoptic_share(r):.0f} %",
                        r["panoptic_steps"], _num(r["f1"], ".4f"), _num(r["chamfer_cm"], ".2f"), _num(r["pq"], ".3f"),
                        _num(r["object_f"], ".3f"),
                        f"{r['found']}/{r['gt_things']}" if r["gt_things"] is not None else f"{r['found']} exported",
                        f"{r['dynamic']}/{r['movable']}",
                        f"{_num(r.get('fit_depth_cm'), '.2f')} / {_num(r.get('fit_psnr_db'), '.1f')}"])
    cpu_header = ["capture", "label"] + [f"{s} user / sys" for s in STAGES] + ["max sys/user"]
    cpu = []
    for r in rows:
        st = r["stages"]
        ratio = max((st[s]["sys"] / st[s]["user"] for s in STAGES if st[s]["user"] > 0.5), default=0.0)
        cpu.append([r["capture"], r["label"]] + [f"{st[s]['user']:.1f} / {st[s]['sys']:.1f}" for s in STAGES]
                   + [f"{ratio:.2f}"])
    runs = "; ".join(f"{r['capture']} / {r['label']}: {r['measured']}, commit {r['commit']}, load {r['load']}"
                     + (f", {r['cpu']}" if r.get("cpu") else "") for r in rows)

    fig, ax = plt.subplots(figsize=(9, 0.55 * len(rows) + 1.6))
    names = [f"{r['capture']} ({r['label']})" for r in rows]
    left = np.zeros(len(rows))
    colors = plt.get_cmap("tab10")
    for i, s in enumerate(STAGES):
        w = np.array([r["stages"][s]["wall"] for r in rows])
        ax.barh(names, w, left=left, color=colors(i), label=s)
        left += w
    for y, (r, x) in enumerate(zip(rows, left)):
        ax.text(x + 1, y, f"PQ {_num(r['pq'], '.3f')}, obj F {_num(r['object_f'], '.3f')}" if r["pq"] is not None
                else f"{r['found']} objects, {r['dynamic']} dynamic", va="center", fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("wall seconds (2-core CPU)")
    ax.set_xlim(0, left.max() * 1.35 if len(rows) else 1)
    ax.legend(ncol=4, fontsize=7, loc="lower right")
    ax.set_title("psimap end to end: stage times per capture")
    fig.tight_layout()
    if not write:
        print(markdown_table(header, table))
        print(markdown_table(cpu_header, cpu))
        plt.close(fig)
        return
    png = save_plot(fig, KEY)
    body = (markdown_table(header, table)
            + "\n\nCPU seconds per stage (user / system; the issue asks that no stage spend more system than "
              "user time):\n\n" + markdown_table(cpu_header, cpu)
            + "\n\nStage times are exclusive (completion and collision are not in extraction). train s = "
              "prior + geometry + panoptic; panoptic share = panoptic / train. Quality: F1@5cm and "
              "Chamfer-L1 of the checkpoint's mesh, PQ of its rendered labels (psimap eval), object "
              "F-score at 2.5 cm over the ground-truth things and things found / dynamic of the export "
              "(psimap eval EXPORT); fit: the checkpoint's mean depth error against its own frames' depth and "
              "their PSNR (psimap eval's fit, no ground truth needed; n/a in rows from before it existed); "
              "chess (real, no ground truth): objects exported and dynamic, its "
              "labels from `psimap segment` (seconds in the runs file, not a stage). Times compare only between rows measured on one CPU: rows that "
              "name none were measured on the machine of the sessions up to 2026-11-25 (AVX-512, ~1.7x "
              "faster than the AMD EPYC of the rows after it). Runs: " + runs + ".")
    head = []
    for r in rows:
        if r["capture"] == "tabletop" and r["label"] == labels[-1]:
            head.append((f"tabletop 640x480x10 ({r['label']}): train + export; panoptic share",
                         f"{sum(r['stages'][s]['wall'] for s in STAGES):.0f} s; {100 * panoptic_share(r):.0f} %"))
    write_section(KEY, "End to end: stage times and quality per capture", body, headlines=head, plot=png,
                  command="python benchmarks/end_to_end.py [--captures ...] --label LABEL [--code TREE]")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    present = [c for c in CAPTURES if c != "chess" or CHESS.is_dir()]
    ap.add_argument("--captures", default=",".join(present),
                    help="comma-separated: " + ", ".join(CAPTURES) + " (chess needs ../shared/data)")
    ap.add_argument("--label", default="current", help="tag of this run's rows (before / after ...)")
    ap.add_argument("--code", default="", help="a psimap source tree to time instead of the installed one")
    ap.add_argument("--work", default="", help="keep the captures, checkpoints and exports here")
    ap.add_argument("--no-write", action="store_true", help="print the table, write nothing")
    ap.add_argument("--report-only", action="store_true", help="rebuild the section from the kept runs")
    ap.add_argument("--child", default="", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        return child_main(a)
    if a.report_only:
        return report(load_runs())
    names = [c for c in a.captures.split(",") if c]
    bad = [c for c in names if c not in CAPTURES]
    if bad:
        sys.exit(f"error: unknown capture {bad[0]!r} (choose from {', '.join(CAPTURES)})")
    if "chess" in names and not CHESS.is_dir():
        sys.exit(f"error: capture chess needs the shared 7-Scenes frames at {CHESS}")
    base = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="psimap-e2e-"))
    run_all(a, names, base)
    if not a.work:      # its own scratch (~20-50 MB a run); kept when a capture failed, for its log
        import shutil

        shutil.rmtree(base, ignore_errors=True)


def run_all(a, names: list[str], base: Path) -> None:
    """Each capture in its own child process under base; rows kept and the section written."""
    commit = subprocess.run(["git", "-C", str(a.code or ROOT), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip() or "tree " + str(a.code)
    new = []
    for name in names:
        work = base / f"{name}_{a.label}"
        work.mkdir(parents=True, exist_ok=True)
        load = os.getloadavg()[0]
        t = time.perf_counter()
        cmd = [sys.executable, __file__, "--child", name, "--work", str(work)] + (["--code", a.code] if a.code else [])
        with open(work / "log.txt", "w") as log:
            p = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT)
        if p.returncode != 0:
            sys.exit(f"error: capture {name} failed (exit {p.returncode}); see {work / 'log.txt'}")
        row = json.loads((work / "row.json").read_text())
        row.update(label=a.label, commit=commit, measured=time.strftime("%Y-%m-%d %H:%M"),
                   load=f"{load:.1f}-{os.getloadavg()[0]:.1f}", process_s=time.perf_counter() - t,
                   cpu=cpu_model())
        print(f"{name} ({a.label}): train {row['train']['wall']:.1f} s (panoptic "
              f"{row['stages']['panoptic']['wall']:.1f} s), export {row['export']['wall']:.1f} s; PQ "
              f"{_num(row['pq'], '.3f')}, object F {_num(row['object_f'], '.3f')}, F1 {_num(row['f1'], '.4f')}, "
              f"{row['found']} objects, {row['dynamic']} dynamic"
              + (f"; segment {row['segment_s']:.1f} s" if row.get("segment_s") else ""), flush=True)
        new.append(row)
        if not a.no_write:      # kept after every capture: a later failure loses nothing measured
            rows = [r for r in load_runs() if (r["label"], r["capture"]) != (a.label, name)] + [row]
            save_runs(rows)
    report(load_runs() if not a.no_write else new, write=not a.no_write)


if __name__ == "__main__":
    main()
