"""Completion benchmark: partial scans of objects on a table, against a wall, touching neighbours.

Scenes: synthetic objects (boxes, cylinder, mug, bottle) and, when ../shared/data/ycb exists, the
shared YCB scans. A few RGB-D viewpoints in front of and above the table are ray cast (Open3D
RaycastingScene, 1 mm depth noise); each object's observed points, its seen faces (the partial
scan) and the depth maps (observed free space) feed `psimap.completion.complete`.
Compared in one run: no completion (the partial scan), the convex hull of the partial scan, ours.
Metrics as the paper's completion table: CD-O / F-score-O (object vs its complete GT mesh, F at
1 cm), CD-S / F-score-S (all objects of a scene together), IoU-B (axis-aligned box IoU), Col-O /
Col-S (share of objects whose result intersects another object's GT / the table or wall by more
than 0.1 cm³ and 1 % of its volume), time per object. Writes its section of RESULTS.md and its
plot (benchmarks/plots/completion.png); --quick (synthetic scene only) and --no-append print only.

    .venv/bin/python benchmarks/completion.py [--quick]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import markdown_table, save_plot, write_section  # noqa: E402
from psimap.camera import look_at
from psimap.data.synthetic_shapes import solid_mug

SHARED_YCB = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ycb"
VOXEL = 0.005
F_THRESHOLD = 0.01
COL_VOLUME = 1e-7          # 0.1 cm³
WALL_Y = 0.25              # wall front face; table top is z = 0


def _solid(mesh):
    from psimap.completion.meshops import from_manifold, to_manifold

    return from_manifold(to_manifold(mesh))


def bottle_mesh():
    import trimesh

    prof = np.array([[0, 0], [0.032, 0], [0.035, 0.01], [0.035, 0.12], [0.02, 0.16], [0.013, 0.17],
                     [0.013, 0.2], [0, 0.2]])
    return trimesh.creation.revolve(prof, sections=64)


def synthetic_objects():
    import trimesh

    cyl = trimesh.creation.cylinder(0.035, 0.14, sections=64)
    cyl.apply_translation([0, 0, 0.07])
    box_a = trimesh.creation.box([0.12, 0.07, 0.16])
    box_a.apply_translation([0, 0, 0.08])
    box_b = trimesh.creation.box([0.08, 0.08, 0.06])
    box_b.apply_translation([0, 0, 0.03])
    return {"box_tall": box_a, "box_low": box_b, "can": cyl, "mug": solid_mug(), "bottle": bottle_mesh()}


def ycb_objects():
    import trimesh

    out = {}
    for d in sorted(SHARED_YCB.glob("*/textured.obj")):
        m = trimesh.load(d, force="mesh")
        m = _solid(trimesh.Trimesh(m.vertices, m.faces, process=True))
        m.apply_translation([0, 0, -m.bounds[0, 2]])
        out[d.parent.name] = m
    return out


def arrange(objects: dict):
    """Place objects on the table in a row along x, the first half backed against the wall, each
    touching the previous one (bounding boxes in contact). Returns dict name -> placed mesh."""
    placed, x = {}, 0.0
    names = list(objects)
    for i, name in enumerate(names):
        m = objects[name].copy()
        lo, hi = m.bounds
        dx = x - lo[0]
        dy = (WALL_Y - hi[1]) if i % 2 == 0 else (WALL_Y - 0.02 - hi[1] - 0.5 * (hi[1] - lo[1]))
        m.apply_translation([dx, dy, -lo[2]])
        placed[name] = m
        x = m.bounds[1, 0]
    shift = -0.5 * x
    for m in placed.values():
        m.apply_translation([shift, 0, 0])
    return placed


def background_mesh(half_width: float):
    import trimesh

    from psimap.completion.meshops import from_manifold, to_manifold

    table = trimesh.creation.box([2 * half_width + 0.4, 1.0, 0.05])
    table.apply_translation([0, WALL_Y - 0.5, -0.025])
    wall = trimesh.creation.box([2 * half_width + 0.4, 0.05, 0.8])
    wall.apply_translation([0, WALL_Y + 0.025, 0.35])
    return from_manifold(to_manifold(table) + to_manifold(wall))


def scan(placed: dict, background, n_views: int, rng):
    """Ray cast every view. Returns cameras, depths, per-object observed points and seen faces."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    ids = {}
    for name, m in placed.items():
        ids[scene.add_triangles(o3d.core.Tensor(m.vertices.astype(np.float32)),
                                o3d.core.Tensor(m.faces.astype(np.uint32)))] = name
    scene.add_triangles(o3d.core.Tensor(background.vertices.astype(np.float32)),
                        o3d.core.Tensor(background.faces.astype(np.uint32)))
    W, H, f = 320, 240, 280.0
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    centre = np.mean([m.bounds.mean(0) for m in placed.values()], axis=0)
    cams, depths = [], []
    pts = {n: [] for n in placed}
    seen = {n: np.zeros(len(m.faces), bool) for n, m in placed.items()}
    for k in range(n_views):
        az = np.radians(-90 + (k - (n_views - 1) / 2) * 35.0)
        eye = centre + np.array([0.7 * np.cos(az), 0.7 * np.sin(az), 0.45])
        c2w = look_at(eye, centre)
        u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
        dirs_c = np.stack([(u - K[0, 2]) / f, (v - K[1, 2]) / f, np.ones_like(u)], -1).reshape(-1, 3)
        dirs_w = dirs_c @ c2w[:3, :3].T
        rays = np.concatenate([np.broadcast_to(eye, dirs_w.shape), dirs_w], 1).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))
        t = hit["t_hit"].numpy().astype(np.float64)
        gid = hit["geometry_ids"].numpy()
        pid = hit["primitive_ids"].numpy()
        ok = np.isfinite(t)
        # Camera-frame ray directions have unit z, so t is the z-depth a depth sensor reports.
        z = np.where(ok, t + rng.normal(0, 0.001, t.shape), 0.0)
        depths.append(z.reshape(H, W))
        cams.append((K, c2w, W, H))
        p = eye + dirs_w * z[:, None]
        for g, name in ids.items():
            sel = ok & (gid == g)
            pts[name].append(p[sel])
            seen[name][pid[sel]] = True
    return cams, depths, {n: np.concatenate(v) for n, v in pts.items()}, seen


def bbox_iou(a, b) -> float:
    lo = np.maximum(a.bounds[0], b.bounds[0])
    hi = np.minimum(a.bounds[1], b.bounds[1])
    inter = np.prod(np.clip(hi - lo, 0, None))
    va, vb = np.prod(a.extents), np.prod(b.extents)
    return float(inter / (va + vb - inter)) if va + vb - inter > 0 else 0.0


def collides(result, other) -> bool:
    from psimap.completion.meshops import is_solid, volume_of_intersection

    if not is_solid(result):
        return False        # an open shell has no volume to intersect
    v = volume_of_intersection(result, other)
    return v > max(COL_VOLUME, 0.01 * result.volume)


def surface_metrics(pred, gt):
    from psimap.metrics.geometry import summarize, surface_distances

    d = surface_distances(pred, gt, thresholds=(F_THRESHOLD,), max_samples=20_000, min_samples=4_000)
    s = summarize(d, F_THRESHOLD)
    return s["chamfer_l1"], s["f1"]


def run_scene(tag: str, objects: dict, n_views: int, rng, log):
    import trimesh

    from psimap.completion import CompletionContext, complete

    placed = arrange(objects)
    half = max(abs(m.bounds[:, 0]).max() for m in placed.values())
    background = background_mesh(half)
    cams, depths, pts, seen = scan(placed, background, n_views, rng)
    rows = []
    results = {"none": {}, "hull": {}, "ours": {}}
    for name, gt in placed.items():
        p = pts[name]
        partial = gt.submesh([np.flatnonzero(seen[name])], append=True) if seen[name].any() else None
        neighbours = [gt_o.submesh([np.flatnonzero(seen[o])], append=True)
                      for o, gt_o in placed.items() if o != name and seen[o].any()]
        t0, c0 = time.perf_counter(), time.process_time()
        res = complete(partial, CompletionContext(points=p, voxel_size=VOXEL, label=name,
                                                  support_planes=[((0, 0, 1), 0.0), ((0, -1, 0), -WALL_Y)],
                                                  background=background, neighbours=neighbours,
                                                  cameras=cams, depths=depths))
        dt = time.perf_counter() - t0
        cpu = time.process_time() - c0
        hull = trimesh.convex.convex_hull(p) if len(p) >= 4 else partial
        results["none"][name] = (partial, 0.0, 0.0)
        results["hull"][name] = (hull, 0.0, 0.0)
        results["ours"][name] = (res.mesh, dt, cpu)
        log(f"{tag}/{name}: {res.method} ({dt:.2f} s) {res.reason[:160]}")
    for method, res in results.items():
        for name, (mesh, dt, cpu) in res.items():
            gt = placed[name]
            if mesh is None or len(mesh.faces) == 0:
                rows.append((tag, method, name, np.nan, 0.0, 0.0, False, False, dt, cpu))
                continue
            cd, f = surface_metrics(mesh, gt)
            col_o = any(collides(mesh, placed[o]) for o in placed if o != name)
            col_s = collides(mesh, background)
            rows.append((tag, method, name, cd, f, bbox_iou(mesh, gt), col_o, col_s, dt, cpu))
    scene_rows = {}
    gt_all = trimesh.util.concatenate(list(placed.values()))
    for method, res in results.items():
        meshes = [m for m, _, _ in res.values() if m is not None and len(m.faces)]
        scene_rows[method] = surface_metrics(trimesh.util.concatenate(meshes), gt_all)
    return rows, scene_rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="synthetic scene only; RESULTS.md untouched")
    ap.add_argument("--views", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-append", action="store_true", help="print only, do not touch RESULTS.md")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    scenes = [("synthetic", synthetic_objects())]
    if not args.quick and SHARED_YCB.is_dir():
        scenes.append(("ycb", ycb_objects()))
    elif not args.quick:
        print(f"note: {SHARED_YCB} absent, YCB scene skipped")
    all_rows, scene_level = [], {}
    for tag, objs in scenes:
        rows, srows = run_scene(tag, objs, args.views, rng, print)
        all_rows += rows
        scene_level[tag] = srows
    header = ["scene", "method", "CD-S (m)", "F-S", "CD-O (m)", "F-O", "IoU-B", "Col-O", "Col-S",
              "wall s / object", "CPU s / object", "objects"]
    table = []
    for tag, _ in scenes:
        for method in ("none", "hull", "ours"):
            r = [x for x in all_rows if x[0] == tag and x[1] == method]
            table.append([tag, method, scene_level[tag][method][0], scene_level[tag][method][1],
                          float(np.nanmean([x[3] for x in r])), float(np.mean([x[4] for x in r])),
                          float(np.mean([x[5] for x in r])), float(np.mean([x[6] for x in r])),
                          float(np.mean([x[7] for x in r])), float(np.mean([x[8] for x in r])),
                          float(np.mean([x[9] for x in r])), len(r)])
    per_obj = markdown_table(["scene", "method", "object", "CD-O", "F-O", "IoU-B", "Col-O", "Col-S",
                              "wall s", "CPU s"],
                             [list(x) for x in all_rows if x[1] == "ours"])
    md = markdown_table(header, table)
    notes = (f"{args.views} views, 320x240, 1 mm depth noise, voxel {VOXEL * 1000:.0f} mm, F at "
             f"{F_THRESHOLD * 100:.0f} cm. none = partial scan (open: no volume, so never counted as "
             "colliding), hull = convex hull of the partial scan. Neighbours are passed as the other "
             "objects' partial scans, background = table + wall. Time = complete() per object on a "
             "2-core CPU shared with other jobs (wall clock and process CPU time).\n\nOurs per object:\n\n" + per_obj)
    if args.no_append or args.quick:
        print(md)
        print(notes)
        return 0
    heads = []
    for tag, _ in scenes:
        ours, hull = (next(r for r in table if r[0] == tag and r[1] == m) for m in ("ours", "hull"))
        heads.append((f"{tag}: F-score-O @ 1 cm, ours vs convex hull; CPU s per object",
                      f"{ours[5]:.4f} vs {hull[5]:.4f}; {ours[10]:.2f} s"))
    write_section("completion", "Completion (issue 8): partial scans vs convex hull vs psimap.completion",
                  md + "\n\n" + notes, headlines=heads, plot=save_plot(_plot(all_rows), "completion"))
    return 0


def _plot(rows):
    """F-score-O per object and method, as a bar chart (the figure, not yet saved)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    names = sorted({(x[0], x[2]) for x in rows})
    w = 0.27
    for k, method in enumerate(("none", "hull", "ours")):
        vals = [next(x[4] for x in rows if x[1] == method and (x[0], x[2]) == n) for n in names]
        ax.bar(np.arange(len(names)) + (k - 1) * w, vals, w, label=method)
    ax.set_xticks(np.arange(len(names)), [n[1] for n in names], rotation=45, ha="right")
    ax.set_ylabel(f"F-score-O @ {F_THRESHOLD * 100:.0f} cm")
    ax.legend()
    fig.tight_layout()
    return fig


if __name__ == "__main__":
    sys.exit(main())
