"""SOGMM prior benchmark: fit time and K beside the point-to-plane residual they buy, at several
residual budgets, on the shared real KITTI Velodyne sweep (skipped if absent) and on a synthetic
room with boxes sampled to 1 M points; plus the 1 M point timing with default settings.

Run: .venv/bin/python benchmarks/sogmm.py   (its section of benchmarks/RESULTS.md, plot in benchmarks/plots/)
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import markdown_table, save_plot, write_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
KITTI = ROOT.parent / "shared" / "data" / "kitti-velodyne" / "000000.bin"


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


def cylinder_surface(centre, radius, height, n: int, rng):
    """n points on the side of a vertical cylinder standing on z = centre z -> (points, normals)."""
    phi = rng.uniform(0, 2 * np.pi, n)
    nrm = np.c_[np.cos(phi), np.sin(phi), np.zeros(n)]
    p = np.asarray(centre, float) + radius * nrm
    p[:, 2] += rng.uniform(0, height, n)
    return p, nrm


def sphere_surface(centre, radius, n: int, rng):
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(centre, float) + radius * d, d


def synthetic_room(n: int, seed: int = 0, noise: float = 0.003):
    """A 6 x 5 x 3 m room (floor, walls, ceiling) with 6 boxes, 2 cylinders and a ball on the floor:
    n points in all, area-uniform, with Gaussian noise along the normal and a grey value per surface.
    Returns points [n, 4] (x, y, z, grey) float32 and true normals [n, 3]."""
    rng = np.random.default_rng(seed)
    shapes = [("box", ([0, 0, 0], [6, 5, 3]), True)]     # room, normals inward
    for i in range(6):
        size = rng.uniform([0.3, 0.3, 0.2], [1.2, 0.9, 1.0])
        corner = np.r_[rng.uniform(0.2, 5.8 - size[0]), rng.uniform(0.2, 4.8 - size[1]), 0.0]
        shapes.append(("box", (corner, corner + size), False))
    shapes.append(("cyl", ([4.8, 1.0, 0.0], 0.25, 1.2), False))
    shapes.append(("cyl", ([1.2, 4.0, 0.0], 0.12, 0.8), False))
    shapes.append(("ball", ([3.0, 2.5, 0.4], 0.4), False))

    def area(kind, args):
        if kind == "box":
            e = np.asarray(args[1], float) - np.asarray(args[0], float)
            return 2 * (e[0] * e[1] + e[0] * e[2] + e[1] * e[2])
        if kind == "cyl":
            return 2 * np.pi * args[1] * args[2]
        return 4 * np.pi * args[1] ** 2

    areas = np.array([area(k, a) for k, a, _ in shapes])
    counts = np.floor(n * areas / areas.sum()).astype(int)
    counts[0] += n - counts.sum()
    pts, nrms, greys = [], [], []
    for (kind, args, inward), c in zip(shapes, counts):
        if kind == "box":
            p, q = box_surface(args[0], args[1], c, rng, inward=inward)
        elif kind == "cyl":
            p, q = cylinder_surface(*args, c, rng)
        else:
            p, q = sphere_surface(*args, c, rng)
        pts.append(p), nrms.append(q), greys.append(np.full(c, rng.uniform(0.1, 0.9)))
    p, q, g = np.concatenate(pts), np.concatenate(nrms), np.concatenate(greys)
    p = p + rng.normal(0.0, noise, (len(p), 1)) * q
    return np.c_[p, g].astype(np.float32), q


def run_case(name, pts, budgets, rows, curve, normals=None, **kw):
    """Fit at each residual budget; one table row per fit. With true normals [N,3], also the fraction
    of points whose component normal is within 10 degrees of the truth."""
    from psimap.geometry import fit_sogmm

    fits = []
    for b in budgets:
        t = time.perf_counter()
        g = fit_sogmm(pts, residual=b, **kw)
        wall = time.perf_counter() - t
        s = g.fit_stats
        good = "-"
        if normals is not None:
            lab = g.assign(pts[:, :3])
            good = f"{(np.abs((g.normals[lab] * normals).sum(1)) > np.cos(np.radians(10))).mean():.3f}"
        rows.append([name, len(pts), s["n_points"], f"{s['voxel'] * 100:.2f}",
                     f"{b * 100:.2f}" if b else f"auto {s['residual_budget'] * 100:.2f}", s["K"],
                     f"{s['residual_mean'] * 1000:.2f}", good, f"{wall:.2f}"])
        if b:
            curve.setdefault(name, []).append((s["residual_budget"], s["K"], wall))
        print(rows[-1], flush=True)
        fits.append(g)
    return fits


def near_residual(g, pts, voxel: float, radius: float) -> float:
    """Mean point-to-plane distance of the (downsampled) points within `radius` m of the sensor."""
    from psimap.geometry import voxel_downsample

    p = voxel_downsample(np.asarray(pts, np.float64), voxel)
    p = p[np.linalg.norm(p[:, :2], axis=1) < radius]
    lab = g.assign(p)
    return float(np.abs(((p[:, :3] - g.means[lab, :3]) * g.normals[lab]).sum(1)).mean())


def main() -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from psimap.geometry import fit_sogmm, lidar_points

    rows, curve = [], {}
    notes = []
    if KITTI.exists():
        kitti = lidar_points(np.fromfile(KITTI, dtype=np.float32).reshape(-1, 4))
        fits = run_case("KITTI 000000, 5 cm voxel", kitti, [0.2, 0.05, 0.02], rows, curve, voxel=0.05)
        run_case("KITTI 000000, all auto", kitti, [None], rows, curve)
        near = near_residual(fits[-1], kitti, 0.05, 10.0)
        notes.append("KITTI: the mean residual can stay above small budgets because far returns lie on "
                     "sparse rings whose components reach min_points (8) before the budget; within 10 m "
                     f"of the sensor the 2 cm-budget fit has a {near * 100:.2f} cm mean residual.")
    else:
        notes.append(f"KITTI sweep not found at {KITTI}: skipped.")
    room, room_normals = synthetic_room(1_000_000)
    # budgets at a fixed 1 cm voxel and a loose 1 m extent cap, so K follows the budget
    run_case("room 1M pts, 1 cm voxel", room, [0.03, 0.01, 0.004], rows, curve, normals=room_normals,
             voxel=0.01, max_extent=1.0)
    # the 1 M point timing with every setting automatic, and with no downsampling at all
    run_case("room 1M pts, all auto", room, [None], rows, curve, normals=room_normals)
    run_case("room 1M pts, no downsampling", room, [0.004], rows, curve, normals=room_normals, voxel=0.0)

    header = ["cloud", "input pts", "fitted pts", "voxel cm", "budget cm", "K", "mean pt-to-plane mm",
              "normals within 10 deg", "fit time s"]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for name, pts in curve.items():
        if len(pts) < 2:
            continue
        b, k, t_s = (np.array(v) for v in zip(*pts))
        axes[0].plot(b * 100, k, "o-", label=name)
        axes[1].plot(b * 100, t_s, "o-", label=name)
    axes[0].set(xlabel="residual budget (cm)", ylabel="components K", xscale="log", yscale="log")
    axes[1].set(xlabel="residual budget (cm)", ylabel="fit time (s)", xscale="log")
    for ax in axes:
        ax.legend()
        ax.grid(alpha=0.3)
    fig.suptitle("SOGMM: K and fit time vs point-to-plane budget")
    fig.tight_layout()
    png = save_plot(fig, "sogmm")
    notes.append("Synthetic room: 6x5x3 m, 6 boxes, 2 cylinders, a ball; 3 mm noise along the normal "
                 "(mean |noise| 2.4 mm). Budget sweep rows use max_extent = 1 m. "
                 "Fit time = the fit_sogmm call, voxel downsampling included (the normals check is "
                 "not timed). No-downsampling row: every point fitted, the budget near the noise level. "
                 "Target: <= 30 s for 1 M points on this machine (2 cores).")
    auto = next(r for r in rows if r[0] == "room 1M pts, all auto")
    write_section("sogmm", "SOGMM prior: fit time, K and residual vs budget",
                  markdown_table(header, rows) + "\n\n" + " ".join(notes),
                  headlines=[("fit of 1 M points, all auto (target <= 30 s)",
                              f"{auto[8]} s, K {auto[5]}, mean residual {auto[6]} mm")],
                  plot=png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
