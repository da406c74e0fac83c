"""examples/ run as a user runs them (a subprocess, its own MuJoCo GL choice)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_real_capture_example_end_to_end(tmp_path):
    """A capture without masks of its own (the generated scene's are overridden) -> segment -> train ->
    export -> summary table and a MuJoCo render; the user's folder is copied, never written."""
    from psimap.data.synthetic import generate

    data = tmp_path / "capture"
    generate(data, seed=1, frames=8, width=64, height=48, progress=False)
    before = sorted(p.relative_to(data) for p in data.rglob("*"))
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, str(ROOT / "examples" / "real_capture.py"), "--data", str(data),
                        "--out", str(out), "--quick"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(p.relative_to(data) for p in data.rglob("*")) == before      # the input is untouched
    labels = json.loads((out / "capture" / "labels.json").read_text())
    assert labels["source"].startswith("psimap segment") and len(labels["frames"]) == 8
    report = json.loads((out / "export" / "report.json").read_text())
    names = [o["name"] for o in report["objects"] if not o.get("skipped")]
    assert names, "no object exported"
    table = r.stdout[r.stdout.index("object  "):]
    assert all(n in table for n in names)                      # one row per exported object
    assert "static world:" in table and "MuJoCo check: passed" in table
    if "no preview" not in r.stdout:                           # offscreen GL (EGL) present
        import numpy as np
        from PIL import Image

        img = np.asarray(Image.open(out / "preview.png").convert("L"))
        assert img.shape == (480, 640) and len(np.unique(img)) > 50                     # not a blank frame
