"""RANSAC plane fits that give the same answer on every run and on every thread.

Open3D's `PointCloud.segment_plane` scores its hypotheses on an OpenMP team whose threads draw from
one process-wide generator and stop early on a shared counter: which samples a run tries, and so the
plane it returns, depends on thread timing (7-Scenes frames labelled twice by `psimap segment` got
different labels). Here the hypotheses come from the caller's numpy Generator and are scored in fixed
batches in order, so a seed fixes the answer, and no lock is needed when frames are labelled on
several threads at once.
"""
from __future__ import annotations

import numpy as np

# hypotheses scored per batch: one [BATCH, N] float32 distance matrix (N = 4000 points: 1 MB)
BATCH = 64


def _required_iterations(inlier_share: float, probability: float, sample: int = 3) -> float:
    """RANSAC's stopping rule: draws needed to have drawn one all-inlier sample with `probability`
    when `inlier_share` of the points are inliers."""
    good = inlier_share ** sample
    if good <= 0.0:
        return np.inf
    if good >= 1.0:
        return 0.0
    return float(np.log1p(-probability) / np.log1p(-good))


def fit_plane_lsq(points: np.ndarray) -> np.ndarray:
    """Least-squares plane [4] (unit n, d with n.x + d = 0) through points [N, 3], N >= 3: the normal
    is the direction of least spread about the centroid."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    n = vt[-1]
    return np.append(n, -float(n @ centre))


def ransac_plane(points: np.ndarray, threshold: float, rng: np.random.Generator,
                 iterations: int = 1000, probability: float = 0.99999999) -> tuple[np.ndarray, np.ndarray]:
    """The plane most points of `points` [N, 3] (finite) lie within `threshold` of.

    Hypotheses are planes through three points drawn by `rng`; the best holds most inliers (the
    earliest drawn on a tie). Draws stop after `iterations`, or once the best's inlier share says a
    clean sample has been drawn with `probability`. Returns (plane [4]: unit normal n and offset d,
    n.x + d = 0, refitted by least squares to the inliers; inliers [M] int64 indices within
    `threshold` of the plane the hypothesis gave). With fewer than three points, or only collinear
    ones, the plane is zeros and inliers empty."""
    P = np.asarray(points, np.float64).reshape(-1, 3)
    N = len(P)
    none = (np.zeros(4), np.zeros(0, np.int64))
    if N < 3 or iterations < 1:
        return none
    # hypotheses are scored in float32 about the centroid (half the memory traffic of float64; a
    # world kilometres from its origin keeps its millimetres)
    centre = P.mean(axis=0)
    Q = P - centre
    QT = np.ascontiguousarray(Q.T, np.float32)                          # [3, N]
    best_count, best = 0, None
    done = 0
    while done < iterations:
        b = min(BATCH, iterations - done)
        ijk = rng.integers(0, N, (b, 3))
        a, u, v = Q[ijk[:, 0]], Q[ijk[:, 1]] - Q[ijk[:, 0]], Q[ijk[:, 2]] - Q[ijk[:, 0]]
        n = np.cross(u, v)
        length = np.linalg.norm(n, axis=1)
        scale = np.maximum(np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1), 1e-300)
        ok = length > 1e-9 * scale                          # repeated or collinear draws: no plane
        n = np.where(ok[:, None], n / np.maximum(length, 1e-300)[:, None], 0.0)
        d = -np.einsum("ij,ij->i", n, a)
        # einsum, not a BLAS product: BLAS would spin a thread per core for a product this small
        # (twice the CPU time, and segment labels a frame on every core already)
        dist = np.einsum("ij,jk->ik", n.astype(np.float32), QT)          # [b, N]
        dist += d.astype(np.float32)[:, None]
        np.abs(dist, out=dist)
        count = np.where(ok, np.count_nonzero(dist < threshold, axis=1), 0)
        j = int(np.argmax(count))                           # the first of the batch's best
        if count[j] > best_count:
            best_count, best = int(count[j]), (n[j], float(d[j]))
        done += b
        if best_count and done >= _required_iterations(best_count / N, probability):
            break
    if best is None or best_count < 3:
        return none
    inliers = np.flatnonzero(np.abs(Q @ best[0] + best[1]) < threshold)
    if len(inliers) < 3:                                    # float32 counted a point or two more
        return none
    return fit_plane_lsq(P[inliers]), inliers
