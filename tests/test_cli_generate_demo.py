"""`psimap generate` and `psimap demo` through the real command line entry point."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from psimap.cli import main

SMALL = ["--frames", "4", "--width", "48", "--height", "36"]


def test_generate_writes_loadable_scene(tmp_path, capsys):
    from psimap.data import load
    from psimap.data.scene_format import read_gt

    out = tmp_path / "gen"
    rc = main(["generate", str(out), "--seed", "4", "--objects", "6", "--lidar", "--pose-noise", "0.005", *SMALL])
    assert rc == 0
    text = capsys.readouterr().out
    assert f"wrote {out}" in text and " s (" in text and "4 frames 48x36" in text
    seq = load(out)
    assert len(seq) == 4 and seq[0].rgb.shape == (36, 48, 3)
    assert seq[0].lidar is not None
    assert (seq[0].depth > 0).mean() > 0.5
    gt = read_gt(out)
    assert 3 <= len(gt.instances) <= 6 and len(gt.objects) == len(gt.instances)
    meta = json.loads((out / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV" and meta["w"] == 48
    assert [c["id"] for c in meta["classes"]] == list(range(1, len(meta["classes"]) + 1))
    assert np.isfinite(np.asarray(meta["frames"][0]["transform_matrix"])).all()


def test_generate_bad_input_is_one_line(tmp_path, capsys):
    rc = main(["generate", str(tmp_path / "x"), "--frames", "0"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and "frames must be >= 1" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "x").exists()
    rc = main(["generate", str(tmp_path / "x"), "--noise", "3", *SMALL])
    assert rc == 1 and "label noise" in capsys.readouterr().err


def test_demo_runs(tmp_path, capsys):
    from psimap.data import load

    out = tmp_path / "demo"
    rc = main(["demo", "--out", str(out), "--seed", "1", *SMALL, "--iters", "20", "--panoptic-iters", "20"])
    text = capsys.readouterr().out
    # the exit code follows the simulation check and the export's outcome (too few things dynamic:
    # exit 2, outputs still written, the reason said)
    rep = json.loads((out / "export" / "report.json").read_text())
    passed = rep["check"]["passed"] and rep["outcome"]["passed"]
    assert rc == (0 if passed else 2)
    assert rep["outcome"]["summary"] in text
    assert "generate" in text and ("psimap demo: done" in text if passed else
                                   ("simulation check FAILED" in text and "psimap demo: simulation" in text)
                                   or "psimap demo: too few things dynamic" in text)
    # the whole chain ran: checkpoint, metrics, exported scene with its report
    for stage in ("train", "eval", "export"):
        assert f"] {stage}:" in text
    assert (out / "scene.ckpt").exists()
    ev = json.loads((out / "eval.json").read_text())
    assert 0.0 <= ev["geometry"]["f1"] <= 1.0 and 0.0 <= ev["panoptic"]["pq"] <= 1.0
    report = json.loads((out / "export" / "report.json").read_text())
    assert (out / "export" / "scene.xml").exists() and "check" in report
    assert len(load(out / "scene")) == 4
    from PIL import Image

    img = Image.open(out / "scene_preview.png")
    assert img.size[0] > 500 and np.asarray(img).std() > 10
    # An existing file where the folder should go is a clean error.
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["demo", "--out", str(f), *SMALL]) == 1


def test_help_is_instant_and_lists_generate():
    # The generator's heavy imports (open3d, trimesh, manifold3d) must not load for --help.
    code = ("import sys; from psimap.cli import main\n"
            "try:\n    main(['generate', '--help'])\nexcept SystemExit:\n    pass\n"
            "heavy = [m for m in ('open3d', 'trimesh', 'manifold3d', 'torch') if m in sys.modules]\n"
            "print('HEAVY', heavy)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert "--seed" in r.stdout and "--lidar" in r.stdout
    assert "HEAVY []" in r.stdout
