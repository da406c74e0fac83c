"""`psimap batch`: many captures through train -> export -> check on a Dask cluster (docs/batch.md).

Three tiny generated captures (4 frames of 48x36, 30 + 5 training steps), one with a broken
transforms.json: two finish, one is reported with its error and the batch goes on; a second run
runs only the failed one; a worker killed in the middle of an export has its task run again and the
capture still finishes, leaving nothing half-written. The manifest and the CLI's errors are checked
without a cluster.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import threading
import time
from pathlib import Path

import pytest

from distributed import WorkerPlugin

from psimap import PsimapError
from psimap.cli import main

TRAIN = {"iters": 30, "panoptic_iters": 5}
MANIFEST = """
[defaults]
formats = ["mjcf"]
train = {{ iters = {iters}, panoptic_iters = {panoptic_iters} }}

[[captures]]
path = "caps/cap*"

[[captures]]
path = "caps/other"
name = "renamed"
formats = ["mjcf", "glb"]
up = "+z"
""".format(**TRAIN)


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> Path:
    """caps/cap0, caps/cap1 (its transforms.json cut short: bad data), caps/other; batch.toml."""
    from psimap.data.synthetic import generate

    root = tmp_path_factory.mktemp("batch")
    for name, seed in (("cap0", 1), ("cap1", 2), ("other", 3)):
        generate(root / "caps" / name, seed=seed, frames=4, width=48, height=36)
    t = root / "caps" / "cap1" / "transforms.json"
    t.write_text(t.read_text()[:200])
    (root / "batch.toml").write_text(MANIFEST)
    return root


def _summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


# ---- a whole batch on a local cluster, then the resumed run ----------------------------------------
@pytest.fixture(scope="module")
def first_run(captures):
    out = captures / "out"
    t0 = time.perf_counter()
    rc = main(["batch", str(captures / "batch.toml"), "--out", str(out), "--workers", "2",
               "--threads-per-worker", "1"])
    return rc, out, time.perf_counter() - t0


def test_a_failed_capture_is_reported_and_the_others_finish(first_run, captures):
    import mujoco

    rc, out, _ = first_run
    s = _summary(out)
    caps = s["captures"]
    assert rc == 1 and set(caps) == {"cap0", "cap1", "renamed"}
    assert s["counts"] == {"done": 2, "failed": 1, "pending": 0, "skipped": 0}
    bad = caps["cap1"]
    assert bad["status"] == "failed" and bad["error_stage"] == "train"
    assert "transforms.json is not valid JSON" in bad["error"]
    assert not (out / "cap1" / "done.json").exists() and not (out / "cap1" / "scene.ckpt").exists()
    assert "is not valid JSON" in (out / "cap1" / "log.txt").read_text()
    for name in ("cap0", "renamed"):
        e = caps[name]
        assert e["status"] == "done" and e["error"] is None, e
        assert set(e["stage_seconds"]) == {"train", "export", "check"}
        assert all(v > 0 for v in e["stage_seconds"].values())
        assert e["check"]["passed"] and e["settle"]["passed"]
        assert e["things"] >= 1 and 0 <= e["dynamic"] <= e["movable"] <= e["things"]
        # each task stated its threads and its memory. What a tiny capture's training adds is
        # small and may come from heap an earlier task in the same worker freed (1.5-2.7 MB
        # measured, sometimes above 5): only its sign is certain here; PeakMemory's own test
        # checks that a short-lived allocation is seen
        assert e["threads"] == {"train": 1, "export": 1, "check": 1}
        assert e["stage_peak_memory_mb"]["train"]["above_start"] >= 0
        assert e["peak_memory_mb"] >= max(v["peak"] for v in e["stage_peak_memory_mb"].values()) > 100
        done = json.loads((out / name / "done.json").read_text())
        assert done["key"] and not done["error"]
        mujoco.MjModel.from_xml_path(str(out / name / "export" / "scene.xml"))
    # the per-capture options reached the export; the defaults the others
    assert (out / "renamed" / "export" / "scene.glb").is_file()
    assert not (out / "cap0" / "export" / "scene.glb").exists()
    report = json.loads((out / "renamed" / "export" / "report.json").read_text())
    assert report["gravity"]["source"] == "given" and report["format"] == ["glb", "mjcf"]
    # the manifest's training options reached the training (steps counts the geometry schedule)
    trained = json.loads((out / "cap0" / "train.json").read_text())["result"]
    assert trained["steps"] == TRAIN["iters"] and trained["surfels"] > 100


def test_tasks_never_share_a_worker_thread(first_run):
    """2 workers x 1 thread, each task asking for the worker's whole 'threads' resource: at most one
    task at a time on a worker."""
    _, out, _ = first_run
    by_worker: dict[str, list] = {}
    for e in _summary(out)["captures"].values():
        for t in e["tasks"].values():
            by_worker.setdefault(t["worker"], []).append((t["started"], t["ended"]))
    assert 1 <= len(by_worker) <= 2
    for spans in by_worker.values():
        spans.sort()
        assert all(b[0] >= a[1] - 1e-3 for a, b in zip(spans, spans[1:])), spans


def test_a_second_run_runs_only_the_failed_capture(first_run, captures):
    _, out, _ = first_run
    before = {n: (out / n / "scene.ckpt").stat().st_mtime_ns for n in ("cap0", "renamed")}
    rc = main(["batch", str(captures / "batch.toml"), "--out", str(out), "--workers", "1"])
    s = _summary(out)
    assert rc == 1 and s["counts"] == {"done": 2, "failed": 1, "pending": 0, "skipped": 2}
    assert s["captures"]["cap1"]["ran"] and not s["captures"]["cap0"]["ran"]
    assert {n: (out / n / "scene.ckpt").stat().st_mtime_ns for n in before} == before
    # the failed capture really ran again: its log holds two attempts
    assert (out / "cap1" / "log.txt").read_text().count("== train on") == 2


# ---- a worker killed mid-task ----------------------------------------------------------------------
class KillOnce(WorkerPlugin):
    """Dask WorkerPlugin: SIGKILL the worker process `delay` s after it starts a task whose key begins
    with `prefix`, the first time only (a marker file remembers it across the worker's restart)."""

    name = "kill-once"

    def __init__(self, prefix: str, marker: str, delay: float):
        self.prefix, self.marker, self.delay = prefix, marker, delay

    def transition(self, key, start, finish, **kw):
        if finish == "executing" and str(key).startswith(self.prefix) and not os.path.exists(self.marker):
            Path(self.marker).write_text(str(os.getpid()))
            threading.Timer(self.delay, os.kill, (os.getpid(), signal.SIGKILL)).start()


def test_a_killed_worker_is_replaced_and_the_task_runs_again(first_run, captures, tmp_path):
    import cloudpickle
    import dask
    import sys
    from distributed import Client, LocalCluster

    from psimap.batch import runner
    from psimap.batch.manifest import read_manifest

    _, first, _ = first_run
    out = tmp_path / "out"
    # the checkpoint of the first run, kept (same data and training options): only export and check run
    shutil.copytree(first / "cap0", out / "cap0", ignore=shutil.ignore_patterns("done.json", "export"))
    meta = json.loads((out / "cap0" / ".psimap-output").read_text())
    meta["files"] = [f for f in meta["files"] if f in ("log.txt", "scene.ckpt", "train.json")]
    (out / "cap0" / ".psimap-output").write_text(json.dumps(meta))
    (out / ".psimap-output").write_text(json.dumps({"kind": "batch", "psimap": "0", "files": []}))
    cap0 = [c for c in read_manifest(captures / "batch.toml") if c.name == "cap0"]
    marker = tmp_path / "killed"
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    with dask.config.set({"distributed.scheduler.allowed-failures": runner.ALLOWED_FAILURES}):
        with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, resources={"threads": 1},
                          dashboard_address=None, silence_logs=50) as cluster, Client(cluster) as client:
            client.register_plugin(KillOnce("export-cap0", str(marker), delay=1.5))
            s = runner.run_batch(cap0, out, scheduler=cluster.scheduler_address, log=lambda m: None)
    assert marker.exists(), "the plugin never killed the worker"
    e = s["captures"]["cap0"]
    assert e["status"] == "done" and e["check"]["passed"], e
    # the checkpoint of the first run was kept: no retraining (asserted by outcome, not by a time)
    assert e["trained_earlier"]
    # the export ran again on the new worker process, not on the one that was killed
    assert e["tasks"]["export"]["worker"].split(":")[-1] != marker.read_text()
    # nothing half-written: no temporary export folder or file left by the killed write
    assert sorted(p.name for p in (out / "cap0").iterdir()) == [
        ".psimap-output", "done.json", "export", "log.txt", "scene.ckpt", "train.json"]
    assert (out / "cap0" / "export" / "scene.xml").is_file()


def test_a_task_whose_worker_keeps_dying_is_reported_and_the_batch_goes_on(captures, tmp_path):
    """allowed-failures 0 on the test's scheduler: the first death is final. The capture is reported
    with the stage that died, the batch returns its summary, and no completion marker is written."""
    import cloudpickle
    import dask
    import sys
    from distributed import Client, LocalCluster

    from psimap.batch import runner
    from psimap.batch.manifest import read_manifest

    out = tmp_path / "out"
    other = [c for c in read_manifest(captures / "batch.toml") if c.name == "renamed"]
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, resources={"threads": 1},
                          dashboard_address=None, silence_logs=50) as cluster, Client(cluster) as client:
            client.register_plugin(KillOnce("train-renamed", str(tmp_path / "killed"), delay=0.3))
            s = runner.run_batch(other, out, scheduler=cluster.scheduler_address, log=lambda m: None)
    e = s["captures"]["renamed"]
    assert e["status"] == "failed" and e["error_stage"] == "train", e
    assert "the worker running train died 1 time(s)" in e["error"]
    assert json.loads((out / "summary.json").read_text())["counts"]["failed"] == 1
    assert not (out / "renamed" / "done.json").exists()
    assert "died 1 time(s)" in (out / "renamed" / "log.txt").read_text()


# ---- without a cluster: manifest, CLI errors, memory, leftovers --------------------------------------
def test_manifest_toml_json_globs_and_options(captures):
    from psimap.batch.manifest import parse_manifest, read_manifest

    caps = read_manifest(captures / "batch.toml")
    assert [c.name for c in caps] == ["cap0", "cap1", "renamed"]
    assert caps[0].options["formats"] == ["mjcf"] and caps[2].options["formats"] == ["mjcf", "glb"]
    assert caps[2].options["up"] == "+z" and caps[0].options["up"] == "auto"
    assert caps[0].options["train"] == TRAIN and caps[0].options["completion"] == "auto"
    doc = {"defaults": {"train": {"iters": 7}}, "captures": [{"path": "caps/cap0", "train": {"seed": 3}}]}
    (captures / "m.json").write_text(json.dumps(doc))
    (c,) = read_manifest(captures / "m.json")
    assert c.options["train"] == {"iters": 7, "seed": 3}
    # the key follows what decides the result: training options change both keys, export options one
    other = parse_manifest({**doc, "defaults": {"train": {"iters": 8}}}, base=captures)[0]
    assert other.key("train") != c.key("train") and other.key() != c.key()
    up = parse_manifest({"captures": [{"path": "caps/cap0", "up": "-y"}]}, base=captures)[0]
    plain = parse_manifest({"captures": [{"path": "caps/cap0"}]}, base=captures)[0]
    assert up.key("train") == plain.key("train") and up.key() != plain.key()


@pytest.mark.parametrize("doc, message", [
    ({"captures": []}, "no captures"),
    ({"captures": [{"path": "caps/none_*"}]}, "matches no folder"),
    ({"captures": [{"path": "caps/missing"}]}, "is not a folder"),
    ({"captures": [{"path": "caps/cap0", "colour": 1}]}, "unknown option 'colour'"),
    ({"captures": [{"path": "caps/cap0", "formats": ["fbx"]}]}, "formats"),
    ({"captures": [{"path": "caps/cap0", "train": {"iters": "many"}}]}, "train.iters = 'many' should be of type int"),
    ({"captures": [{"path": "caps/cap0", "train": {"speed": 1}}]}, "train.speed is no training option"),
    ({"captures": [{"path": "caps/cap0", "min_dynamic": 2}]}, "min_dynamic must lie in 0..1"),
    ({"captures": [{"path": "caps/cap0"}, {"path": "caps/cap0"}]}, "two captures named 'cap0'"),
    ({"captures": [{"path": "caps/cap*", "name": "x"}]}, "'name' names one capture"),
    ({"captures": [{"path": "caps/cap0", "name": "../x"}]}, "not a plain folder name"),
    ({"defaults": {"up": "sideways"}, "captures": [{"path": "caps/cap0"}]}, "up"),
])
def test_bad_manifests_are_one_clear_error(captures, doc, message):
    from psimap.batch.manifest import parse_manifest

    with pytest.raises(PsimapError, match=None) as e:
        parse_manifest(doc, base=captures)
    assert message in str(e.value) and "\n" not in str(e.value)


def test_cli_errors_are_one_line_and_write_nothing(captures, tmp_path, capsys, monkeypatch):
    from psimap.batch import runner

    out = tmp_path / "out"
    (tmp_path / "bad.toml").write_text("[[captures]\npath = 'x'\n")
    monkeypatch.setattr(runner, "CONNECT_TIMEOUT", "1s")
    cases = {
        "no such file": ["batch", str(tmp_path / "missing.toml"), "--out", str(out)],
        "not valid TOML": ["batch", str(tmp_path / "bad.toml"), "--out", str(out)],
        "cannot reach a Dask scheduler": ["batch", str(captures / "batch.toml"), "--out", str(out),
                                          "--scheduler", "tcp://127.0.0.1:9"],
        "--workers sizes a local cluster": ["batch", str(captures / "batch.toml"), "--out", str(out),
                                            "--scheduler", "tcp://127.0.0.1:9", "--workers", "2"],
    }
    for message, argv in cases.items():
        t0 = time.perf_counter()
        rc = main(argv)
        err = capsys.readouterr().err.strip()
        assert rc == 1 and message in err and len(err.splitlines()) == 1, (message, err)
        assert time.perf_counter() - t0 < 8
    assert not out.exists() or not any(p.name != ".psimap-output" for p in out.iterdir())


def test_a_folder_psimap_did_not_write_is_refused(captures, tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    rc = main(["batch", str(captures / "batch.toml"), "--out", str(out)])
    assert rc == 1 and "did not write" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_peak_memory_sees_a_short_lived_allocation():
    import numpy as np

    from psimap.batch.stages import PeakMemory

    with PeakMemory() as m:
        a = np.ones(200 * 2**20 // 8)        # 200 MB, touched
        time.sleep(0.1)
        del a
    r = m.report()
    assert r["delta_mb"] >= 180, r
    assert r["peak_mb"] >= r["baseline_mb"] + 180


def test_leftovers_of_a_killed_write_are_cleared_and_nothing_else(tmp_path):
    from psimap.batch.stages import clear_leftovers
    from psimap.io_utils import mark_output_dir

    d = tmp_path / "cap"
    mark_output_dir(d, "batch", ["log.txt"])
    for name in (".scene.ab12_x9z.tmp.ckpt", ".log.k2j3h4g5.tmp.txt", "..psimap-output.tmp"):
        (d / name).write_text("partial")
    (d / ".export.q1w2e3r4.tmp").mkdir()
    (d / ".export.q1w2e3r4.tmp" / "scene.xml").write_text("partial")
    (d / ".scene.notes").write_text("not a leftover")
    assert sorted(clear_leftovers(d)) == sorted(["..psimap-output.tmp", ".export.q1w2e3r4.tmp",
                                                 ".log.k2j3h4g5.tmp.txt", ".scene.ab12_x9z.tmp.ckpt"])
    assert sorted(p.name for p in d.iterdir()) == [".psimap-output", ".scene.notes"]
    # a folder without psimap's batch marker is never cleared
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / ".scene.ab12_x9z.tmp.ckpt").write_text("x")
    assert clear_leftovers(tmp_path / "other") == []
