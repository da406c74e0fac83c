"""Constraints every completion result must meet, and the re-check that measures them.

1. Observed free space stays free: cells of the result that a camera saw empty are carved out
   (voxel domain at the tolerance pitch; the cells holding observed points are kept).
2. No intersection with neighbours or the background: exact boolean difference (manifold3d) with
   every closed obstacle, and a trim by every background plane the observation lies in front of.
3. Consistency with the observation: the share of observed points within tolerance of the result
   surface is measured and reported.
"""
from __future__ import annotations

import numpy as np


def carve_free(mesh, points: np.ndarray, free_fn, pitch: float):
    """Remove the known-free cells (of `pitch`, coarser past meshops.CUT_CELLS cells) from closed
    `mesh` by an exact boolean difference with the closed surface around them, so the rest of the
    surface keeps its shape. Cells holding observed points are never removed. Returns a closed mesh
    (or None when nothing is left)."""
    from .meshops import CUT_CELLS, from_manifold, grid_points, occupancy_to_mesh, to_manifold

    lo, hi = mesh.bounds
    # The grid reaches past the mesh so the cutter also covers the shell of boundary cells.
    centres, shape, origin, pitch = grid_points(lo - 2 * pitch, hi + 2 * pitch, pitch, max_cells=CUT_CELLS)
    free = free_fn(centres).reshape(shape)
    idx = np.clip(np.floor((points - origin) / pitch + 0.5).astype(int), 0, np.array(shape) - 1)
    free[tuple(idx.T)] = False
    if not free.any():
        return mesh
    cutter = occupancy_to_mesh(free, origin, pitch)
    if cutter is None:
        return mesh
    man = to_manifold(mesh) - to_manifold(cutter)
    return None if man.is_empty() else from_manifold(man)


def attach_outliers(mesh, points: np.ndarray, tolerance: float, min_points: int = 20):
    """Observed parts a fitted shape leaves outside (a mug's handle on a cylinder) are added back:
    each cluster of outside points, with its nearest points on the shape, becomes a convex hull
    unioned onto the shape. Returns the new closed mesh and the number of parts added."""
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    from .meshops import (closest_points, convex_hull, distance_to_surface, from_manifold, inside,
                          raycasting_scene, to_manifold)

    scene = raycasting_scene(mesh)          # one index for the distances, the parity and the anchors
    far = distance_to_surface(points, mesh, scene) > 2 * tolerance
    far &= ~inside(points, mesh, scene)
    if far.sum() < min_points:
        return mesh, 0
    out = points[far]
    pairs = cKDTree(out).query_pairs(2.5 * tolerance, output_type="ndarray")
    from scipy.sparse import coo_matrix

    adj = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(out), len(out)))
    n, lab = connected_components(adj, directed=False)
    man, added = to_manifold(mesh), 0
    if man.is_empty():      # not an oriented 2-manifold: a union would keep only the added parts
        return mesh, 0
    for k in range(n):
        part = out[lab == k]
        if len(part) < min_points:
            continue
        anchor = closest_points(part, mesh, scene)
        hull = convex_hull(np.concatenate([part, anchor]))
        if hull is not None and hull.volume > 0:        # None: a degenerate (flat) cluster
            man = man + to_manifold(hull)
            added += 1
    if not added:
        return mesh, 0
    merged = from_manifold(man)
    # a union that came back empty or open (the shape did not convert cleanly) adds nothing
    if len(merged.faces) == 0 or not merged.is_watertight:
        return mesh, 0
    return merged, added


def blocking_planes(planes, points: np.ndarray, tolerance: float):
    """Planes the whole observation lies in front of (within tolerance): the result must too."""
    return [(n, d) for n, d in planes if (points @ n - d).min() >= -tolerance]


def subtract_obstacles(mesh, obstacles, planes, points: np.ndarray, manifolds=None):
    """mesh minus every closed obstacle mesh, trimmed to the front of every plane (n, d).
    manifolds: the obstacles already converted by `to_manifold` (converted here when None).

    Of the pieces left, keeps those that hold observed points and the largest (only the first piece
    when no points are given). Returns trimesh or None.
    """
    from scipy.spatial import cKDTree

    from .meshops import from_manifold, signed_volume, to_manifold

    man = to_manifold(mesh)
    for n, d in planes:
        man = man.trim_by_plane(tuple(float(x) for x in n), float(d))
    for k, ob in enumerate(obstacles):
        if ob is None:
            continue
        lo, hi = ob.bounds
        mlo, mhi = mesh.bounds
        if (hi < mlo).any() or (lo > mhi).any():
            continue
        man = man - (manifolds[k] if manifolds is not None else to_manifold(ob))
    if man.is_empty():
        return None
    pieces = [from_manifold(p) for p in man.decompose()]
    # the pieces' volumes from one triple-product sum each (trimesh's `volume` computes every mass
    # property)
    volume = [signed_volume(p.vertices, p.faces) if len(p.faces) else 0.0 for p in pieces]
    pieces = [p for p, v in zip(pieces, volume) if v > 0]
    volume = [v for v in volume if v > 0]
    if not pieces:
        return None
    if len(pieces) > 1 and len(points):
        import trimesh

        largest = max(volume)
        keep = []
        for p, v in zip(pieces, volume):
            # a piece holds observed points when some point is near one of its vertices (one tree
            # of the points asked for every piece's vertices instead was slower on chess: a few
            # pieces of many vertices each)
            d, _ = cKDTree(p.vertices).query(points, k=1)
            if d.min() <= 3 * np.sqrt(p.area / max(len(p.faces), 1)) + 1e-9 or v >= largest:
                keep.append(p)
        pieces = keep
        return trimesh.util.concatenate(pieces) if len(pieces) > 1 else pieces[0]
    return pieces[0]


def check(mesh, points: np.ndarray, tolerance: float, obstacles=(), planes=(), free_fn=None,
          pitch: float | None = None) -> dict:
    """Measured constraint state of a closed result mesh (all volumes in m³, distances in m)."""
    from .coverage import fit_quality
    from .meshops import volume_of_intersection

    rms, inliers = fit_quality(mesh, points, tolerance)
    col = [volume_of_intersection(mesh, ob) for ob in obstacles if ob is not None]
    depth = 0.0
    for n, d in planes:
        depth = max(depth, float(-(mesh.vertices @ n - d).min()))
    out = {"fit_rms": rms, "observed_on_surface": inliers,
           "collision_volume": float(sum(col)), "plane_penetration": depth,
           "watertight": bool(mesh.is_watertight)}
    if free_fn is not None:
        from .freespace import free_space_share

        out["free_space_fraction"] = free_space_share(mesh, free_fn, pitch or tolerance)
    return out
