"""The work of one capture, as the three tasks a Dask worker runs: train -> export -> check.

Each task takes the capture, its output folder DIR/<name>/ and the record the previous task returned,
and returns that record with its own stage added. A task never raises for a capture's own failure
(bad data, a PsimapError, a bug in a stage): it records the error and the later stages pass the
record through, so one capture's failure is a value the batch reports, and Dask's retries are left to
what they are for (a worker that died). Everything a task writes lands atomically (psimap.io_utils):
the checkpoint, the export folder, the log, and last of all `done.json`, the completion marker a
re-run reads to skip the capture.

Each task runs with the thread count it is given (torch and the native kernels) and reports its wall
time and its peak memory: the worker process's resident set sampled every SAMPLE_S during the task,
absolute and above what the process held when the task started.
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import re
import socket
import threading
import time
import traceback
from pathlib import Path

from psimap import PsimapError

SAMPLE_S = 0.02             # memory sampling period; a peak shorter than this can be missed
STAGES = ("train", "export", "check")
CKPT, EXPORT, LOG, TRAINED, DONE = "scene.ckpt", "export", "log.txt", "train.json", "done.json"
MARK = "batch"              # psimap.io_utils output kind of DIR and of each DIR/<name>/
# main file of each format, for its read-back check (exporters.formats writers' names)
MAIN_FILE = {"mjcf": "scene.xml", "usd": "scene.usda", "glb": "scene.glb"}


class PeakMemory:
    """Context manager: peak resident set of this process while the block runs (a sampling thread).

    baseline_mb: RSS when the block started; peak_mb: the highest RSS sampled (at least the RSS at the
    end); delta_mb = peak - baseline, what the block added on top of what the process already held.
    """

    def __init__(self, period: float = SAMPLE_S):
        import psutil

        self.proc, self.period = psutil.Process(), period
        self._stop = threading.Event()

    def _rss(self) -> int:
        return self.proc.memory_info().rss

    def _sample(self) -> None:
        while not self._stop.wait(self.period):
            self.peak = max(self.peak, self._rss())

    def __enter__(self):
        self.baseline = self.peak = self._rss()
        self._thread = threading.Thread(target=self._sample, name="psimap-peak-memory", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self._rss())
        return False

    def report(self) -> dict:
        mb = 1 << 20
        return {"peak_mb": round(self.peak / mb, 1), "baseline_mb": round(self.baseline / mb, 1),
                "delta_mb": round((self.peak - self.baseline) / mb, 1)}


def prepare_worker() -> None:
    """Once per worker process, in its main thread, before any task (runner.PrepareWorker).

    pymeshlab (repair, decimation) builds its global plugin state on first use; built in one of Dask's
    task threads, its exit-time destructor frees it from a dead thread's heap arena and glibc aborts
    the worker at shutdown ("malloc_consolidate(): unaligned fastbin chunk detected"; reproduced
    without Dask: an export in a threading.Thread, then exit). Built here, it lives in the main arena.
    """
    import pymeshlab

    pymeshlab.MeshSet()


def new_record(capture) -> dict:
    """The record a capture's first task starts from."""
    return {"name": capture.name, "data": capture.data, "key": capture.key(), "stages": {},
            "error": None, "error_stage": None}


def run_stage(stage: str, work, capture, capdir: str, threads: int, record: dict) -> dict:
    """Run `work(capture, Path(capdir), threads, log) -> dict` as stage `stage` of the capture, timed,
    memory-sampled, with `threads` threads, its output appended to DIR/<name>/log.txt. A failure is
    recorded (error, error_stage), never raised; a record that failed earlier passes through."""
    if record.get("error"):
        return record
    from psimap.threads import limited_threads

    folder = Path(capdir)
    lines: list[str] = [f"== {stage} on {socket.gethostname()} pid {os.getpid()}, {threads} thread(s)"]
    out = io.StringIO()
    started = time.time()
    t0 = time.perf_counter()
    with PeakMemory() as mem:
        try:
            with limited_threads(threads), contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
                result = work(capture, folder, threads, lines.append)
        except PsimapError as e:
            result = None
            record = {**record, "error": str(e), "error_stage": stage}
        except Exception as e:      # a bug in a stage: this capture fails, the batch goes on
            result = None
            record = {**record, "error": f"{type(e).__name__}: {e}", "error_stage": stage}
            lines.append(traceback.format_exc())
    seconds = time.perf_counter() - t0
    lines[1:1] = out.getvalue().splitlines()
    entry = {"seconds": round(seconds, 3), "started": round(started, 3), "ended": round(started + seconds, 3),
             "threads": threads, "worker": f"{socket.gethostname()}:{os.getpid()}",
             **mem.report(), **(result or {})}
    lines.append(f"== {stage}: {'failed: ' + record['error'] if record.get('error') else 'ok'} in "
                 f"{seconds:.1f} s, peak memory {entry['peak_mb']:.0f} MB (+{entry['delta_mb']:.0f} MB)")
    append_log(folder, lines)
    return {**record, "stages": {**record["stages"], stage: entry}}


def append_log(folder: Path, lines) -> None:
    """Add `lines` to DIR/<name>/log.txt (rewritten whole, atomically)."""
    from psimap.io_utils import mark_output_dir, write_text_atomic

    path = folder / LOG
    old = path.read_text() if path.is_file() else ""
    write_text_atomic(path, old + "\n".join(lines) + "\n")
    mark_output_dir(folder, MARK, [LOG])


# what psimap's atomic writers leave behind when a process dies mid-write (io_utils.atomic_path's
# ".<stem>.<random>.tmp<suffix>", atomic_dir's ".<name>.<random>.tmp" / ".old", the marker's temp)
LEFTOVER = re.compile(r"^\.(scene|log|train|done|summary|export)\.[A-Za-z0-9_]+\.(tmp|old)(\.[a-z]+)?$"
                      r"|^\.\.psimap-output\.tmp$")


def clear_leftovers(folder: Path) -> list[str]:
    """Remove the temporary files and folders of writes a killed worker never finished, in a folder
    psimap's batch wrote (its marker says so); returns their names."""
    import shutil

    from psimap.io_utils import read_marker

    meta = read_marker(folder)
    if meta is None or meta["kind"] != MARK:
        return []
    gone = []
    for p in folder.iterdir():
        if LEFTOVER.match(p.name) and p.name not in meta["files"]:
            shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
            gone.append(p.name)
    return gone


def read_json(path: Path) -> dict | None:
    try:
        out = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return out if isinstance(out, dict) else None


# ---- the three stages ---------------------------------------------------------------------------
def _train(capture, folder: Path, threads: int, log) -> dict:
    """Train the capture's map -> DIR/<name>/scene.ckpt (+ train.json). A checkpoint an earlier run
    trained with the same data and training options is kept (a failed export does not cost a
    second training)."""
    from psimap.io_utils import mark_output_dir, write_text_atomic

    key = capture.key("train")
    done = read_json(folder / TRAINED)
    if done is not None and done.get("key") == key and (folder / CKPT).is_file():
        log(f"kept {CKPT} trained by an earlier run (same data and training options)")
        return {**done["result"], "reused": True}
    from psimap.checkpoint import save_checkpoint
    from psimap.data import load
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import train

    opts = capture.options
    cfg = TrainConfig(seed=opts.get("seed", 0), **opts.get("train", {}))
    cfg.threads = threads               # used when the run is not `deterministic` (one thread then)
    seq = load(capture.data)
    log(seq.describe())
    scene = train(seq, cfg, progress=False, log=log)
    save_checkpoint(folder / CKPT, scene.state())
    m = scene.metrics
    result = {"surfels": len(scene), "steps": int(m.get("steps", 0)), "instances": int(m.get("instances", 0)),
              "depth_l1_end": float(m.get("depth_l1_end", float("nan")))}
    write_text_atomic(folder / TRAINED, json.dumps({"key": key, "result": result}, indent=1) + "\n")
    mark_output_dir(folder, MARK, [CKPT, TRAINED])
    return result


def _export(capture, folder: Path, threads: int, log) -> dict:
    """DIR/<name>/scene.ckpt -> DIR/<name>/export/ (psimap export with the capture's options)."""
    from psimap.exporters.physics import parse_static_classes
    from psimap.exporters.pipeline import export_scene
    from psimap.io_utils import mark_output_dir
    from psimap.scene import load_scene

    opts = capture.options
    report = export_scene(load_scene(folder / CKPT), folder / EXPORT, opts["formats"],
                          completion=opts["completion"], check=opts["check"], up=opts["up"],
                          static_classes=parse_static_classes(opts["static_classes"]),
                          min_dynamic=opts["min_dynamic"], seed=opts.get("seed", 0), progress=False)
    mark_output_dir(folder, MARK, _export_files(folder))
    out = report["outcome"]
    log(out["summary"])
    chk = report.get("check")
    return {"objects": len(report["objects"]), "skipped": len(report["skipped"]),
            "things": out["things"], "movable": out["movable"], "dynamic": out["dynamic"],
            "outcome": out["summary"], "outcome_passed": out["passed"],
            "settle": None if chk is None else {"passed": chk["passed"], "failures": chk["failures"],
                                                 "max_drift": chk["max_drift"], "pinned": sorted(chk["pinned"])}}


def _export_files(folder: Path) -> list[str]:
    """The files of DIR/<name>/export/, as its own marker lists them (and the marker)."""
    from psimap.io_utils import MARKER, read_marker

    meta = read_marker(folder / EXPORT) or {"files": []}
    return [f"{EXPORT}/{f}" for f in [*meta["files"], MARKER]]


def _check(capture, folder: Path, threads: int, log) -> dict:
    """Read the export back the way its consumers will: every format's registry validator on its
    main file, the GLB through trimesh, and the MJCF loaded and settled in MuJoCo as written (no
    nudges: the export already applied them)."""
    from psimap.exporters.formats import FORMATS, load

    export = folder / EXPORT
    failures, found = [], {}
    for name in capture.options["formats"]:
        main = export / MAIN_FILE.get(name, "")
        if name not in MAIN_FILE or not main.is_file():
            failures.append(f"{name}: no {MAIN_FILE.get(name, 'main file')} in the export")
            continue
        if FORMATS[name].validator:
            res = load(FORMATS[name].validator)(main)
            found[name] = {"errors": len(res["errors"])}
            failures += [f"{name}: {e}" for e in res["errors"][:3]]
        if name == "glb":
            import trimesh

            found[name] = {"meshes": len(trimesh.load(main, force="scene").geometry)}
        if name == "mjcf" and capture.options["check"]:
            from psimap.sim.check import check_mjcf

            res = check_mjcf(main, resolve=False)
            found[name] = {k: res[k] for k in ("bodies", "min_contact_dist", "max_drift")}
            failures += [f"mjcf: {f}" for f in res["failures"]]
    passed = not failures
    log("read-back check " + ("passed" if passed else "FAILED: " + "; ".join(failures)))
    return {"passed": passed, "failures": failures, **found}


WORK = {"train": _train, "export": _export, "check": _check}


def train_task(capture, capdir: str, threads: int) -> dict:
    """Dask task: stage 1 of a capture."""
    return run_stage("train", WORK["train"], capture, capdir, threads, new_record(capture))


def export_task(capture, capdir: str, threads: int, record: dict) -> dict:
    """Dask task: stage 2 (takes the train task's record)."""
    return run_stage("export", WORK["export"], capture, capdir, threads, record)


def check_task(capture, capdir: str, threads: int, record: dict) -> dict:
    """Dask task: stage 3, then the completion marker done.json when every stage succeeded."""
    record = run_stage("check", WORK["check"], capture, capdir, threads, record)
    if not record.get("error"):
        write_done(Path(capdir), record)
    return record


def write_done(folder: Path, record: dict) -> None:
    """DIR/<name>/done.json: the capture's finished record, written last (a re-run skips it)."""
    from psimap.io_utils import mark_output_dir, write_text_atomic

    write_text_atomic(folder / DONE, json.dumps(record, indent=1, sort_keys=True) + "\n")
    mark_output_dir(folder, MARK, [DONE])
