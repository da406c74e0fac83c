"""Synthetic scene generator benchmark: time to write a scene at three image sizes (cold CLI run
with imports, and warm in-process), beside the curved-surface error the tessellation budget costs.

Run: .venv/bin/python benchmarks/generate.py   (its section of benchmarks/RESULTS.md, plot in benchmarks/plots/)
Target (issue 2): 60 frames at 160x120 in <= 10 s on 2 cores.
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import markdown_table, save_plot, write_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SIZES = [(60, 80, 60), (60, 160, 120), (60, 320, 240)]
SEEDS = (0, 1)


def cold_run(out: Path, frames: int, w: int, h: int, seed: int) -> tuple[float, float]:
    """(wall s, CPU s) of a fresh `psimap generate` process (imports included), as a user sees it.
    CPU time (user + sys of the child) does not depend on what else the machine runs."""
    import resource

    cmd = [sys.executable, "-m", "psimap", "generate", str(out), "--seed", str(seed), "--frames", str(frames),
           "--width", str(w), "--height", str(h)]
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, cwd=ROOT)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def tessellation_error(tol: float) -> tuple[float, int]:
    """Largest measured distance (m) of a ball (r = 0.1 m) and a bottle-sized cylinder (r = 0.04 m)
    mesh from the true surface, at chordal budget `tol`, and their triangle count."""
    import manifold3d as m3d
    import trimesh

    from psimap.data import synthetic_shapes as S

    S.CHORD_TOL = tol
    worst, tris = 0.0, 0
    for r, solid, radial in ((0.1, S.sphere(0.1), lambda p: np.linalg.norm(p, axis=1)),
                             (0.04, m3d.Manifold.cylinder(0.2, 0.04, circular_segments=S.segments_for(0.04)),
                              lambda p: np.linalg.norm(p[:, :2], axis=1))):
        mesh = S.to_trimesh(solid)
        pts, face = trimesh.sample.sample_surface_even(mesh, 20000, seed=0)
        side = np.abs(mesh.face_normals[face][:, 2]) < 0.99 if r == 0.04 else slice(None)
        worst = max(worst, float(np.abs(radial(pts[side]) - r).max()))
        tris += len(mesh.faces)
    return worst, tris


def main() -> None:
    from psimap.data import synthetic as G
    from psimap.data import synthetic_shapes as S

    tmp = Path(tempfile.mkdtemp(prefix="psimap_bench_gen_"))
    G.generate(tmp / "warmup", seed=0, frames=4, width=32, height=24)  # imports + first-call costs
    rows, plot = [], []
    for frames, w, h in SIZES:
        warm, cpu, cold, cold_cpu, invalid, errs = [], [], [], [], [], []
        for seed in SEEDS:
            t0, c0 = time.perf_counter(), time.process_time()
            s = G.generate(tmp / f"w{w}_{seed}", seed=seed, frames=frames, width=w, height=h)
            warm.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            invalid.append(s["invalid_depth_fraction"])
            ln = s["label_noise"]
            errs.append((ln["merged"] + ln["split"] + ln["missed"] + ln["flipped"]) / max(ln["instances"], 1))
            wall, c = cold_run(tmp / f"c{w}_{seed}", frames, w, h, seed)
            cold.append(wall)
            cold_cpu.append(c)
        rays = frames * w * h
        rows.append([frames, f"{w}x{h}", f"{np.mean(cold):.2f}", f"{np.mean(cold_cpu):.2f}",
                     f"{np.mean(warm):.2f}", f"{np.mean(cpu):.2f}",
                     f"{1e3 * np.mean(warm) / frames:.1f}", f"{rays / np.mean(warm) / 1e6:.2f}",
                     f"{100 * np.mean(invalid):.1f}", f"{np.mean(errs):.2f}"])
        plot.append((rays, np.mean(cold), np.mean(warm)))
    table = markdown_table(["frames", "size", "cold CLI s", "cold CLI CPU s", "warm s", "warm CPU s",
                            "ms/frame (warm)", "Mrays/s (warm)",
                            "invalid depth %", "label errors / instance view"], rows)

    tol_rows = []
    default_tol = S.CHORD_TOL
    for tol in (2e-3, default_tol, 1e-4):
        err, tris = tessellation_error(tol)
        S.CHORD_TOL = tol
        t0 = time.perf_counter()
        s = G.generate(tmp / f"tol{tol}", seed=0, frames=60, width=160, height=120)
        dt = time.perf_counter() - t0
        tol_rows.append([f"{1e3 * tol:.2f}", f"{1e3 * err:.3f}", tris, f"{dt:.2f}",
                         f"{s['timings']['layout']:.2f}"])
    S.CHORD_TOL = default_tol
    tol_table = markdown_table(["chord budget mm", "measured max surface error mm", "triangles (ball + cylinder)",
                                "scene s (60 @ 160x120, warm)", "layout s"], tol_rows)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    r, c, wm = (np.array(v) for v in zip(*plot))
    ax.plot(r / 1e6, c, "o-", label="cold CLI run (imports included)")
    ax.plot(r / 1e6, wm, "s-", label="warm, in process")
    ax.axhline(10, color="grey", ls="--", lw=0.8, label="target for 60 @ 160x120")
    ax.set_xlabel("rays cast (millions) = frames x W x H")
    ax.set_ylabel("seconds")
    ax.set_title("psimap generate: time per scene")
    ax.legend(fontsize=8)
    fig.tight_layout()
    png = save_plot(fig, "generate")

    load = os.getloadavg()[0]
    notes = (f"Mean over seeds {list(SEEDS)}; {os.cpu_count()} CPU cores shared with other jobs (1-min load "
             f"average {load:.1f} at the end: wall time grows with load, CPU s is the process's own CPU "
             "time and does not). Cold = a fresh `python -m psimap "
             "generate` process, imports (open3d, trimesh, manifold3d, scipy) included. Label "
             "errors at the default noise 0.15. Chord budget table: the curved-surface error the "
             "tessellation budget buys and what it costs (default "
             f"{1e3 * default_tol:.2f} mm).")
    demo = next(r for r in rows if r[1] == "160x120")
    write_section("generate", "Synthetic scene generator (psimap generate)",
                  table + "\n\n" + tol_table + "\n\n" + notes,
                  headlines=[("60 frames 160x120, cold CLI run (target <= 10 s)",
                              f"{demo[2]} s wall, {demo[3]} s CPU")], plot=png)
    import shutil

    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
