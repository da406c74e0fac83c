"""benchmarks/_results.py: one section per benchmark key in RESULTS.md, replaced by the next run."""
import os
import threading

import pytest
from scripts import load_script

R = load_script("benchmarks/_results.py", "bench_results")


def write(path, key, figure, **kw):
    kw.setdefault("headlines", [("figure", f"{figure} s")])
    return R.write_section(key, f"Bench {key}", f"| a |\n|---|\n| {figure} |", command="python b.py",
                           results=path, **kw)


def keys(path):
    return list(R.parse(path.read_text())[1])


def test_new_file_has_preamble_summary_and_section(tmp_path):
    res = tmp_path / "RESULTS.md"
    write(res, "sogmm", 6.13)
    text = res.read_text()
    assert text.startswith("# Benchmark results\n")
    assert keys(res) == ["sogmm"]
    # the summary row links the section's heading and carries its headline and date
    row = next(ln for ln in text.splitlines() if ln.startswith("| [Bench sogmm](#bench-sogmm)"))
    assert "| figure | 6.13 s |" in row
    assert "`python b.py` — " in text and "load average" in text
    assert R.compose(*R.parse(text)) == text          # what was written parses back unchanged


def test_rerun_replaces_only_its_own_section(tmp_path):
    res = tmp_path / "RESULTS.md"
    write(res, "geometry", 1.898)
    write(res, "panoptic", 0.842)
    other = R.parse(res.read_text())[1]["panoptic"]
    write(res, "geometry", 1.5)
    text = res.read_text()
    assert "1.898" not in text and text.count("| 1.5 |") == 1
    assert keys(res) == ["geometry", "panoptic"]
    assert R.parse(text)[1]["panoptic"] == other          # byte for byte
    assert text.count("<!-- section: geometry -->") == 1


def test_sections_keep_reading_order(tmp_path):
    res = tmp_path / "RESULTS.md"
    for k in ("export/scene", "zzz", "geometry", "demo", "geometry/chess", "export/ycb", "aaa"):
        write(res, k, 1.0)
    want = ["demo", "geometry", "geometry/chess", "export/scene", "export/ycb", "zzz", "aaa"]
    assert keys(res) == want
    write(res, "geometry", 2.0)           # a re-run keeps its place
    write(res, "zzz", 2.0)
    assert keys(res) == want
    summary_order = [ln.split("](#")[1].split(")")[0] for ln in res.read_text().splitlines()
                     if ln.startswith("| [Bench ")]
    assert summary_order == ["bench-" + k.replace("/", "") for k in want]


def test_summary_rebuilt_from_headlines_on_every_write(tmp_path):
    res = tmp_path / "RESULTS.md"
    write(res, "render", 1.0, headlines=[("fwd+bwd | speed-up", "24.1x -- CPU"), ("pairs", "26.5 % fewer")])
    write(res, "completion", 1.0, headlines=[])
    text = res.read_text().replace("24.1x", "99x", 1)      # a hand edit inside the summary only
    res.write_text(text)
    write(res, "sogmm", 6.0)
    summary = res.read_text().split("<!-- end summary -->")[0]
    assert "| fwd+bwd \\| speed-up | 24.1x -- CPU |" in summary     # '|' escaped, '--' survives JSON
    assert "|  | pairs | 26.5 % fewer |  |" in summary                # second headline row of a section
    assert "| [Bench completion](#bench-completion) | - | - |" in summary   # listed without headline
    assert "99x" not in summary
    assert "-->" not in R.parse(res.read_text())[1]["render"].split("\n")[1][:-4]   # comment not ended early


def test_missing_section_is_added_in_place(tmp_path):
    res = tmp_path / "RESULTS.md"
    for k in ("demo", "geometry", "export"):
        write(res, k, 1.0)
    pre, secs = R.parse(res.read_text())
    del secs["geometry"]                                   # deleted by hand
    res.write_text(R.compose(pre, secs))
    write(res, "geometry", 3.0)
    assert keys(res) == ["demo", "geometry", "export"]


def test_findings_survive_a_rerun(tmp_path):
    res = tmp_path / "RESULTS.md"
    write(res, "geometry", 1.0)
    notes = "<!-- findings -->\n- 2026-11-22: ss = 2 rays per pixel (Chamfer 1.661 -> 1.297 cm).\n<!-- end findings -->"
    pre, secs = R.parse(res.read_text())
    secs["geometry"] = secs["geometry"].replace(R.END, notes + "\n" + R.END)
    res.write_text(R.compose(pre, secs))
    write(res, "geometry", 2.0)
    sec = R.parse(res.read_text())[1]["geometry"]
    assert "| 2.0 |" in sec and "1.661 -> 1.297" in sec and sec.count(R.FINDINGS_BEGIN) == 1


@pytest.mark.parametrize("bad, line", [
    ("<!-- section: a -->\n## A\n", 1),                                        # never closed
    ("<!-- section: a -->\n## A\n<!-- section: b -->\n## B\n<!-- end -->\n", 1),  # closed by the next one
    ("# R\n\n<!-- end -->\n", 3),                                               # end without begin
    ("<!-- section: a -->\n<!-- end -->\n<!-- section: a -->\n<!-- end -->\n", 3),  # twice
    ("# Benchmark results\n\n## SOGMM prior\n\n| x |\n", 3),                    # the old append-only log
    ("<!-- section: a -->\n<!-- end -->\nstray note\n", 3),                     # text between sections
    ("<!-- section: a -->\n<!-- findings -->\n<!-- end -->\n", 1),              # findings not closed
])
def test_malformed_file_is_refused_and_left_untouched(tmp_path, bad, line):
    res = tmp_path / "RESULTS.md"
    res.write_text(bad)
    with pytest.raises(R.ResultsFileError, match=f"line {line}\\b"):
        write(res, "sogmm", 1.0)
    assert res.read_text() == bad
    assert os.listdir(tmp_path) == ["RESULTS.md"]


def test_failed_write_leaves_the_old_file(tmp_path, monkeypatch):
    res = tmp_path / "RESULTS.md"
    write(res, "sogmm", 1.0)
    before = res.read_text()

    def crash(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr("psimap.io_utils.os.replace", crash)
    with pytest.raises(OSError, match="disk full"):
        write(res, "sogmm", 2.0)
    assert res.read_text() == before
    assert os.listdir(tmp_path) == ["RESULTS.md"]          # no temporary file left behind


def test_concurrent_writers_lose_no_section(tmp_path):
    res = tmp_path / "RESULTS.md"

    def run(k):
        for i in range(5):
            write(res, k, float(i))

    threads = [threading.Thread(target=run, args=(k,)) for k in ("geometry", "panoptic", "export")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    secs = R.parse(res.read_text())[1]
    assert list(secs) == ["geometry", "panoptic", "export"]
    assert all("| 4.0 |" in s for s in secs.values())


def test_plot_linked_small_and_removed_when_a_rerun_has_none(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    res = tmp_path / "RESULTS.md"
    rng = np.random.default_rng(0)
    fig, ax = plt.subplots(figsize=(12, 9))
    ax.plot(rng.random(3000), rng.random(3000), ".", ms=2)      # ~210 KB at 300 dpi: must shrink
    png = R.save_plot(fig, "export/scene", results=res, dpi=300)
    assert png == tmp_path / "plots" / "export-scene.png"
    assert png.stat().st_size <= R.PLOT_MAX_BYTES
    write(res, "export/scene", 1.0, plot=png)
    assert "![Bench export/scene](plots/export-scene.png)" in res.read_text()
    write(res, "export/scene", 2.0)
    assert not png.exists() and "plots/export-scene.png" not in res.read_text()


def test_refresh_rebuilds_the_summary(tmp_path):
    res = tmp_path / "RESULTS.md"
    write(res, "demo", 220.1)
    good = res.read_text()
    res.write_text(good.replace("| figure | 220.1 s |", "| figure | stale |"))
    R.refresh(res)
    assert res.read_text() == good


def test_bad_key_is_refused(tmp_path):
    with pytest.raises(ValueError, match="section key"):
        write(tmp_path / "RESULTS.md", "Geometry Noise", 1.0)


def test_committed_results_parse_with_an_up_to_date_summary():
    text = R.RESULTS.read_text()
    pre, secs = R.parse(text)
    assert R.compose(pre, secs) == text, "run `python benchmarks/_results.py` after editing RESULTS.md"
    for key, sec in secs.items():
        for link in [ln for ln in sec.splitlines() if ln.startswith("![")]:
            assert (R.RESULTS.parent / link.split("](")[1].rstrip(")")).exists(), f"{key}: {link}"


def test_what_benchmarks_write_does_not_mark_the_commit_dirty():
    """The header's '+ uncommitted changes' is about code: RESULTS.md, plots and the run records a
    benchmark rewrites while it runs (end_to_end_runs.json) do not count, code and benchmark scripts
    do."""
    for line in (" M benchmarks/RESULTS.md", " M benchmarks/plots/end_to_end.png", " M benchmarks/end_to_end_runs.json"):
        assert R.benchmark_output(line), line
    for line in (" M benchmarks/end_to_end.py", " M psimap/panoptic/fit.py", " M benchmarks/runs.py"):
        assert not R.benchmark_output(line), line
