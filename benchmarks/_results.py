"""benchmarks/RESULTS.md as one section per benchmark (or benchmark + mode), each replaced by its
benchmark's next run; git keeps the history. The file opens with a summary table rebuilt from every
section's headline lines whenever any section is written.

Layout of RESULTS.md (the markers are HTML comments, invisible when rendered):

    # Benchmark results
    free text (kept as is)
    <!-- summary: ... -->            generated; edits here are overwritten
    | benchmark | headline | value | measured |
    <!-- end summary -->
    <!-- section: geometry -->
    <!-- headline: ["psimap Chamfer-L1", "1.898 cm"] -->      one per summary row (JSON)
    <!-- measured: 2026-11-22 17:49 -->
    ## Geometry: ...
    `command` — date, commit, machine, load
    tables, notes, ![plot](plots/geometry.png)
    <!-- findings -->                dated notes kept when the section is re-run
    <!-- end findings -->
    <!-- end -->

A section is written whole into a temporary file that replaces RESULTS.md (never half-written),
under a lock on the folder so two benchmarks finishing together do not drop each other's section.
A file that does not parse is left untouched: ResultsFileError names the line.

    python benchmarks/_results.py     # check RESULTS.md and rebuild its summary (after hand edits)
"""
from __future__ import annotations

import contextlib
import datetime
import fcntl
import json
import os
import platform
import re
import subprocess
import sys
from pathlib import Path

from psimap import PsimapError
from psimap.io_utils import atomic_path

RESULTS = Path(__file__).with_name("RESULTS.md")
PLOT_DIR = "plots"                    # next to RESULTS.md, committed with it
PLOT_MAX_BYTES = 150_000
# Reading order of the sections: the end-to-end demo, then the pipeline's data flow. A key's
# benchmark is the part before '/' ("export/scene" -> "export"); a benchmark not listed goes last.
ORDER = ("demo", "generate", "sogmm", "render", "render_ablation", "geometry", "panoptic", "completion",
         "export")
PREAMBLE = ("# Benchmark results\n\n"
            "One section per benchmark (or benchmark and mode), written by its script in `benchmarks/` "
            "(all of them: `make bench`). A re-run replaces its own section, so every figure here is "
            "the latest run of that benchmark; older runs are in git history. Each section gives the "
            "command, date, commit, machine and load average, and speed beside the error it costs, "
            "measured in one run.\n")

KEY_RE = re.compile(r"[a-z0-9_.-]+(/[a-z0-9_.-]+)*")
BEGIN_RE = re.compile(r"<!-- section: (\S+) -->")
END = "<!-- end -->"
SUMMARY_BEGIN = ("<!-- summary: generated from the sections' headline lines by benchmarks/_results.py; "
                 "edits here are overwritten -->")
SUMMARY_BEGIN_RE = re.compile(r"<!-- summary\b.*-->")
SUMMARY_END = "<!-- end summary -->"
HEADLINE_RE = re.compile(r"<!-- headline: (.*) -->")
MEASURED_RE = re.compile(r"<!-- measured: (.*) -->")
FINDINGS_BEGIN, FINDINGS_END = "<!-- findings -->", "<!-- end findings -->"
TITLE_RE = re.compile(r"## (.+)")


class ResultsFileError(PsimapError):
    """RESULTS.md does not parse as sections; it is left as it was."""


def markdown_table(header: list[str], rows: list[list]) -> str:
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


def plot_path(key: str, results: Path = RESULTS) -> Path:
    """Where section `key`'s plot lives: plots/KEY.png beside RESULTS.md ('/' -> '-')."""
    return results.parent / PLOT_DIR / f"{key.replace('/', '-')}.png"


def save_plot(fig, key: str, results: Path = RESULTS, dpi: int = 100) -> Path:
    """Write a matplotlib figure as section `key`'s plot (atomically) and close it. The PNG is
    committed, so a file over PLOT_MAX_BYTES is written again at a lower resolution."""
    import matplotlib.pyplot as plt

    path = plot_path(key, results)
    while True:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format="png")
            size = tmp.stat().st_size
        if size <= PLOT_MAX_BYTES or dpi <= 40:
            break
        dpi = int(dpi * 0.75)
    plt.close(fig)
    if size > PLOT_MAX_BYTES:
        print(f"warning: {path} is {size // 1000} KB (> {PLOT_MAX_BYTES // 1000} KB) even at {dpi} dpi")
    os.chmod(path, 0o644)
    return path


def write_section(key: str, title: str, body: str, *, headlines=(), command: str | None = None,
                  plot: Path | None = None, results: Path = RESULTS) -> str:
    """Replace section `key` of RESULTS.md (add it in reading order if new), keep every other section
    as it is, rebuild the summary table; print the section and return its text.

    headlines: (label, value) pairs, one summary row each, e.g. ("fit time, 1 M points", "6.1 s").
    command: what was run (default: this process's command line, path relative to the repository).
    plot: a PNG from save_plot, linked under the body. Without one, a plot an earlier run left at
    plot_path(key) is removed: it would no longer match the section's figures.
    """
    if not KEY_RE.fullmatch(key):
        raise ValueError(f"section key {key!r}: use lower-case words joined by '-', '_', '.', '/'")
    now = datetime.datetime.now().strftime("%Y-%m-%d %H:%M")
    text = render_section(key, title, body, headlines=headlines, measured=now,
                          stamp=run_stamp(command, now), plot=plot, results=results)
    print(text, flush=True)
    with _locked(results.parent):
        old = results.read_text() if results.exists() else None
        preamble, sections = parse(old) if old is not None else (PREAMBLE, {})
        findings = _findings(sections.get(key, ""))
        if findings and FINDINGS_BEGIN not in body:      # dated notes outlive the figures they sit under
            text = with_findings(text, findings)
        sections[key] = text
        _write(results, compose(preamble, sections), old is not None)
        if plot is None:
            plot_path(key, results).unlink(missing_ok=True)
    return text


def render_section(key: str, title: str, body: str, *, headlines=(), measured: str, stamp: str,
                   plot: Path | None = None, results: Path = RESULTS) -> str:
    """One section's text, markers included."""
    lines = [f"<!-- section: {key} -->"]
    for label, value in headlines:
        lines.append(f"<!-- headline: {_comment_json([str(label), str(value)])} -->")
    lines += [f"<!-- measured: {measured} -->", f"## {title}", "", stamp, "", body.strip()]
    if plot is not None:
        rel = Path(plot).resolve().relative_to(results.parent.resolve()).as_posix()
        lines += ["", f"![{title}]({rel})"]
    # blank line before the marker: a table's last row must not run into it
    return "\n".join(lines) + "\n\n" + END


def run_stamp(command: str | None, when: str) -> str:
    """`command` — date, commit, machine, Python, load average: what a reader needs to trust a figure."""
    command = command or _own_command()
    load = " / ".join(f"{v:.1f}" for v in os.getloadavg())
    commit = _commit()
    return (f"`{command}` — {when}" + (f", commit {commit}" if commit else "") +
            f", {platform.machine()}, Python {platform.python_version()}, {os.cpu_count()} cores, "
            f"load average {load} (1 / 5 / 15 min) when written: wall times on a shared machine are "
            "noisy, CPU times less so")


def parse(text: str) -> tuple[str, dict[str, str]]:
    """(preamble without the summary, {key: section text with its markers}, in file order)."""
    lines = text.splitlines()
    preamble, sections, seen_section = [], {}, False
    i = 0
    while i < len(lines):
        line = lines[i]
        if SUMMARY_BEGIN_RE.fullmatch(line.strip()):
            j = _find(lines, i + 1, SUMMARY_END, "summary")
            i = j + 1
            continue
        m = BEGIN_RE.fullmatch(line.strip())
        if m:
            key = m.group(1)
            if key in sections:
                raise ResultsFileError(f"{_where(i)}: section '{key}' appears twice")
            j = _find(lines, i + 1, END, f"section '{key}'")
            body = lines[i:j + 1]
            if any(FINDINGS_BEGIN == b.strip() for b in body) != any(FINDINGS_END == b.strip() for b in body):
                raise ResultsFileError(f"{_where(i)}: section '{key}' has an unclosed findings block")
            sections[key] = "\n".join(body)
            seen_section = True
            i = j + 1
            continue
        if line.strip() == END or line.strip() == SUMMARY_END:
            raise ResultsFileError(f"{_where(i)}: '{line.strip()}' without its opening marker")
        if line.strip() and (seen_section or line.startswith("## ")):
            raise ResultsFileError(f"{_where(i)}: text outside a section ({line[:60]!r}); "
                                   "every '## ' heading belongs inside <!-- section: KEY --> ... <!-- end -->")
        preamble.append(line)
        i += 1
    return "\n".join(preamble).strip() + "\n", sections


def compose(preamble: str, sections: dict[str, str]) -> str:
    """The whole file: preamble, summary rebuilt from the sections, sections in reading order."""
    order = sorted(sections, key=lambda k: _rank(k))       # stable: same rank keeps file order
    ordered = {k: sections[k] for k in order}
    parts = [preamble.strip(), summary(ordered)] + [s.strip() for s in ordered.values()]
    return "\n\n".join(parts) + "\n"


def summary(sections: dict[str, str]) -> str:
    """Table of every section's headline rows (a section without any gets one row of '-')."""
    rows, slugs = [], {}
    for key, text in sections.items():
        title = next((m.group(1) for m in map(TITLE_RE.fullmatch, text.splitlines()) if m), key)
        slug = _slug(title)
        n = slugs.get(slug, 0)
        slugs[slug] = n + 1
        link = f"[{_cell(title)}](#{slug if n == 0 else f'{slug}-{n}'})"
        measured = next((m.group(1) for m in map(MEASURED_RE.fullmatch, text.splitlines()) if m), "-")
        heads = [json.loads(m.group(1)) for m in map(HEADLINE_RE.fullmatch, text.splitlines()) if m] or [["-", "-"]]
        for k, (label, value) in enumerate(heads):
            rows.append([link if k == 0 else "", _cell(label), _cell(value), measured if k == 0 else ""])
    return "\n".join([SUMMARY_BEGIN, markdown_table(["benchmark", "headline", "value", "measured"], rows),
                      SUMMARY_END])


def refresh(results: Path = RESULTS) -> None:
    """Check RESULTS.md parses and rebuild its summary (after a hand edit)."""
    with _locked(results.parent):
        old = results.read_text()
        new = compose(*parse(old))
        if new != old:
            _write(results, new, True)


def with_findings(section: str, block: str) -> str:
    """`section` with a findings block (markers included) as its last part, before the end marker."""
    return section[: -len(END)].rstrip("\n") + "\n\n" + block.strip() + "\n\n" + END


def _findings(section: str) -> str:
    """The section's findings block with its markers, or ''."""
    lines = section.splitlines()
    starts = [i for i, s in enumerate(lines) if s.strip() == FINDINGS_BEGIN]
    if not starts:
        return ""
    end = next(i for i in range(starts[0], len(lines)) if lines[i].strip() == FINDINGS_END)
    return "\n".join(lines[starts[0]:end + 1])


def _write(results: Path, text: str, existed: bool) -> None:
    mode = results.stat().st_mode & 0o777 if existed else 0o644
    with atomic_path(results) as tmp:
        tmp.write_text(text)
        os.chmod(tmp, mode)


@contextlib.contextmanager
def _locked(folder: Path):
    """Exclusive lock on the folder itself (no lock file): read-modify-write of RESULTS.md by one
    process at a time."""
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _find(lines, start, marker, what) -> int:
    for j in range(start, len(lines)):
        s = lines[j].strip()
        if s == marker:
            return j
        if BEGIN_RE.fullmatch(s) or SUMMARY_BEGIN_RE.fullmatch(s):
            raise ResultsFileError(f"{_where(start - 1)}: {what} is not closed by '{marker}' "
                                   f"before the next marker at line {j + 1}")
    raise ResultsFileError(f"{_where(start - 1)}: {what} is not closed by '{marker}'")


def _where(i: int) -> str:
    return f"{RESULTS.name} line {i + 1}"


def _rank(key: str) -> int:
    bench = key.split("/")[0]
    return ORDER.index(bench) if bench in ORDER else len(ORDER)


def _slug(title: str) -> str:
    """GitHub's heading anchor: lower case, punctuation dropped, spaces -> '-'."""
    return re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")


def _cell(s: str) -> str:
    return str(s).replace("|", "\\|").replace("\n", " ")


def _comment_json(v) -> str:
    """JSON that cannot end the HTML comment it sits in ('--' written as '-\\u002d')."""
    return json.dumps(v, ensure_ascii=False).replace("--", "-\\u002d")


def _own_command() -> str:
    """This process's command line with the script path relative to the repository."""
    root = Path(__file__).resolve().parents[1]
    script = Path(sys.argv[0]).resolve()
    with contextlib.suppress(ValueError):
        script = script.relative_to(root)
    return " ".join(["python", str(script), *sys.argv[1:]])


def _commit() -> str:
    """Short HEAD, '+ uncommitted changes' when tracked code differs (what benchmarks write aside:
    RESULTS.md, plots, and the run records a benchmark keeps, benchmarks/*_runs.json, which
    end_to_end.py rewrites while it runs)."""
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True,
                              text=True, timeout=10)
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                                capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return ""
    if head.returncode != 0:
        return ""
    dirty = [ln for ln in status.stdout.splitlines() if not benchmark_output(ln)]
    return head.stdout.strip() + (" + uncommitted changes" if dirty else "")


def benchmark_output(status_line: str) -> bool:
    """Whether a `git status --porcelain` line names a file the benchmarks write (not code)."""
    return re.search(r"benchmarks/(RESULTS\.md|plots/|\w+_runs\.json)", status_line) is not None


if __name__ == "__main__":
    try:
        refresh()
    except ResultsFileError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(1)
    print(f"{RESULTS}: {len(parse(RESULTS.read_text())[1])} sections, summary rebuilt")
