"""Mutation check (`make mutate`, not part of CI): does each mutation in tests/mutations.md still
fail the tests named for it?

    .venv/bin/python tests/mutate.py              # every entry
    .venv/bin/python tests/mutate.py M01 M07      # some entries
    .venv/bin/python tests/mutate.py --list       # what is listed, and whether each snippet is found

For each entry the original snippet is replaced by the mutated one in a *copy* of the repository,
the named tests run against that copy, and the outcome is one of
  caught        the tests failed (what we want)
  SURVIVED      the tests passed: a blind spot, write the assertion that catches it
  n/a           the original snippet is not in the file (or not exactly once): the code moved,
                update the entry
  ERROR         the tests could not run (bad test id, or they already fail without the mutation)

Why a copy and not the working tree: the tree is never touched, so an interrupted run leaves no
mutated file behind, and someone running the suite meanwhile sees the real code. The copy is the
git-visible tree (tracked + untracked-not-ignored files) laid out the way the wheel installs it
(pyproject's [tool.scikit-build.wheel.packages]: exporters/ -> psimap/exporters, ...) plus the built
native module. The venv's editable install redirects `import psimap` to the working tree through a
meta-path finder that runs before sys.path; a sitecustomize.py on PYTHONPATH removes that finder, so
the tests - and every subprocess they start (`psimap` console script, `python -c`) - import the copy.
../shared is linked next to the copy so tests that read the shared data still run.
A mutation of the native kernels (psimap/render/csrc) is built with CMake in the copy first; one that
does not compile counts as caught. A mutation of the CUDA kernel (psimap/render/csrc_cuda) is
**skipped** without a CUDA device (its tests would skip, and read as SURVIVED); with one, the
copy's tests build the mutated kernel themselves (torch's extension builder).

Exit status: 0 every mutation caught, 1 any SURVIVED or ERROR, 2 none survived but some n/a.
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIST = ROOT / "tests" / "mutations.md"
TIMEOUT_S = 900

SITECUSTOMIZE = '''\
"""Written by tests/mutate.py: import psimap from the mutated copy, not the editable install."""
import sys

sys.meta_path[:] = [f for f in sys.meta_path if not type(f).__module__.startswith("_editable_")]
'''


@dataclass
class Mutation:
    id: str
    title: str
    file: str
    tests: list[str]
    original: str
    mutated: str
    date: str = ""
    extra: dict = field(default_factory=dict)


def parse(text: str) -> list[Mutation]:
    """Entries of mutations.md: a `### ID title` heading, `- file:` / `- tests:` / `- date:` lines
    and two fenced blocks (original, then mutated; the mutated one may be empty)."""
    out = []
    for chunk in re.split(r"^### ", text, flags=re.M)[1:]:
        head, _, body = chunk.partition("\n")
        mid, _, title = head.strip().partition(" ")

        def item(name):
            m = re.search(rf"^- {name}:(.*)$", body, flags=re.M)
            return m.group(1).strip() if m else ""

        files = re.findall(r"`([^`]+)`", item("file"))
        tests = re.findall(r"`([^`]+)`", item("tests"))
        blocks = re.findall(r"^```[a-z]*\n(.*?)^```$", body, flags=re.M | re.S)
        if len(files) != 1 or not tests or len(blocks) != 2:
            raise SystemExit(f"mutations.md entry {mid}: needs one `file`, `tests` and two code blocks "
                             f"(found {len(files)} file, {len(tests)} tests, {len(blocks)} blocks)")
        original, mutated = (b[:-1] if b.endswith("\n") else b for b in blocks)
        if not original:
            raise SystemExit(f"mutations.md entry {mid}: the original snippet is empty")
        out.append(Mutation(mid, title.strip(), files[0], tests, original, mutated, item("date")))
    ids = [m.id for m in out]
    dup = {i for i in ids if ids.count(i) > 1}
    if dup:
        raise SystemExit(f"mutations.md: duplicate ids {sorted(dup)}")
    return out


def applies(m: Mutation, root: Path) -> str:
    """'' when the original snippet occurs exactly once in the file under `root`, else why not."""
    path = root / m.file
    if not path.is_file():
        return f"{m.file} does not exist"
    n = path.read_text().count(m.original)
    return "" if n == 1 else ("snippet not found" if n == 0 else f"snippet found {n} times")


def repo_files(root: Path) -> list[str]:
    r = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=root,
                       capture_output=True, check=True)
    return [p for p in r.stdout.decode().split("\0") if p and (root / p).is_file()]


def native_module_path() -> Path | None:
    """Where the venv loads psimap.render._native from (a subprocess: this script stays light)."""
    code = "import importlib.util as u; s = u.find_spec('psimap.render._native'); print(s.origin if s else '')"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    p = r.stdout.strip()
    return Path(p) if r.returncode == 0 and p else None


def wheel_packages() -> dict[str, str]:
    """pyproject's [tool.scikit-build.wheel.packages]: {installed path: source folder}."""
    text = (ROOT / "pyproject.toml").read_text()
    try:
        import tomllib                  # Python >= 3.11
    except ImportError:                 # 3.10: the table is plain `"a" = "b"` lines
        table = text.split("[tool.scikit-build.wheel.packages]", 1)[-1].split("\n[", 1)[0]
        return dict(re.findall(r'^"([^"]+)"\s*=\s*"([^"]+)"', table, flags=re.M))
    return tomllib.loads(text)["tool"]["scikit-build"]["wheel"]["packages"]


def make_copy(tmp: Path) -> tuple[Path, dict]:
    """The repository copy under tmp/repo, importable as installed; returns (copy root, env)."""
    repo = tmp / "repo"
    for rel in repo_files(ROOT):
        dst = repo / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / rel, dst)
    for dest, src in wheel_packages().items():
        if dest != src:                 # e.g. psimap/exporters <- exporters
            link = repo / dest
            link.parent.mkdir(parents=True, exist_ok=True)
            link.symlink_to(os.path.relpath(repo / src, link.parent), target_is_directory=True)
    so = native_module_path()
    if so is not None:
        (repo / "psimap" / "render" / so.name).symlink_to(so)
    shared = ROOT.parent / "shared"
    if shared.exists():
        (tmp / "shared").symlink_to(shared.resolve())
    site = tmp / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(SITECUSTOMIZE)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(site), str(repo)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    # the copy must be what gets imported, native module included
    code = ("import psimap, psimap.exporters.usd, psimap.render.native as n; "
            "print(psimap.__file__); print(psimap.exporters.usd.__file__); print(n.__file__)")
    r = subprocess.run([sys.executable, "-c", code], cwd=repo, env=env, capture_output=True, text=True)
    where = r.stdout.split()
    if r.returncode != 0 or len(where) != 3 or not all(w.startswith(str(repo)) for w in where):
        raise SystemExit(f"mutate: the copy under {repo} is not what Python imports:\n{r.stdout}{r.stderr}")
    return repo, env


def tests_at(repo: Path, rev: str) -> None:
    """Replace the copy's tests/ by the tests/ folder of git revision `rev`."""
    archive = subprocess.run(["git", "archive", rev, "tests"], cwd=ROOT, capture_output=True)
    if archive.returncode != 0:
        raise SystemExit(f"mutate: git archive {rev} tests: {archive.stderr.decode().strip()}")
    shutil.rmtree(repo / "tests")
    subprocess.run(["tar", "-x", "-C", str(repo)], input=archive.stdout, check=True)


NATIVE_SOURCES = "psimap/render/csrc/"
CUDA_SOURCES = "psimap/render/csrc_cuda/"


def swap_in_native_build(repo: Path, build: Path):
    """Build the copy's (mutated) native module with CMake and put it where the copy imports it
    from; returns (link path, what it linked to before) to restore, or the compiler's last line
    when the mutated code does not build."""
    cfg = subprocess.run(["cmake", "-S", str(repo), "-B", str(build), "-DCMAKE_BUILD_TYPE=Release",
                          f"-DPython_EXECUTABLE={sys.executable}"], capture_output=True, text=True)
    out = cfg if cfg.returncode else subprocess.run(
        ["cmake", "--build", str(build), "-j", "2"], capture_output=True, text=True)
    if out.returncode:
        return "does not compile: " + last_line(out.stdout + out.stderr)
    built = next(build.rglob("_native*.so"))
    link = next((repo / "psimap" / "render").glob("_native*.so"))
    before = Path(os.readlink(link))
    link.unlink()
    link.symlink_to(built)
    return link, before


def cuda_device() -> bool:
    """Whether this machine has a CUDA device torch can use (the CUDA kernel's tests need one)."""
    try:
        import torch
    except ImportError:
        return False
    return bool(torch.cuda.is_available())


def run_tests(repo: Path, env: dict, tests: list[str]) -> tuple[int, float, str]:
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", "--no-header", *tests]
    try:
        r = subprocess.run(cmd, cwd=repo, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
        rc, out = r.returncode, r.stdout + r.stderr
    except subprocess.TimeoutExpired:
        rc, out = -1, f"timed out after {TIMEOUT_S} s"
    return rc, time.perf_counter() - t0, out


def last_line(text: str) -> str:
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    return lines[-1][:160] if lines else ""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("ids", nargs="*", help="mutation ids to run (default: all)")
    ap.add_argument("--list", action="store_true", help="list the entries and whether each applies")
    ap.add_argument("--no-baseline", action="store_true",
                    help="skip running each test set once unmutated (faster; a test that already "
                         "fails then reads as 'caught')")
    ap.add_argument("--tests", nargs="+", metavar="TEST",
                    help="run these tests instead of each entry's (e.g. the suite as it was before "
                         "a new test: does the mutation survive it?)")
    ap.add_argument("--tests-at", metavar="REV",
                    help="run the tests as they were at git revision REV (the copy's tests/ folder "
                         "is replaced): was this mutation a blind spot before?")
    ap.add_argument("-v", "--verbose", action="store_true", help="print the tail of each pytest run")
    args = ap.parse_args(argv)
    muts = parse(LIST.read_text())
    if args.ids:
        unknown = sorted(set(args.ids) - {m.id for m in muts})
        if unknown:
            raise SystemExit(f"mutate: unknown ids {unknown}")
        muts = [m for m in muts if m.id in args.ids]
    if args.tests:
        for m in muts:
            m.tests = list(args.tests)
    if args.list:
        for m in muts:
            why = applies(m, ROOT)
            print(f"{m.id:5} {'ok ' if not why else 'n/a'} {m.file:34} {m.title}" + (f"  ({why})" if why else ""))
        return 0

    results = []
    with tempfile.TemporaryDirectory(prefix="psimap-mutate-") as t:
        repo, env = make_copy(Path(t))
        if args.tests_at:
            tests_at(repo, args.tests_at)
        print(f"mutate: {len(muts)} mutation(s) against a copy in {repo}", flush=True)
        baseline: dict[tuple, tuple[int, str]] = {}
        for m in muts:
            why = applies(m, repo)
            if why:
                results.append((m, "n/a", why, 0.0))
                print(f"{m.id:5} n/a       {m.title}: {why}", flush=True)
                continue
            if m.file.startswith(CUDA_SOURCES) and not cuda_device():
                results.append((m, "skipped", "needs a CUDA device", 0.0))
                print(f"{m.id:5} skipped   {m.title}: needs a CUDA device", flush=True)
                continue
            key = tuple(m.tests)
            if not args.no_baseline and key not in baseline:
                rc, dt, out = run_tests(repo, env, m.tests)
                baseline[key] = (rc, last_line(out))
            if not args.no_baseline and baseline[key][0] != 0:
                results.append((m, "ERROR", f"tests fail without the mutation: {baseline[key][1]}", 0.0))
                print(f"{m.id:5} ERROR     {m.title}: tests fail unmutated ({baseline[key][1]})", flush=True)
                continue
            path = repo / m.file
            text = path.read_text()
            so_link = None
            try:
                path.write_text(text.replace(m.original, m.mutated, 1))
                if m.file.startswith(NATIVE_SOURCES):
                    so_link = swap_in_native_build(repo, Path(t) / "native-build")
                    if isinstance(so_link, str):        # the mutated kernels do not compile
                        results.append((m, "caught", so_link, 0.0))
                        print(f"{m.id:5} caught    {m.title}: {so_link}", flush=True)
                        so_link = None
                        continue
                rc, dt, out = run_tests(repo, env, m.tests)
            finally:
                path.write_text(text)
                if so_link is not None:
                    so_link[0].unlink()
                    so_link[0].symlink_to(so_link[1])
            if rc in (1, 2):            # failed tests, or a collection error the mutation caused
                status = "caught"
            elif rc == 0:
                status = "SURVIVED"
            elif rc == -1:
                status = "caught"       # a hang fails CI too; said in the detail
            else:
                status = "ERROR"
            detail = last_line(out)
            results.append((m, status, detail, dt))
            print(f"{m.id:5} {status:9} {m.title} ({dt:.0f} s): {detail}", flush=True)
            if args.verbose:
                print("\n".join("      " + ln for ln in out.strip().splitlines()[-15:]), flush=True)

    counts = {s: sum(r[1] == s for r in results) for s in ("caught", "SURVIVED", "n/a", "ERROR", "skipped")}
    print("mutate: " + ", ".join(f"{v} {k}" for k, v in counts.items()))
    for m, status, detail, _ in results:
        if status not in ("caught", "skipped"):
            print(f"  {m.id} {status}: {m.file}: {m.title} -- {detail}")
    if counts["SURVIVED"] or counts["ERROR"]:
        return 1
    return 2 if counts["n/a"] else 0


if __name__ == "__main__":
    sys.exit(main())
