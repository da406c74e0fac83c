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


# The demo's test configuration and what it scores (measured 2026-11-23, deterministic run to run):
# F1@5cm 0.602, precision 0.969, accuracy 1.74 cm, PQ 0.430, mIoU 0.483, check passed. The floors
# leave ~10 % margin and still fail a map shifted 5 cm before saving (tests/mutations.md M04-M06:
# along x precision 0.865 / accuracy 2.74 cm; up, the hardest direction here, accuracy 2.41 cm).
# 2026-11-28, surfels spaced by viewing distance (TrainConfig.distance_spacing on): F1 0.604,
# precision 0.971, accuracy 1.76 cm, PQ 0.449, mIoU 0.537. The panoptic steps reach the field's
# first query adjustment (PanopticConfig.adjust_start, step 60): at 20 steps every initial per-mask
# query was still there and PQ fell to 0.305 (things 0.000) on the new surfels, a coin toss.
DEMO = ["--seed", "1", "--frames", "8", "--width", "64", "--height", "48", "--iters", "100",
        "--panoptic-iters", "60"]
DEMO_FLOORS = {"f1": 0.55, "precision": 0.93, "pq": 0.38, "miou": 0.44}
DEMO_MAX_ACCURACY_M = 0.020


def test_demo_runs(tmp_path, capsys):
    from psimap.data import load

    out = tmp_path / "demo"
    rc = main(["demo", "--out", str(out), *DEMO])
    text = capsys.readouterr().out
    report = json.loads((out / "export" / "report.json").read_text())
    # this scene passes the simulation check: exit 0 (a failed check would be exit 2)
    assert report["check"]["passed"], report["check"]["failures"]
    assert rc == 0 and "psimap demo: done" in text and "simulation check passed" in text
    # and the export's outcome leads its report: the things found came out as things that move
    assert report["outcome"]["passed"] and report["outcome"]["summary"] in text
    # the whole chain ran: checkpoint, metrics, exported scene with its report
    for stage in ("generate", "preview", "train", "eval", "export"):
        assert f"] {stage}:" in text
    assert (out / "scene.ckpt").exists() and (out / "export" / "scene.xml").exists()
    assert len(report["objects"]) >= 1 and (out / "export" / "scene.usda").exists()
    ev = json.loads((out / "eval.json").read_text())
    g, p = ev["geometry"], ev["panoptic"]
    scores = {"f1": g["f1"], "precision": g["precision"], "pq": p["pq"], "miou": p["miou"]}
    low = {k: v for k, v in scores.items() if v < DEMO_FLOORS[k]}
    assert not low, f"demo scores below their floors {DEMO_FLOORS}: {low}"
    assert g["accuracy"] <= DEMO_MAX_ACCURACY_M, f"accuracy {g['accuracy'] * 100:.2f} cm"
    assert len(load(out / "scene")) == 8
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
