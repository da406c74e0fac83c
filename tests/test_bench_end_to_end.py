"""benchmarks/end_to_end.py --code TREE times TREE's psimap, not the installed one."""
import subprocess
import sys
from pathlib import Path

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
