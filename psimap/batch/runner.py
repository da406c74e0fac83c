"""`run_batch`: every capture of a manifest through train -> export -> check on a Dask cluster.

A local cluster (worker processes on this machine) by default, or any running scheduler. Each capture
is three chained tasks (psimap.batch.stages); the client only submits them, follows their progress and
writes DIR/summary.json (atomically, each time a capture finishes). Tasks read and write files: with a
remote scheduler, DIR and the captures must be on a filesystem the workers see at the same paths.

Threads: every task asks for `threads` units of the worker resource "threads", and a local worker
offers exactly its thread count, so a worker runs one task at a time and the tasks never hold more
threads than the cluster has cores. Faults: a worker that dies mid-task (killed, crashed, out of
memory) has its task run again on another worker, up to `distributed.scheduler.allowed-failures`
times (Dask's `retries` only count errors a task raises, and a task here raises none for a capture's
own failure: a PsimapError or a bug gives the same result on a second try).
"""
from __future__ import annotations

import json
import os
import time
import uuid
from pathlib import Path

from psimap import PsimapError, __version__
from psimap.batch.stages import DONE, MARK, STAGES, append_log, read_json

SUMMARY = "summary.json"
ALLOWED_FAILURES = 2            # a task whose worker died is run again on up to this many more workers
CONNECT_TIMEOUT = "10s"         # --scheduler: how long to try reaching it
WORKER_WAIT_S = 60              # --scheduler: how long to wait for its first worker


def check_batch_dir(out, captures) -> Path:
    """The resolved DIR if psimap may write the batch there, else PsimapError (one line): DIR is new,
    empty or an earlier batch output; each DIR/<name>/ new, empty or psimap's (psimap.io_utils rules:
    nothing psimap did not write is ever replaced). Runs before any work."""
    from psimap.io_utils import OVERWRITE_HINT, check_file_in_marked_dir, check_output_dir, read_marker, resolve_output_dir

    p = resolve_output_dir(out, what="--out")
    if p.is_dir() and any(p.iterdir()):
        meta = read_marker(p)
        if meta is None or meta["kind"] != MARK:
            what = "a folder psimap did not write" if meta is None else f"a psimap {meta['kind']} output"
            raise PsimapError(f"--out {out} is {what}; choose another folder (nothing of yours is deleted)")
        check_file_in_marked_dir(p, SUMMARY, what="--out")
    from psimap.batch.stages import clear_leftovers

    clear_leftovers(p)
    for c in captures:
        clear_leftovers(p / c.name)
        try:
            check_output_dir(p / c.name, MARK, what="--out")
        except PsimapError as e:
            raise PsimapError(f"{e} (capture {c.name}); {OVERWRITE_HINT.split(' or ')[0]}") from None
    return p


def worker_plugin():
    """A Dask WorkerPlugin running stages.prepare_worker on every worker (restarted ones too)."""
    from distributed import WorkerPlugin

    class PrepareWorker(WorkerPlugin):
        name = "psimap-prepare-worker"

        def setup(self, worker):
            from psimap.batch.stages import prepare_worker

            prepare_worker()

    return PrepareWorker()


def local_cluster(workers: int, threads: int):
    """A LocalCluster of `workers` processes x `threads` threads, each offering resource threads=N,
    with BLAS / OpenMP pools of the same size, and killed-worker retries set (ALLOWED_FAILURES)."""
    import dask
    from distributed import LocalCluster

    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
    environ.update({k: str(threads) for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")})
    with dask.config.set({"distributed.scheduler.allowed-failures": ALLOWED_FAILURES,
                          "distributed.nanny.pre-spawn-environ": environ}):
        return LocalCluster(n_workers=workers, threads_per_worker=threads, processes=True,
                            resources={"threads": threads}, dashboard_address=None, silence_logs=40)


def connect(scheduler: str, workers: int, threads: int, log):
    """(client, cluster or None, threads per task, resources per task, where it runs (words))."""
    from distributed import Client

    if scheduler:
        if workers:
            raise PsimapError("--workers sizes a local cluster; a --scheduler's cluster has its own workers")
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT)
        except (OSError, TimeoutError, ValueError, TypeError) as e:
            raise PsimapError(f"--scheduler {scheduler}: cannot reach a Dask scheduler there "
                              f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else 'no answer'})") from None
        try:
            client.wait_for_workers(1, timeout=WORKER_WAIT_S)
        except TimeoutError:
            client.close()
            raise PsimapError(f"--scheduler {scheduler}: no worker joined it within {WORKER_WAIT_S} s "
                              f"(start one: dask worker {scheduler})") from None
        infos = client.scheduler_info(n_workers=-1)["workers"].values()
        if infos and all(w.get("resources", {}).get("threads", 0) >= threads for w in infos):
            return client, None, threads, {"threads": threads}, f"scheduler {scheduler}"
        # workers started without `--resources threads=N`: one task per worker thread, one thread each
        log(f"psimap batch: the workers of {scheduler} offer no 'threads' resource (start them with "
            f"`dask worker {scheduler} --nthreads N --resources threads=N`): one task per worker thread, "
            f"one thread per task")
        return client, None, 1, None, f"scheduler {scheduler}"
    cores = os.cpu_count() or 1
    if threads < 1:
        raise PsimapError(f"--threads-per-worker must be >= 1, got {threads}")
    if workers < 0:
        raise PsimapError(f"--workers must be >= 0, got {workers}")
    n = workers or max(1, cores // threads)
    cluster = local_cluster(n, threads)
    return Client(cluster), cluster, threads, {"threads": threads}, f"local cluster, {n} worker(s) x {threads} thread(s)"


def run_batch(captures, out, *, scheduler: str = "", workers: int = 0, threads_per_worker: int = 1,
              progress: bool = False, log=print) -> dict:
    """Train, export and check every capture (psimap.batch.manifest.Capture) into `out`/<name>/;
    returns the summary (also written to `out`/summary.json). Captures finished by an earlier run
    with the same data and options (their done.json) are skipped; failed ones run again."""
    from psimap.io_utils import mark_output_dir

    root = check_batch_dir(out, captures)
    mark_output_dir(root, MARK)
    t0 = time.perf_counter()
    summary = {"psimap": __version__, "out": str(root), "runs_on": "nothing to run", "wall_s": 0.0, "captures": {}}
    todo = []
    for c in captures:
        done = read_json(root / c.name / DONE)
        if done is not None and done.get("key") == c.key() and not done.get("error"):
            summary["captures"][c.name] = capture_entry(done, ran=False)
        else:
            if done is not None:        # another run's result (other options): not this run's
                (root / c.name / DONE).unlink()
            todo.append(c)
            summary["captures"][c.name] = {"status": "pending", "data": c.data, "ran": True}
    if todo:
        client, cluster, threads, resources, where = connect(scheduler, workers, threads_per_worker, log)
        summary["runs_on"] = where
        client.register_plugin(worker_plugin())
        log(f"psimap batch: {len(todo)} capture(s) to run on a {where}"
            + (f"; {len(captures) - len(todo)} done earlier, skipped" if len(todo) < len(captures) else ""))
        try:
            _run(client, todo, root, threads, resources, summary, progress, log, t0)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    summary["wall_s"] = round(time.perf_counter() - t0, 3)
    write_summary(root, summary)
    return summary


def _run(client, todo, root: Path, threads: int, resources, summary: dict, progress: bool, log, t0: float) -> None:
    from distributed import as_completed
    from tqdm import tqdm

    from psimap.batch import stages as S

    tasks = {"train": S.train_task, "export": S.export_task, "check": S.check_task}
    token = uuid.uuid4().hex[:8]
    which = {}          # future key -> (capture, stage)
    futures = []
    for c in todo:
        capdir = root / c.name
        capdir.mkdir(parents=True, exist_ok=True)
        prev = None
        for stage in STAGES:
            args = (c, str(capdir), threads) + (() if prev is None else (prev,))
            prev = client.submit(tasks[stage], *args, key=f"{stage}-{c.name}-{token}", pure=False,
                                 resources=resources)
            which[prev.key] = (c, stage)
            futures.append(prev)
    failed_early: set[str] = set()
    with tqdm(total=len(futures), desc="psimap batch", unit="task", disable=not progress) as bar:
        for fut in as_completed(futures):
            c, stage = which[fut.key]
            bar.update(1)
            if fut.status == "error":
                if c.name not in failed_early:      # later stages of the same capture err with it
                    failed_early.add(c.name)
                    where, err = _task_error(fut.exception(), stage)
                    record = {**S.new_record(c), "error": err, "error_stage": where}
                    append_log(root / c.name, [f"== {where}: failed: {err}"])
                    _finish(summary, root, c, record, bar, log, t0)
                continue
            if stage == "check":
                _finish(summary, root, c, fut.result(), bar, log, t0)
            else:
                bar.set_postfix_str(f"{c.name}: {stage} done")


def _finish(summary: dict, root: Path, c, record: dict, bar, log, t0: float) -> None:
    entry = summary["captures"][c.name] = capture_entry(record, ran=True)
    summary["wall_s"] = round(time.perf_counter() - t0, 3)
    write_summary(root, summary)
    if bar.disable:
        log(describe(c.name, entry))
    else:
        bar.write(describe(c.name, entry))


def _task_error(exc, stage: str) -> tuple[str, str]:
    """(stage, message) of a task that erred: a worker died under it too often (KilledWorker: the
    capture's later stages err with the same exception, so the stage is the dead task's), or an error
    that escaped the stage."""
    from distributed import KilledWorker

    if isinstance(exc, KilledWorker):
        died = str(exc.task).split("-", 1)[0]
        stage = died if died in STAGES else stage
        return stage, (f"the worker running {stage} died {exc.allowed_failures + 1} time(s) (killed, crashed or "
                       f"out of memory; last on {exc.last_worker.address})")
    return stage, f"{type(exc).__name__}: {exc}"


def capture_entry(record: dict, *, ran: bool) -> dict:
    """A capture's line of summary.json from its stages' record."""
    st = record.get("stages", {})
    ex, chk = st.get("export", {}), st.get("check", {})
    ok = not record.get("error")
    return {
        "status": "done" if ok else "failed", "ran": ran, "data": record["data"],
        "seconds": round(sum(s.get("seconds", 0.0) for s in st.values()), 3),
        "stage_seconds": {k: s.get("seconds") for k, s in st.items()},
        "peak_memory_mb": max((s.get("peak_mb", 0.0) for s in st.values()), default=None),
        "stage_peak_memory_mb": {k: {"peak": s.get("peak_mb"), "above_start": s.get("delta_mb")} for k, s in st.items()},
        "threads": {k: s.get("threads") for k, s in st.items()},
        "tasks": {k: {f: s.get(f) for f in ("worker", "started", "ended")} for k, s in st.items()},
        "things": ex.get("things"), "movable": ex.get("movable"), "dynamic": ex.get("dynamic"),
        "outcome": ex.get("outcome"), "outcome_passed": ex.get("outcome_passed"),
        "settle": ex.get("settle"),
        "check": None if not chk or not ok else {k: chk[k] for k in ("passed", "failures")},
        "error": record.get("error"), "error_stage": record.get("error_stage"),
        "trained_earlier": bool(st.get("train", {}).get("reused")),
    }


def describe(name: str, e: dict) -> str:
    """One line per finished capture."""
    if e["status"] == "failed":
        return f"  {name}: FAILED in {e['error_stage']}: {e['error']}"
    times = ", ".join(f"{k} {v:.1f}" for k, v in e["stage_seconds"].items())
    check = "check passed" if e["check"]["passed"] else "check FAILED: " + "; ".join(e["check"]["failures"][:2])
    return (f"  {name}: done in {e['seconds']:.1f} s ({times}); {e['outcome']}; {check}; "
            f"peak memory {e['peak_memory_mb']:.0f} MB")


def write_summary(root: Path, summary: dict) -> None:
    from psimap.io_utils import mark_output_dir, write_text_atomic

    caps = summary["captures"].values()
    summary["counts"] = {s: sum(1 for e in caps if e["status"] == s) for s in ("done", "failed", "pending")}
    summary["counts"]["skipped"] = sum(1 for e in caps if e["status"] == "done" and not e["ran"])
    write_text_atomic(root / SUMMARY, json.dumps(summary, indent=1, sort_keys=True) + "\n")
    mark_output_dir(root, MARK, [SUMMARY])
