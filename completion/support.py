"""Support planes and support-aware closing.

Planes are (n [3] unit, d) with the plane {x : n·x = d} and n pointing to the object's side. They
come from `context["support_planes"]` and from the background mesh (rays cast from the object's
centre hit the floor / table / wall; the hit face gives the plane).

Support-aware closing (the fallback that works for any shape): every observed point fills its
vertical column down to the supporting surface (objects rest on something; the hidden underside
lies between the seen top and the support), the 2D footprint's holes are filled, and space that a
camera saw empty is carved away again. Without a support the closed shape is the convex hull of the
observed points, carved the same way.
"""
from __future__ import annotations

import numpy as np

from psimap import PsimapError

UP = np.array([0.0, 0.0, 1.0])     # world frame is Z-up (docs/conventions.md)
_SUPPORT_COS = np.cos(np.radians(30.0))


def normalise_planes(raw, centre: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Validate planes given as (normal [3], offset) and orient them towards `centre` [3]."""
    planes = []
    for i, item in enumerate(raw or []):
        try:
            n, d = item
            n = np.asarray(n, dtype=np.float64).reshape(3)
            d = float(d)
        except (TypeError, ValueError) as e:
            raise PsimapError(f"completion context: support_planes[{i}] must be (normal [3], offset)") from e
        norm = np.linalg.norm(n)
        if not (np.isfinite(n).all() and np.isfinite(d) and norm > 1e-12):
            raise PsimapError(f"completion context: support_planes[{i}] has a zero or non-finite normal")
        n, d = n / norm, d / norm
        if n @ centre - d < 0:
            n, d = -n, -d
        planes.append((n, d))
    return planes


def planes_from_background(background, points: np.ndarray, reach: float,
                           radius: float = 0.03) -> list[tuple[np.ndarray, float]]:
    """Planes of the background surfaces the object faces: rays from the centre of points [P, 3]
    along ±x, ±y, and straight down from a 3 x 3 ring of origins around it (the floor right under
    an object was never seen, so a scan has a hole there), hit the background within `reach`; each
    hit gives a plane fitted (PCA) to the background vertices within `radius` of it — a scanned
    (TSDF) surface's single facets tilt with the noise; near-duplicates are merged."""
    import open3d as o3d

    from scipy.spatial import cKDTree

    from .meshops import cached_on, raycasting_scene

    if background is None or len(background.faces) == 0:
        return []
    lo, hi = points.min(0), points.max(0)
    centre = 0.5 * (lo + hi)
    r = 0.75 * float((hi - lo)[:2].max()) + 1e-6
    origins = [centre] * 4 + [centre + [dx, dy, 0.0] for dx in (-r, 0.0, r) for dy in (-r, 0.0, r)]
    dirs = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]] + [[0, 0, -1]] * 9
    origins, dirs = np.asarray(origins, dtype=np.float64), np.asarray(dirs, dtype=np.float64)
    rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
    # one index of the background for every object it supports
    scene = cached_on(background, "psimap.raycasting_scene", lambda: raycasting_scene(background))
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy()
    normals = hit["primitive_normals"].numpy().astype(np.float64)
    verts = np.asarray(background.vertices, dtype=np.float64)
    tree = cached_on(background, "psimap.vertex_tree", lambda: cKDTree(verts))
    planes: list[tuple[np.ndarray, float]] = []
    for k in range(len(dirs)):
        if not (np.isfinite(t[k]) and t[k] <= reach):
            continue
        p = origins[k] + t[k] * dirs[k]
        n = normals[k] / max(np.linalg.norm(normals[k]), 1e-12)
        near = verts[tree.query_ball_point(p, radius)]
        if len(near) >= 6:
            q = near - near.mean(0)
            fitted = np.linalg.svd(q, full_matrices=False)[2][2]
            if abs(fitted @ n) > 0.5:           # same surface, denoised orientation
                n = fitted if fitted @ n > 0 else -fitted
        # Median offset of the patch: a scan's hole rims curl away and would drag a mean.
        d = float(np.median(near @ n)) if len(near) >= 6 else float(n @ p)
        if n @ centre - d < 0:
            n, d = -n, -d
        if any(n @ q > 0.98 and abs(d - e) < 0.01 for q, e in planes):
            continue
        planes.append((n, d))
    return planes


def support_below(planes, points: np.ndarray, reach: float, tolerance: float = 0.0):
    """The nearest plane under points [P, 3] that faces up: the lowest point lies above it by at
    most `reach` and below it by at most `tolerance` (noise), so a plane through the object is not
    taken for its support."""
    best, best_gap = None, np.inf
    for n, d in planes:
        if n @ UP < _SUPPORT_COS:
            continue
        gap = float((points @ n - d).min())
        if -tolerance <= gap <= reach and gap < best_gap:
            best, best_gap = (n, d), gap
    return best


def support_closing(points: np.ndarray, pitch: float, support, free_fn=None, keep=None):
    """Closed mesh from points [P, 3]: columns down to `support` (n, d) (or the convex hull when
    None), minus cells that free_fn(centres [Q,3]) -> [Q] bool says were seen empty, except cells
    holding a `keep` point [K, 3] (default: all points; pass the observed ones when `points` also
    holds inferred ones)."""
    from scipy import ndimage
    from scipy.spatial import ConvexHull, Delaunay

    from .meshops import CUT_CELLS, grid_points, occupancy_to_mesh

    lo, hi = points.min(0), points.max(0)
    if support is not None:
        n, d = support
        # Lowest point on the support plane under the object: extend the box down to it.
        z_plane = (d - lo[:2] @ n[:2]) / n[2] if abs(n[2]) > 1e-9 else lo[2]
        lo = lo.copy()
        lo[2] = min(lo[2], float(z_plane))
    # at most CUT_CELLS cells: large furniture closes on a coarser grid (work bounded per object)
    centres, shape, origin, pitch = grid_points(lo - pitch, hi + pitch, pitch, max_cells=CUT_CELLS)
    idx = np.clip(np.floor((points - origin) / pitch + 0.5).astype(int), 0, np.array(shape) - 1)
    if support is not None:
        n, d = support
        top = np.full(shape[:2], -1, dtype=int)
        np.maximum.at(top, (idx[:, 0], idx[:, 1]), idx[:, 2])
        seen = top >= 0
        footprint = ndimage.binary_fill_holes(ndimage.binary_closing(seen, iterations=2) | seen)
        # Unseen footprint cells take the height of the nearest seen column.
        _, (ii, jj) = ndimage.distance_transform_edt(~seen, return_indices=True)
        top = np.where(footprint, top[ii, jj], -1)
        k = np.arange(shape[2])[None, None, :]
        occ = k <= top[:, :, None]
        occ &= (centres @ n - d >= -0.5 * pitch).reshape(shape)
    else:
        try:
            hull = Delaunay(points[ConvexHull(points).vertices])
        except Exception:       # coplanar / degenerate: nothing to close
            return None
        occ = (hull.find_simplex(centres) >= 0).reshape(shape)
        occ[tuple(idx.T)] = True
    if free_fn is not None:
        flat = occ.reshape(-1)
        cand = np.flatnonzero(flat)
        flat[cand[free_fn(centres[cand])]] = False
        occ = flat.reshape(shape)
        if keep is not None:
            idx = np.clip(np.floor((keep - origin) / pitch + 0.5).astype(int), 0, np.array(shape) - 1)
        occ[tuple(idx.T)] = True    # observed surface cells stay
    occ = ndimage.binary_fill_holes(occ)
    return occupancy_to_mesh(occ, origin, pitch)
