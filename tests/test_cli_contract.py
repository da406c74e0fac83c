"""The command-line contract, end to end through the installed `psimap` console script (the entry
point pip wrote into the venv, not `psimap.cli.main` in-process): every subcommand and every
documented option at least once on tiny data, the exit codes (0 ok, 1 error, 2 failed check or
usage), one-line errors and --debug tracebacks.

`CALLS` is the whole list of invocations; `test_every_documented_option_is_exercised` checks it
against the options dataclasses, so a new option fails the suite until a call here uses it. The
calls run once per module, two at a time (independent ones in parallel on CI's 2 cores).
"""
from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

PSIMAP = Path(sys.executable).parent / "psimap"

# {name: argv}; "{tmp}" is the module's temp folder. Stage 1 needs nothing, stage 2 the demo's
# scene and checkpoint.
CALLS1 = {
    "version": ["--version"],
    "no_command": [],
    "help": ["--help"],
    "generate": ["generate", "{tmp}/gen", "--seed", "4", "--frames", "3", "--width", "40", "--height", "30",
                 "--objects", "5", "--noise", "0.3", "--lidar", "--pose-noise", "0.01", "--layout", "room"],
    # the smallest demo whose export passes its check and its outcome (tests/test_cli_generate_demo.py)
    "demo": ["demo", "--out", "{tmp}/demo", "--seed", "1", "--frames", "8", "--width", "64", "--height", "48",
             "--iters", "100", "--panoptic-iters", "60"],
    "bad_format": ["export", "{tmp}/none.ckpt", "--format", "fbx"],
    # psimap batch's runs are in tests/test_batch.py; here its options reach the command's first check
    "batch_missing": ["batch", "{tmp}/missing.toml", "--out", "{tmp}/b", "--scheduler", "tcp://127.0.0.1:9",
                      "--workers", "1", "--threads-per-worker", "1"],
    # a tiny 7-Scenes capture and a COCO panoptic file the fixture writes (tests/test_import_masks.py)
    "import_masks": ["import-masks", "{tmp}/chess", "--masks", "{tmp}/m2f/panoptic_val.json", "--format",
                     "coco-panoptic", "--classes", "{tmp}/map.json", "--unmapped", "void", "--min-area", "2",
                     "--min-score", "0.5", "--resize", "--force"],
}
CALLS2 = {
    # resumed from the demo on a copy of its scene without pseudo-labels (no 400-step panoptic phase)
    "train": ["train", "{tmp}/nolabels", "--out", "{tmp}/resumed.ckpt", "--resume", "{tmp}/demo/scene.ckpt",
              "--iters", "5", "--seed", "3", "--no-prior", "--fast", "--no-lidar"],
    "mesh": ["mesh", "{tmp}/demo/scene.ckpt", "--out", "{tmp}/mesh.ply", "--voxel", "0.04"],
    "export_all": ["export", "{tmp}/demo/scene.ckpt", "--format", "all", "--out", "{tmp}/e_all",
                   "--completion", "auto", "--densities", "{tmp}/densities.json", "--static-classes", "none",
                   "--no-pin-unstable", "--up", "+z", "--check-engine", "mujoco"],
    "export_usd": ["export", "{tmp}/demo/scene.ckpt", "--format", "usd", "--out", "{tmp}/e_usd",
                   "--completion", "none", "--no-check", "--dynamic-all", "--min-dynamic", "0"],
    "export_glb": ["export", "{tmp}/demo/scene.ckpt", "--format", "glb", "--out", "{tmp}/e_glb",
                   "--completion", "none", "--no-check"],
    "eval": ["eval", "{tmp}/demo/scene.ckpt", "{tmp}/demo/scene", "--json", "--threshold", "0.1",
             "--samples", "20000", "--seed", "3", "--plot", "{tmp}/eval.png"],
    "labels": ["labels", "{tmp}/demo/scene.ckpt", "{tmp}/demo/scene", "--out", "{tmp}/labels", "--topk", "2"],
    "bad_ckpt": ["mesh", "{tmp}/bad.ckpt", "--out", "{tmp}/bad.ply"],
    "bad_ckpt_debug": ["export", "{tmp}/bad.ckpt", "--out", "{tmp}/e_bad", "--debug"],
    # the generated scene has its own labels: --force replaces them with the segmenter's
    "segment": ["segment", "{tmp}/gen", "--force", "--up", "+z", "--every", "2", "--preview", "{tmp}/seg.png",
                "--noise-k", "3", "--min-wall-area", "0.8", "--min-support-area", "0.15", "--colour-edge", "0.5",
                "--min-pixels", "4"],
    # reads the demo's export only (tests/test_newton_check.py: Newton, and the folder byte for byte)
    "check": ["check", "{tmp}/demo/export", "--engine", "mujoco", "--json", "--duration", "0.5",
              "--max-drift", "0.02"],
}
DENSITY = {"cabinet": 321.0}
# Options a dedicated test file exercises through the console script instead (flag -> where).
ELSEWHERE = {"overwrite": "tests/test_output_safety.py", "objects": "tests/test_metrics_objects.py",
             "no_preview": "tests/test_segment.py", "images": "tests/test_import_masks.py"}


def _run(argv, tmp: Path) -> subprocess.CompletedProcess:
    args = [a.format(tmp=tmp) for a in argv]
    return subprocess.run([str(PSIMAP), *args], capture_output=True, text=True, timeout=600, cwd=tmp)


@pytest.fixture(scope="module")
def ran(tmp_path_factory) -> tuple[dict, Path]:
    if not PSIMAP.exists():
        pytest.fail(f"the console script {PSIMAP} is missing: install psimap (make install)")
    tmp = tmp_path_factory.mktemp("cli")
    (tmp / "bad.ckpt").write_bytes(b"PK\x03\x04 truncated")
    (tmp / "densities.json").write_text(json.dumps(DENSITY))
    _masks_input(tmp)
    res = {}
    with ThreadPoolExecutor(2) as pool:
        res.update(zip(CALLS1, pool.map(lambda a: _run(a, tmp), CALLS1.values())))
        assert res["demo"].returncode == 0, res["demo"].stderr[-2000:]
        _strip_labels(tmp / "demo" / "scene", tmp / "nolabels")
        res.update(zip(CALLS2, pool.map(lambda a: _run(a, tmp), CALLS2.values())))
    return res, tmp


def _strip_labels(src: Path, dst: Path) -> None:
    """A copy of a scene folder whose frames list no pseudo-labels (the format allows that)."""
    import shutil

    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("semantic", "instance"))
    meta = json.loads((dst / "transforms.json").read_text())
    for f in meta["frames"]:
        f.pop("semantic_file_path", None)
        f.pop("instance_file_path", None)
    (dst / "transforms.json").write_text(json.dumps(meta))


def _masks_input(tmp: Path) -> None:
    from test_import_masks import MAPPING, _panoptic, _scene, _seven_scenes

    _seven_scenes(tmp / "chess", n=3)
    _panoptic(tmp / "m2f", {"frame-000000": _scene(0), "frame-000001": _scene(1)})
    (tmp / "map.json").write_text(json.dumps(MAPPING))


def ok(res, name) -> subprocess.CompletedProcess:
    r = res[name]
    assert r.returncode == 0, f"{name}: rc {r.returncode}\n{r.stderr[-3000:]}"
    return r


def test_every_documented_option_is_exercised():
    from psimap.cli import COMMANDS

    used: dict[str, set] = {}
    for argv in [*CALLS1.values(), *CALLS2.values()]:
        cmd = next((a for a in argv if a in COMMANDS), None)
        used.setdefault(cmd, set()).update(a for a in argv if a.startswith("--"))
    missing = []
    for name, (cls, _, _) in COMMANDS.items():
        assert name in used, f"no call runs `psimap {name}`"
        for f in dataclasses.fields(cls):
            flag = "--" + f.name.replace("_", "-")
            if not f.metadata.get("positional") and flag not in used[name] and f.name not in ELSEWHERE:
                missing.append(f"psimap {name} {flag}")
    assert not missing, f"options no call exercises: {missing}"
    assert {"--version", "--help", "--debug"} <= set().union(*used.values())


def test_version_help_and_no_command(ran):
    from psimap import __version__
    from psimap.cli import COMMANDS

    res, _ = ran
    assert ok(res, "version").stdout == f"psimap {__version__}\n"
    r = res["no_command"]
    assert r.returncode == 2 and r.stdout.startswith("usage: psimap") and r.stderr == ""
    text = ok(res, "help").stdout
    for name in COMMANDS:
        assert name in r.stdout and name in text, name
    r = res["bad_format"]                       # argparse: usage error, exit 2, nothing written
    assert r.returncode == 2 and "invalid choice: 'fbx'" in r.stderr


def test_generate_options(ran):
    from psimap.data import load
    from psimap.data.scene_format import read_gt
    from psimap.data.synthetic import generate

    res, tmp = ran
    out = ok(res, "generate").stdout
    assert "3 frames 40x30" in out and ", 5 objects (" in out
    errors = [int(w) for w in out.split("pseudo-label errors:")[1].split("over")[0].split() if w.isdigit()]
    assert sum(errors) > 0                                   # --noise 0.3 corrupted some labels
    seq = load(tmp / "gen")
    assert len(seq) == 3 and seq[0].rgb.shape == (30, 40, 3) and seq[0].lidar is not None
    assert len(read_gt(tmp / "gen").instances) == 5
    # --pose-noise: the written poses are the true ones (same seed, no noise) perturbed by ~1 cm
    generate(tmp / "gen_exact", seed=4, frames=3, width=40, height=30, n_objects=5, label_noise=0.3)
    exact = load(tmp / "gen_exact")
    shift = max(float(np.linalg.norm(a.c2w[:3, 3] - b.c2w[:3, 3])) for a, b in zip(seq, exact))
    assert 0.002 < shift < 0.08
    assert np.array_equal(seq[0].depth, exact[0].depth)         # only the poses were perturbed


def test_demo_through_the_console_script(ran):
    res, tmp = ran
    out = ok(res, "demo").stdout
    assert "psimap demo: done" in out and "simulation check passed" in out
    for f in ("scene.ckpt", "eval.json", "scene_preview.png", "export/scene.xml", "export/scene.usda",
              "export/scene.glb", "export/report.json"):
        assert (tmp / "demo" / f).is_file(), f
    assert "8 frames 64x48" in out


def test_train_resume_no_prior_fast(ran):
    import psimap

    res, tmp = ran
    out = ok(res, "train").stdout
    before = psimap.load(tmp / "demo" / "scene.ckpt")
    after = psimap.load(tmp / "resumed.ckpt")
    steps = int(before.metrics["steps"]) + 5                   # --resume continues the count
    assert f"wrote {tmp / 'resumed.ckpt'}: {len(after)} surfels, {steps} steps" in out
    assert after.metrics["steps"] == steps and len(after) == len(before)
    assert after.config["use_prior"] is False
    assert after.config["lidar"] is False
    assert after.config["seed"] == 3 and after.config["iters"] == 5
    assert "resuming from" in res["train"].stderr and "SOGMM" not in res["train"].stderr


def test_mesh_voxel(ran):
    import trimesh

    res, tmp = ran
    out = ok(res, "mesh").stdout
    assert "(voxel 4.00 cm)" in out
    mesh = trimesh.load(tmp / "mesh.ply")
    assert len(mesh.faces) > 100 and f"{len(mesh.faces)} faces" in out


def test_export_formats_and_options(ran):
    res, tmp = ran
    # all formats, completion, the density table, no static classes, no pinning: exit 0 or 2 as the check says
    r = res["export_all"]
    rep = json.loads((tmp / "e_all" / "report.json").read_text())
    assert r.returncode == (0 if rep["check"]["passed"] else 2), r.stderr
    assert {"scene.xml", "scene.usda", "scene.glb"} <= {p.name for p in (tmp / "e_all").iterdir()}
    assert rep["format"] == ["glb", "mjcf", "usd"] and rep["check"]["pinned"] == {}
    cab = [o for o in rep["objects"] if o["class"] == "cabinet"]
    assert cab and all(not o["static"] for o in cab)           # --static-classes none
    assert all(o["physics"]["density_kg_m3"] == DENSITY["cabinet"] for o in cab)
    assert "completion_method" in cab[0] and f"exported {len(rep['objects'])} object(s)" in r.stdout
    # one format each, no check
    for name, fmt, scene in (("export_usd", "usd", "scene.usda"), ("export_glb", "glb", "scene.glb")):
        out = ok(res, name).stdout
        rep = json.loads((tmp / f"e_{fmt}" / "report.json").read_text())
        files = {p.name for p in (tmp / f"e_{fmt}").iterdir()}
        assert scene in files and not ({"scene.xml", "scene.usda", "scene.glb"} - {scene}) & files, name
        assert "check" not in rep and "simulation check" not in out and rep["format"] == [fmt]
        assert all(not o["completed"] for o in rep["objects"])   # --completion none
    rep = json.loads((tmp / "e_usd" / "report.json").read_text())
    assert rep["objects"] and all(not o["static"] for o in rep["objects"])   # --dynamic-all
    rep = json.loads((tmp / "e_glb" / "report.json").read_text())
    assert all(o["static"] for o in rep["objects"] if o["class"] == "cabinet")  # the default rule


def test_eval_options(ran):
    res, tmp = ran
    g = json.loads(ok(res, "eval").stdout)["geometry"]
    demo = json.loads((tmp / "demo" / "eval.json").read_text())["geometry"]
    assert g["threshold"] == 0.1 and g["f1"] >= demo["f1"]    # a looser threshold than the demo's 5 cm
    assert g["n_pred_points"] <= 20000 and g["n_gt_points"] <= 20000
    # a checkpoint with labels gets both plots, named after --plot
    assert (tmp / "eval_geometry.png").stat().st_size > 10_000 and (tmp / "eval_panoptic.png").is_file()


def test_labels_topk(ran):
    from psimap.cli import main

    res, tmp = ran
    ok(res, "labels")
    meta = json.loads((tmp / "labels" / "panoptic.json").read_text())
    assert len(meta["annotations"]) == 8 and len(list((tmp / "labels").rglob("*.png"))) == 8   # one per frame
    assert main(["eval", str(tmp / "labels"), str(tmp / "demo" / "scene"), "--json"]) == 0


def test_errors_are_one_line_and_debug_shows_the_traceback(ran):
    res, tmp = ran
    r = res["bad_ckpt"]
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr == f"psimap mesh: error: {tmp / 'bad.ckpt'}: truncated or corrupt checkpoint (RuntimeError)\n"
    r = res["bad_ckpt_debug"]
    assert r.returncode == 1 and "Traceback (most recent call last)" in r.stderr
    assert "psimap.PsimapError: " in r.stderr and "truncated or corrupt checkpoint" in r.stderr
    assert not (tmp / "bad.ply").exists() and not (tmp / "e_bad").exists()


def test_segment_options(ran):
    res, tmp = ran
    out = ok(res, "segment").stdout
    assert "labelled 2 of 3 frames" in out and "up [0.0, 0.0, 1.0] (given)" in out
    meta = json.loads((tmp / "gen" / "labels.json").read_text())
    assert sorted(meta["frames"]) == ["frame_00000", "frame_00002"]
    assert (tmp / "seg.png").stat().st_size > 5_000 and not (tmp / "gen" / "segment_preview.png").exists()


def test_import_masks_options(ran):
    res, tmp = ran
    out = ok(res, "import_masks").stdout
    assert "2 of 3 frames labelled; 1 without masks (no labels): frame-000002" in out
    assert "classes: table (thing), floor (stuff)" in out          # cups unmapped -> void, person -> null
    meta = json.loads((tmp / "chess" / "labels.json").read_text())
    assert sorted(meta["frames"]) == ["frame-000000", "frame-000001"]


def test_batch_missing_manifest_is_one_line(ran):
    res, tmp = ran
    r = res["batch_missing"]
    assert r.returncode == 1 and r.stderr.strip().count("\n") == 0
    assert "psimap batch: error: manifest" in r.stderr and "no such file" in r.stderr
    assert not (tmp / "b").exists()


def test_check_reads_the_demo_export(ran):
    res, tmp = ran
    rep = json.loads(ok(res, "check").stdout)
    assert list(rep) == ["mujoco"] and rep["mujoco"]["passed"] and rep["mujoco"]["nudges"] == {}
    assert rep["mujoco"]["duration_s"] == pytest.approx(0.5)
    exported = json.loads((tmp / "demo" / "export" / "report.json").read_text())
    assert rep["mujoco"]["max_drift"] <= 0.02
    assert rep["mujoco"]["bodies"] == sum(not o["static"] for o in exported["objects"])
    assert rep["mujoco"]["static_bodies"] == exported["check"]["static_bodies"]
    # --check-engine mujoco (the default): no Newton report
    assert "check_newton" not in json.loads((tmp / "e_all" / "report.json").read_text())


@pytest.mark.parametrize("value", ["-y", "-x", "-0.1,0.9,0"])
def test_up_takes_a_value_that_starts_with_a_dash(value, tmp_path, capsys):
    # argparse reads "-y" as an option ("expected one argument"); the CLI joins it to --up, so the
    # run gets as far as the missing checkpoint and fails there, with one line
    from psimap.cli import main

    rc = main(["export", str(tmp_path / "missing.ckpt"), "--up", value, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 1 and "expected one argument" not in err and "missing.ckpt" in err, err
    assert not (tmp_path / "o").exists()
