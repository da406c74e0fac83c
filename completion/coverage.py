"""How much of an object was observed, and how well a candidate shape explains the observation.

Two coverage estimates:
- directional: share of view directions from the object's centre (a Fibonacci sphere of
  directions) along which some observed point lies; cheap, needs no candidate, decides whether a
  completion is attempted at all;
- surface: share of a candidate completed surface that lies within tolerance of an observed point;
  reported for the chosen candidate (how much of the result was seen).
"""
from __future__ import annotations

import numpy as np

# 256 directions ~ 12.7 deg apart; a direction is covered when a point lies within 1.2 spacings.
_N_DIRS = 256
_CONE = 1.2 * np.sqrt(4 * np.pi / _N_DIRS)


def fibonacci_directions(n: int) -> np.ndarray:
    """n unit vectors spread evenly over the sphere. [n, 3]."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    phi = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def point_spacing(points: np.ndarray) -> float:
    """Median nearest-neighbour distance of points [P, 3] (0 for fewer than 2 points)."""
    from scipy.spatial import cKDTree

    if len(points) < 2:
        return 0.0
    d, _ = cKDTree(points).query(points, k=2)
    return float(np.median(d[:, 1]))


def directional_coverage(points: np.ndarray, normals: np.ndarray | None = None) -> float:
    """Share of directions d from the bounding-box centre of points [P, 3] that are seen: some
    observed point lies within the cone around d and, when outward normals [P, 3] are given, faces
    that way (n·d >= 0.3). The normal test keeps an inner wall seen through an opening (a mug's far
    inside) from counting as the outside behind it."""
    from scipy.spatial import cKDTree

    if len(points) < 4:
        return 0.0
    centre = 0.5 * (points.min(0) + points.max(0))
    rel = points - centre
    norm = np.linalg.norm(rel, axis=1)
    ok = norm > 1e-9
    rel = rel[ok] / norm[ok, None]
    if len(rel) == 0:
        return 0.0
    dirs = fibonacci_directions(_N_DIRS)
    chord = 2 * np.sin(_CONE / 2)
    if normals is None:
        d, _ = cKDTree(rel).query(dirs, k=1)
        return float((d <= chord).mean())
    nrm = np.asarray(normals, dtype=np.float64)[ok]
    hits = cKDTree(rel).query_ball_point(dirs, chord)
    covered = [len(h) > 0 and bool((nrm[h] @ d >= 0.3).any()) for h, d in zip(hits, dirs)]
    return float(np.mean(covered))


def surface_coverage(mesh, points: np.ndarray, tolerance: float, spacing: float) -> float:
    """Share of `mesh`'s surface (samples ~spacing apart) within `tolerance` of an observed point."""
    from scipy.spatial import cKDTree

    from .meshops import sample_surface

    samples = sample_surface(mesh, spacing, max_points=50_000)
    if len(samples) == 0 or len(points) == 0:
        return 0.0
    d, _ = cKDTree(points).query(samples, k=1)
    return float((d <= tolerance).mean())


def fit_quality(mesh, points: np.ndarray, tolerance: float) -> tuple[float, float]:
    """(RMS distance of observed points to the mesh surface, share of points within tolerance)."""
    from .meshops import distance_to_surface

    d = distance_to_surface(points, mesh)
    if len(d) == 0:
        return float("inf"), 0.0
    return float(np.sqrt(np.mean(d ** 2))), float((d <= tolerance).mean())
