"""Rotational symmetry: detect a surface of revolution in the observed points and revolve it.

Bottles, cans, bowls, cups and vases seen from one side show part of every horizontal circle of
their outer surface. With a support plane the axis is the support normal (they stand on it);
without one each principal axis of the points is tried. Per axial slice (2 tolerances thick) a
circle fit gives a centre; the axis passes through the median centre. The outer radius profile is
a high percentile of the radial distance per slice (inner walls seen through an opening lie inside
it and are carved back by the free-space constraint). The fit is accepted when most points lie on
the profile within tolerance, none lie far outside, and the points span a wide enough arc for the
circle fits to mean something.
"""
from __future__ import annotations

import numpy as np

from .primitives import at_most, axis_frame, circle_fit, circle_sections, principal_axes, support_level
from .support import UP

_MIN_ARC_DEG = 90.0     # narrower arcs do not pin the axis down


def fit_revolution(points: np.ndarray, tolerance: float, support=None):
    """Returns (closed trimesh, stats dict) or (None, stats dict with the reason)."""
    import trimesh

    axes = [UP] if support is not None else list(principal_axes(points))
    best = None
    for axis in axes:
        R = axis_frame(np.asarray(axis, dtype=np.float64))
        local = points @ R
        z = local[:, 2]
        step = max(2 * tolerance, np.ptp(z) / 200)
        n_slices = max(int(np.ceil(np.ptp(z) / step)), 1)
        sl = np.minimum(((z - z.min()) / step).astype(int), n_slices - 1)
        centres = []
        for k in range(n_slices):
            xy = local[sl == k, :2]
            if len(xy) >= 8:
                c = circle_fit(xy)
                if c is not None and c[1] < 5 * np.ptp(local[:, :2], axis=0).max():
                    centres.append(c[0])
        if len(centres) < 2:
            continue
        c2 = np.median(np.array(centres), axis=0)
        rel = local[:, :2] - c2
        radial = np.linalg.norm(rel, axis=1)
        ang = np.degrees(np.arctan2(rel[:, 1], rel[:, 0]))
        arc = 10.0 * np.unique(np.floor(ang / 10.0)).size
        profile = np.full(n_slices, np.nan)
        for k in range(n_slices):
            r_k = radial[sl == k]
            if len(r_k):
                profile[k] = np.percentile(r_k, 90)
        ok = np.isfinite(profile)
        profile = np.interp(np.arange(n_slices), np.flatnonzero(ok), profile[ok])
        on = np.abs(radial - profile[sl]) <= tolerance
        outside = radial > profile[sl] + 2 * tolerance
        stats = {"arc_deg": float(arc), "on_profile": float(on.mean()), "outside": float(outside.mean())}
        score = on.mean() - outside.mean()
        if best is None or score > best[0]:
            best = (score, R, c2, z.min(), z.max(), step, profile, stats)
    if best is None:
        return None, {"reason": "too few points per slice for a circle fit"}
    _, R, c2, z0, z1, step, profile, stats = best
    if stats["arc_deg"] < _MIN_ARC_DEG:
        return None, {**stats, "reason": f"points span only {stats['arc_deg']:.0f} deg around the axis"}
    if stats["on_profile"] < 0.6 or stats["outside"] > 0.05:
        return None, {**stats, "reason": "points do not lie on one surface of revolution"}
    zs = np.minimum(z0 + step * (np.arange(len(profile)) + 0.5), z1)
    bottom, top = z0, z1
    s = support_level(support, R[:, 2], R @ np.array([c2[0], c2[1], 0.0]))
    if s is not None and s < bottom:
        bottom = s
    r = np.concatenate([[profile[0]], profile, [profile[-1]]])
    h = np.concatenate([[bottom], zs, [top]])
    line = np.concatenate([[[0.0, bottom]], np.stack([r, h], 1), [[0.0, top]]])
    mesh = trimesh.creation.revolve(line, sections=circle_sections(float(profile.max()), tolerance))
    if not mesh.is_watertight:
        return None, {**stats, "reason": "revolved profile is not closed"}
    if mesh.volume < 0:
        mesh.invert()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = R @ np.array([c2[0], c2[1], 0.0])
    mesh.apply_transform(T)
    return mesh, stats


# Reflective symmetry -----------------------------------------------------------------------------
# A mirror plane is credible when the mirrored observation lands on observed surface where both
# sides were seen (agreement) and never in space a camera saw empty (contradiction). The planes are
# vertical when the object stands on a support (man-made objects are symmetric about vertical
# planes), else spread over all directions. Up to two planes at least 30 deg apart are used, and
# their composition, so an object seen from one corner gets its three hidden quarters.
_MIN_AGREEMENT = 0.75
_MAX_CONTRADICTION = 0.05
_FREE_BATCH = 8         # candidate planes whose free-space test is asked in one call
_COARSE_POINTS = 150    # mirror_candidates' first pass
_COARSE_MARGIN = 0.15


def _reflect(points: np.ndarray, n: np.ndarray, d: float) -> np.ndarray:
    return points - 2.0 * (points @ n - d)[:, None] * n


def mirror_directions(standing: bool) -> np.ndarray:
    """The candidate mirror normals [D, 3]: vertical planes every 5 deg for an object standing on a
    support, else directions spread over a half sphere."""
    from .coverage import fibonacci_directions

    if standing:
        th = np.radians(np.arange(0.0, 180.0, 5.0))
        return np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], 1)
    normals = fibonacci_directions(128)
    return normals[normals[:, 2] >= 0]


def _agreements(tree, pts: np.ndarray, normals: np.ndarray, offsets: np.ndarray, tolerance: float) -> np.ndarray:
    """[K] share of pts [P, 3] whose reflection about plane k (normals [K, 3], offsets [K]) lands
    within 1.5 tolerances of the tree's points: every plane's reflection (_reflect's arithmetic)
    in one query (a 6 cm object's planes took ~1 s in 1,000 small queries)."""
    if len(normals) == 0:
        return np.zeros(0)
    u = np.stack([pts @ n for n in normals])        # [K, P] (a matrix product may round otherwise)
    m = pts[None] - 2.0 * (u - offsets[:, None])[..., None] * normals[:, None, :]
    dist, _ = tree.query(m.reshape(-1, 3), k=1, distance_upper_bound=1.5 * tolerance)
    return np.isfinite(dist).reshape(len(normals), len(pts)).mean(-1)


def mirror_candidates(points: np.ndarray, tolerance: float, standing: bool, max_points: int = 600,
                      seed: int = 0, exhaustive: bool = False) -> list:
    """The credible planes of points [P, 3] before the free-space test: (agreement, n [3], d) of each
    candidate direction whose best of 17 offsets reaches _MIN_AGREEMENT, best first (the first
    best offset of a direction; ties keep the direction order).

    Every (direction, offset) is first scored on _COARSE_POINTS of the max_points sample, and only
    those within _COARSE_MARGIN of both _MIN_AGREEMENT and their direction's best are scored on the
    whole sample (exhaustive: all of them, the reference the tests hold this to). The coarse sample
    is a subset of the whole, so a plane whose whole-sample share reaches _MIN_AGREEMENT, or that
    of its direction's best, misses the margin on it with a chance of ~1e-6 (4 sigma of a 150-point
    share). The whole-sample scan was 15 of a real capture's 146 s export (34 objects, ~0.4 s each)."""
    from scipy.spatial import cKDTree

    sub = at_most(points, max_points, seed)
    tree = cKDTree(points)
    normals = mirror_directions(standing)
    u = np.stack([sub @ n for n in normals], 1)
    offsets = np.linspace(u.min(0), u.max(0), 19)[1:-1].T                         # [D, 17]
    rows = np.repeat(np.arange(len(normals)), offsets.shape[1])
    if exhaustive or len(sub) <= _COARSE_POINTS:
        ask = np.ones(offsets.shape, bool)
    else:
        coarse = _agreements(tree, at_most(sub, _COARSE_POINTS, seed + 1), normals[rows], offsets.ravel(),
                             tolerance).reshape(offsets.shape)
        ask = coarse >= np.maximum(_MIN_AGREEMENT, coarse.max(1, keepdims=True)) - _COARSE_MARGIN
    score = np.full(offsets.shape, -1.0)
    k, j = np.nonzero(ask)
    score[k, j] = _agreements(tree, sub, normals[k], offsets[k, j], tolerance)
    best = score.argmax(1)                          # the first of equals, as the scan kept it
    found = [(float(score[k, best[k]]), normals[k], float(offsets[k, best[k]])) for k in range(len(normals))]
    found.sort(key=lambda f: -f[0])
    return [f for f in found if f[0] >= _MIN_AGREEMENT]


def mirror_planes(points: np.ndarray, tolerance: float, support=None, free_fn=None,
                  max_points: int = 600, seed: int = 0):
    """Credible mirror planes of points [P, 3]. Returns (list of (n [3], d, agreement), stats)."""
    sub = at_most(points, max_points, seed)
    found = mirror_candidates(points, tolerance, support is not None, max_points, seed)
    contradicted: dict = {}
    planes = []
    for i, (agree, n, d) in enumerate(found):
        if len(planes) == 2:
            break
        if any(abs(n @ q[0]) > np.cos(np.radians(30.0)) for q in planes):
            continue
        if free_fn is not None:
            if i not in contradicted:
                # the next few candidates' free-space tests in one call (free_fn answers per point):
                # a small object agrees with most of its reflections, and dozens of them, each
                # contradicted, were tested one call at a time (~1-2 s an object on a real capture)
                ahead = range(i, min(i + _FREE_BATCH, len(found)))
                mirrored = np.concatenate([_reflect(sub, found[j][1], found[j][2]) for j in ahead])
                share = np.asarray(free_fn(mirrored), dtype=bool).reshape(len(ahead), -1).mean(1)
                contradicted.update({j: bool(s > _MAX_CONTRADICTION) for j, s in zip(ahead, share)})
            if contradicted[i]:
                continue
        planes.append((n, d, agree))
    stats = {"mirror_planes": len(planes), "agreement": [round(p[2], 3) for p in planes]}
    return planes, stats


def mirrored_points(points: np.ndarray, planes) -> np.ndarray:
    """points [P, 3] with their images under each plane and under the composition of two."""
    out = [points]
    for n, d, _ in planes:
        out.append(_reflect(points, n, d))
    if len(planes) == 2:
        (n1, d1, _), (n2, d2, _) = planes
        out.append(_reflect(_reflect(points, n1, d1), n2, d2))
    return np.concatenate(out)
