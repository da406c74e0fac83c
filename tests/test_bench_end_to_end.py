"""benchmarks/end_to_end.py --code TREE times TREE's psimap, not the installed one."""
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_code_child_imports_the_given_tree_before_anything_imports_psimap(tmp_path):
    # a tree whose psimap announces itself and stops; the installed psimap must not be imported first
    # (it was: the child then timed the working tree's code, without its native module)
    pkg = tmp_path / "tree" / "psimap"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("import sys\nprint('psimap from the given tree')\nsys.exit(7)\n")
    p = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "end_to_end.py"), "--child", "no-such-capture",
                        "--work", str(tmp_path / "work"), "--code", str(tmp_path / "tree")],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 7, p.stdout + p.stderr
    assert "psimap from the given tree" in p.stdout


def test_report_shows_a_real_capture_without_ground_truth_as_n_a(capsys):
    """The real capture (chess) has no ground truth: its quality cells read n/a and its objects
    "N exported", beside a generated capture's numbers (a None formatted as a float raised)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import end_to_end as e2e
    finally:
        sys.path.pop(0)
    stages = {s: {"wall": 1.0 + i, "user": 1.0, "sys": 0.1} for i, s in enumerate(e2e.STAGES)}
    common = {"stages": stages, "panoptic_steps": 240, "commit": "abc", "measured": "now", "load": "1.0-1.0"}
    rows = [dict(common, capture="demo", label="x", f1=0.96, chamfer_cm=1.2, pq=0.81, object_f=0.78,
                 found=14, gt_things=15, dynamic=9, movable=11),
            dict(common, capture="chess", label="x", f1=None, chamfer_cm=None, pq=None, object_f=None,
                 found=31, gt_things=None, dynamic=7, movable=31)]
    e2e.report(rows, write=False)
    out = capsys.readouterr().out
    demo = next(line for line in out.splitlines() if line.startswith("| demo |"))
    chess = next(line for line in out.splitlines() if line.startswith("| chess |"))
    assert "| 0.9600 | 1.20 | 0.810 | 0.780 | 14/15 | 9/11 |" in demo
    assert "| n/a | n/a | n/a | n/a | 31 exported | 7/31 |" in chess
    # train = prior + geometry + panoptic (1 + 2 + 3), export = the other five stages (4 + ... + 8)
    assert "| 6.0 | 30.0 | 50 % |" in chess


def test_without_work_the_benchmark_removes_its_scratch_unless_a_capture_failed(monkeypatch, tmp_path):
    """Without --work the captures, checkpoints and exports go to a temporary folder: removed after
    a run (each left ~20-50 MB in /tmp), kept when a capture failed (its log.txt is named)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import end_to_end as e2e
    finally:
        sys.path.pop(0)
    made = []

    def mkdtemp(prefix=""):
        made.append(tmp_path / f"{prefix}{len(made)}")
        made[-1].mkdir()
        return str(made[-1])

    def run_all(a, names, base):
        (base / f"{names[0]}_{a.label}").mkdir(parents=True)
        if a.label == "broken":
            sys.exit(f"error: capture {names[0]} failed (exit 1); see {base / 'log.txt'}")

    monkeypatch.setattr(e2e.tempfile, "mkdtemp", mkdtemp)
    monkeypatch.setattr(e2e, "run_all", run_all)
    monkeypatch.setattr(sys, "argv", ["end_to_end.py", "--captures", "demo", "--label", "ok"])
    e2e.main()
    assert len(made) == 1 and not made[0].exists()
    monkeypatch.setattr(sys, "argv", ["end_to_end.py", "--captures", "demo", "--label", "broken"])
    with pytest.raises(SystemExit, match="failed"):
        e2e.main()
    assert len(made) == 2 and (made[1] / "demo_broken").is_dir()
    keep = tmp_path / "keep"
    monkeypatch.setattr(sys, "argv", ["end_to_end.py", "--captures", "demo", "--label", "ok", "--work", str(keep)])
    e2e.main()
    assert len(made) == 2 and (keep / "demo_ok").is_dir()


def test_the_real_capture_labels_its_copy_again_when_the_work_folder_is_reused(monkeypatch, tmp_path):
    """`--work` kept from an earlier run: the chess copy is labelled again (force), not stopped by
    the labels of the run before ("already exist(s); pass --force")."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import end_to_end as e2e
    finally:
        sys.path.pop(0)
    import psimap.segment.capture as capture

    src = tmp_path / "chess"
    src.mkdir()
    (src / "camera-intrinsics.txt").write_text("1 0 0\n0 1 0\n0 0 1\n")
    for i in range(0, 2 * e2e.CHESS_EVERY, e2e.CHESS_EVERY):
        (src / f"frame-{i:06d}.pose.txt").write_text("pose")
    calls = []
    monkeypatch.setattr(e2e, "CHESS", src)
    monkeypatch.setattr(capture, "segment_capture", lambda data, **kw: calls.append(kw))
    data = tmp_path / "work" / "data"
    for _ in range(2):
        e2e.copy_chess(data, 2)
    assert len(calls) == 2 and all(kw.get("force") is True for kw in calls)
    assert sorted(p.name for p in data.iterdir()) == ["camera-intrinsics.txt", "frame-000000.pose.txt",
                                                      f"frame-{e2e.CHESS_EVERY:06d}.pose.txt"]
