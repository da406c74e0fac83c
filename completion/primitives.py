"""Primitive fits for heavily occluded objects: sphere, upright / principal-axis cylinder, box.

Each fit uses only the observed points [P, 3] (plus the support plane, if any, which closes the
hidden underside: the primitive is extended down to it). A fit returns a closed trimesh or None;
whether it is good enough is judged by the caller on the fit residual. Tessellation is chosen from
the tolerance (sagitta of the polygonal approximation below a twentieth of it), not a constant.
"""
from __future__ import annotations

import numpy as np

from .support import UP


def circle_sections(radius: float, tolerance: float) -> int:
    """Polygon sides so that the chord sagitta r(1 - cos(pi/n)) stays below tolerance / 20."""
    if radius <= 0:
        return 8
    c = np.clip(1 - 0.05 * tolerance / radius, -1, 1)
    return int(np.clip(np.ceil(np.pi / max(np.arccos(c), 1e-6)), 8, 256))


def fit_sphere(points: np.ndarray, tolerance: float):
    """Algebraic least-squares sphere: |p|² = 2 c·p + (r² - |c|²). Returns trimesh or None."""
    import trimesh

    fit = _kasa_fit(points)
    if fit is None:
        return None
    c, r = fit
    if r > 0.75 * np.ptp(points, axis=0).max():     # a gently curved patch, not a seen ball
        return None
    # Icosphere subdivision: edge ~ r * 1.1 / 2^s; sagitta ~ edge² / (8 r) <= tolerance / 20.
    sub = int(np.clip(np.ceil(np.log2(1.1 * r / np.sqrt(0.4 * r * tolerance + 1e-12))), 1, 5))
    m = trimesh.creation.icosphere(subdivisions=sub, radius=r)
    m.apply_translation(c)
    return m


def _kasa_fit(points: np.ndarray):
    """Algebraic (Kasa) circle / sphere fit of points [P, D]: |p|² = 2 c·p + (r² - |c|²).

    Returns (centre [D], radius) or None when the fit is degenerate.
    """
    d = points.shape[1]
    A = np.concatenate([2 * points, np.ones((len(points), 1))], axis=1)
    b = (points ** 2).sum(1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    c, k = sol[:d], sol[d]
    r2 = k + c @ c
    if not (np.isfinite(r2) and r2 > 0):
        return None
    return c, float(np.sqrt(r2))


def circle_fit(xy: np.ndarray):
    """Kasa circle fit of 2D points [P, 2]. Returns (centre [2], radius) or None."""
    return _kasa_fit(xy)


# The geometric circle refinement runs on at most this many of an object's points: its cost grows
# with the points (0.3 s a fit on a 30k-point real scan, 4.5 % of a 7-Scenes export), its answer
# does not past a few thousand (the noise averages out well below a tolerance)
CIRCLE_FIT_POINTS = 3000


def at_most(points: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """points [P, ...], or n of them drawn without replacement (the same n for the same input)."""
    if len(points) <= n:
        return points
    return points[np.random.default_rng(seed).choice(len(points), n, replace=False)]


def _robust_circle(xy: np.ndarray, init, tolerance: float):
    """Geometric circle fit (radial residuals, Cauchy loss) from an algebraic start: points on the
    caps lie inside the circle and would bias a plain least-squares fit. Returns (centre, radius)."""
    from scipy.optimize import least_squares

    c0, r0 = init

    def resid(x):
        return np.linalg.norm(xy - x[:2], axis=1) - x[2]

    sol = least_squares(resid, np.array([c0[0], c0[1], r0]), loss="cauchy", f_scale=0.2 * tolerance,
                        x_scale=max(r0, tolerance))
    if not (np.isfinite(sol.x).all() and sol.x[2] > 0):
        return c0, r0
    return sol.x[:2], float(sol.x[2])


def axis_frame(axis: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] whose third column is `axis` (unit)."""
    axis = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, axis)
    x /= np.linalg.norm(x)
    y = np.cross(axis, x)
    return np.stack([x, y, axis], axis=1)


def support_level(support, axis: np.ndarray, centre: np.ndarray):
    """Axial coordinate (along axis, from 0) where the line centre + s*axis meets the support."""
    if support is None:
        return None
    n, d = support
    denom = n @ axis
    if abs(denom) < 0.9:        # the support is not across this axis
        return None
    return (d - n @ centre) / denom


def principal_axes(points: np.ndarray) -> np.ndarray:
    """[3, 3] rows: the principal axes of points [P, 3], largest spread first. The thin SVD: the
    full one also builds a P x P matrix nobody reads (20k points: 3.2 GB, seconds of page faults)."""
    return np.linalg.svd(points - points.mean(0), full_matrices=False)[2]


def fit_cylinder(points: np.ndarray, tolerance: float, support=None):
    """Cylinder around the up axis (when a support exists) or the best principal axis."""
    import trimesh

    axes = [UP] if support is not None else list(principal_axes(points))
    best, best_res = None, np.inf
    for axis in axes:
        R = axis_frame(np.asarray(axis, dtype=np.float64))
        local = points @ R
        circ = circle_fit(local[:, :2])
        if circ is None:
            continue
        c2, r = _robust_circle(at_most(local[:, :2], CIRCLE_FIT_POINTS), circ, tolerance)
        rel = local[:, :2] - c2
        arc = 10.0 * np.unique(np.floor(np.degrees(np.arctan2(rel[:, 1], rel[:, 0])) / 10.0)).size
        # A flat face is a circle of huge radius: demand a real arc (>= 90 deg, r <= 0.75 extent).
        if r > 0.75 * np.ptp(local[:, :2], axis=0).max() or arc < 90.0:
            continue
        res = np.median(np.abs(np.linalg.norm(local[:, :2] - c2, axis=1) - r))
        if res < best_res:
            best_res, best = res, (R, c2, r, local[:, 2].min(), local[:, 2].max())
    if best is None:
        return None
    R, c2, r, z0, z1 = best
    centre_line = R @ np.array([c2[0], c2[1], 0.0])
    s = support_level(support, R[:, 2], centre_line)
    if s is not None:
        z0 = min(z0, s) if s < z1 else z0
    if z1 - z0 <= 0:
        return None
    m = trimesh.creation.cylinder(radius=r, height=z1 - z0, sections=circle_sections(r, tolerance))
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = R @ np.array([c2[0], c2[1], 0.5 * (z0 + z1)])
    m.apply_transform(T)
    return m


def fit_box(points: np.ndarray, tolerance: float, support=None, planes=()):
    """Box: up-aligned minimum-area footprint rectangle down to the support, or the minimum-volume
    oriented box without one. A side face nobody saw (no point on it) is pushed out to a parallel
    background plane (a wall) when one lies within half the box's extent behind it."""
    import trimesh

    if support is not None:
        T2, ext2 = trimesh.bounds.oriented_bounds_2D(points[:, :2])
        # T2 maps points into the rectangle frame (centred); build the 3D box frame from it.
        R2 = T2[:2, :2]
        R = np.eye(3)
        R[:2, :2] = R2.T
    else:
        T, _ = trimesh.bounds.oriented_bounds(points)
        R = T[:3, :3].T.copy()
    if np.linalg.det(R) < 0:      # keep a proper rotation so the box is not turned inside out
        R[:, 1] *= -1
    local = points @ R
    lo, hi = local.min(0), local.max(0)
    # Bounds sit on the noise's outer edge: move each seen face to the median of its points.
    for axis in range(3):
        for bound in (lo, hi):
            near = np.abs(local[:, axis] - bound[axis]) <= 2 * tolerance
            if near.sum() >= 20:
                bound[axis] = np.median(local[near, axis])
    if support is not None:
        s = support_level(support, R[:, 2], R @ np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), 0.0]))
        if s is not None and s < hi[2]:
            lo[2] = min(lo[2], s)
    ext = hi - lo
    for axis in range(3):
        for sign in (-1, 1):
            face = hi[axis] if sign > 0 else lo[axis]
            on_face = np.abs(local[:, axis] - face) <= tolerance
            if on_face.mean() > 0.02:
                continue
            direction = sign * R[:, axis]
            for n, d in planes:
                if n @ direction > -0.97:       # the plane must face back at this box face
                    continue
                centre = R @ (0.5 * (lo + hi))
                # Distance along `direction` from the face to the plane.
                face_point = centre + direction * 0.5 * ext[axis]
                gap = (n @ face_point - d)
                if 0 < gap <= 0.5 * ext.max():
                    if sign > 0:
                        hi[axis] += gap
                    else:
                        lo[axis] -= gap
                    break
    ext = hi - lo
    if (ext <= 1e-9).any():
        return None
    m = trimesh.creation.box(extents=ext)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = R @ (0.5 * (lo + hi))
    m.apply_transform(T)
    return m
