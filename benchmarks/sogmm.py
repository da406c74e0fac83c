"""SOGMM prior benchmark: fit time and K beside the point-to-plane residual they buy, at several
residual budgets, on the shared real KITTI Velodyne sweep (skipped if absent) and on a synthetic
room with boxes sampled to 1 M points; plus the 1 M point timing with default settings.

Run: .venv/bin/python benchmarks/sogmm.py   (appends to benchmarks/RESULTS.md, plot in bench_out/)
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import append_results, markdown_table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
KITTI = ROOT.parent / "shared" / "data" / "kitti-velodyne" / "000000.bin"
OUT = ROOT / "bench_out"


def box_surface(lo, hi, n: int, rng, *, open_top: bool = False, inward: bool = False):
    """n points uniform on the faces of the axis-aligned box [lo, hi] -> (points [n,3], normals [n,3])."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    ext = hi - lo
    areas = np.array([ext[1] * ext[2]] * 2 + [ext[0] * ext[2]] * 2 + [ext[0] * ext[1]] * 2)
    if open_top:
        areas[5] = 0.0
    face = rng.choice(6, n, p=areas / areas.sum())
    axis, upper = face // 2, face % 2
    p = lo + rng.random((n, 3)) * ext
    p[np.arange(n), axis] = np.where(upper == 1, hi[axis], lo[axis])
    nrm = np.zeros((n, 3))
    nrm[np.arange(n), axis] = np.where(upper == 1, 1.0, -1.0) * (-1.0 if inward else 1.0)
    return p, nrm


def synthetic_room(n: int, seed: int = 0, noise: float = 0.003):
    """A 6 x 5 x 3 m room (floor, walls, ceiling) with 8 boxes on the floor, n points in all with
    Gaussian depth-like noise along the normal and a grey value per surface.
    Returns points [n, 4] (x, y, z, grey), normals [n, 3]."""
    rng = np.random.default_rng(seed)
    boxes = []
    for _ in range(8):
        size = rng.uniform([0.3, 0.3, 0.2], [1.2, 0.9, 1.0])
        corner = rng.uniform([0.2, 0.2, 0.0], [6.0 - size[0] - 0.2, 5.0 - size[1] - 0.2, 0.0])
        boxes.append((corner, corner + size))
    room_area = 2 * (6 * 5 + 6 * 3 + 5 * 3)
    box_areas = [2 * ((h - l)[0] * (h - l)[1] + (h - l)[0] * (h - l)[2] + (h - l)[1] * (h - l)[2])
                 for l, h in boxes]
    total = room_area + sum(box_areas)
    counts = [int(n * room_area / total)] + [int(n * a / total) for a in box_areas]
    counts[0] += n - sum(counts)
    pts, nrms, greys = [], [], []
    p, q = box_surface([0, 0, 0], [6, 5, 3], counts[0], rng, inward=True)
    pts.append(p), nrms.append(q), greys.append(0.3 + 0.4 * (p[:, 2] > 0.01))
    for (l, h), c in zip(boxes, counts[1:]):
        p, q = box_surface(l, h, c, rng)
        pts.append(p), nrms.append(q), greys.append(np.full(c, rng.uniform(0.1, 0.9)))
    p, q, g = np.concatenate(pts), np.concatenate(nrms), np.concatenate(greys)
    p = p + rng.normal(0.0, noise, (len(p), 1)) * q
    return np.c_[p, g].astype(np.float32), q


def run_case(name, pts, budgets, rows, curve, **kw):
    from psimap.geometry import fit_sogmm

    for b in budgets:
        g = fit_sogmm(pts, residual=b, **kw)
        s = g.fit_stats
        rows.append([name, len(pts), s["n_points"], f"{s['voxel'] * 100:.2f}", f"{b * 100:.2f}" if b else
                     f"auto {s['residual_budget'] * 100:.2f}", s["K"], f"{s['residual_mean'] * 1000:.2f}",
                     f"{s['time_s']:.2f}"])
        curve.setdefault(name, []).append((s["residual_budget"], s["K"], s["time_s"], s["residual_mean"]))
        print(rows[-1], flush=True)


def main() -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from psimap.geometry import fit_sogmm, lidar_points

    rows, curve = [], {}
    notes = []
    if KITTI.exists():
        kitti = lidar_points(np.fromfile(KITTI, dtype=np.float32).reshape(-1, 4))
        run_case("KITTI 000000", kitti, [0.2, 0.05, 0.02], rows, curve)
    else:
        notes.append(f"KITTI sweep not found at {KITTI}: skipped.")
    room, _ = synthetic_room(1_000_000)
    # budgets at a fixed 1 cm voxel so the residual reflects the budget, not the downsampling
    run_case("room 1M pts", room, [0.02, 0.008, 0.004], rows, curve, voxel=0.01)
    # the 1 M point timing with every setting automatic
    t = time.perf_counter()
    g = fit_sogmm(room)
    wall = time.perf_counter() - t
    s = g.fit_stats
    rows.append(["room 1M pts, all auto", len(room), s["n_points"], f"{s['voxel'] * 100:.2f}",
                 f"auto {s['residual_budget'] * 100:.2f}", s["K"], f"{s['residual_mean'] * 1000:.2f}",
                 f"{wall:.2f}"])
    print(rows[-1], flush=True)

    header = ["cloud", "input pts", "fitted pts", "voxel cm", "budget cm", "K", "mean pt-to-plane mm",
              "fit time s"]
    OUT.mkdir(exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for name, pts in curve.items():
        b, k, t_s, r = (np.array(v) for v in zip(*pts))
        axes[0].plot(b * 100, k, "o-", label=name)
        axes[1].plot(b * 100, t_s, "o-", label=name)
    axes[0].set(xlabel="residual budget (cm)", ylabel="components K", xscale="log", yscale="log")
    axes[1].set(xlabel="residual budget (cm)", ylabel="fit time (s)", xscale="log")
    for ax in axes:
        ax.legend()
        ax.grid(alpha=0.3)
    fig.suptitle("SOGMM: K and fit time vs point-to-plane budget")
    fig.tight_layout()
    fig.savefig(OUT / "sogmm_budget.png", dpi=120)
    notes.append("Synthetic room: 6x5x3 m + 8 boxes, 3 mm normal noise (mean |noise| 2.4 mm). "
                 "Time includes voxel downsampling. Plot: bench_out/sogmm_budget.png. "
                 "Target: <= 30 s for 1 M points on this machine (2 cores).")
    append_results("SOGMM prior: fit time, K and residual vs budget", markdown_table(header, rows),
                   " ".join(notes), command="python benchmarks/sogmm.py")
    return 0


if __name__ == "__main__":
    sys.exit(main())
