"""Depth-sensor noise estimated from the depth images themselves: std sigma(z) as a function of range.

Why from the data: structured-light and ToF noise grows with range (Kinect: ~z^2) and differs per
sensor and scene, so a loss that trusts every depth pixel alike over-fits the far, noisy ones. The
estimator needs no ground truth: on a plane, inverse depth 1/z is affine in the pixel coordinates,
so its second difference along a row or column, e = w[u-1] - 2 w[u] + w[u+1], is zero up to noise.
With i.i.d. depth noise of std sigma_z, w's noise is sigma_z / z^2 and Var(e) = 6 (sigma_z / z^2)^2,
so sigma_z ~= z^2 |e| / sqrt(6) per triple. Depth edges and curved surfaces give large |e| on a
minority of triples; a median per range bin (1.4826 x median |.| = std for a normal) ignores them.
"""
from __future__ import annotations

import numpy as np

# the robust std of a normal sample: 1.4826 x its median absolute value
_MAD_TO_STD = 1.4826


def second_difference_samples(depth: np.ndarray, *, max_samples: int | None = None,
                              rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-triple noise samples of one depth image.

    depth: [H, W] metres, 0 / non-finite = invalid. Returns (z [M], s [M]): the middle pixel's depth
    and z^2 |second difference of 1/z| / sqrt(6) (one sample of sigma_z, up to the |.| of a normal),
    over every horizontal and vertical triple of valid pixels.
    """
    d = np.asarray(depth, dtype=np.float64)
    ok = np.isfinite(d) & (d > 0)
    w = np.where(ok, 1.0 / np.where(ok, d, 1.0), 0.0)
    zs, ss = [], []
    for a, v in ((w, ok), (w.T, ok.T)):
        good = v[:, :-2] & v[:, 1:-1] & v[:, 2:]
        e = a[:, :-2] - 2.0 * a[:, 1:-1] + a[:, 2:]
        z = 1.0 / a[:, 1:-1][good]
        zs.append(z)
        ss.append(z * z * np.abs(e[good]) / np.sqrt(6.0))
    z, s = np.concatenate(zs), np.concatenate(ss)
    if max_samples is not None and len(z) > max_samples:
        pick = (rng or np.random.default_rng(0)).choice(len(z), max_samples, replace=False)
        z, s = z[pick], s[pick]
    return z, s


def estimate_depth_noise(depths, *, bins: int = 12, min_per_bin: int = 200,
                         samples_per_frame: int = 20_000) -> tuple[np.ndarray, np.ndarray]:
    """Noise std sigma(z) of a depth sensor from its images (no ground truth).

    depths: iterable of [H, W] depth images (metres, 0 = invalid). Returns (z [B], sigma [B]): range
    bin centres (quantiles of the observed depth, so every bin holds data) and the robust std in
    each, made non-decreasing in z (noise never shrinks with range; this also smooths bins that a
    few edges inflated). B <= bins; B = 0 when there are fewer than `min_per_bin` valid triples.
    """
    rng = np.random.default_rng(0)
    zs, ss = [], []
    for depth in depths:
        z, s = second_difference_samples(depth, max_samples=samples_per_frame, rng=rng)
        zs.append(z)
        ss.append(s)
    z = np.concatenate(zs) if zs else np.zeros(0)
    s = np.concatenate(ss) if ss else np.zeros(0)
    if len(z) < min_per_bin:
        return np.zeros(0), np.zeros(0)
    n_bins = int(max(1, min(bins, len(z) // min_per_bin)))
    edges = np.quantile(z, np.linspace(0.0, 1.0, n_bins + 1))
    which = np.clip(np.searchsorted(edges, z, side="right") - 1, 0, n_bins - 1)
    centres, sigmas = [], []
    for b in range(n_bins):
        m = which == b
        if m.sum() < min_per_bin // 2:
            continue
        centres.append(float(np.median(z[m])))
        sigmas.append(_MAD_TO_STD * float(np.median(s[m])))
    sig = np.maximum.accumulate(np.asarray(sigmas))
    return np.asarray(centres), sig


def noise_at(z: np.ndarray, model: tuple[np.ndarray, np.ndarray], floor: float = 1e-4) -> np.ndarray:
    """sigma at depths z [...] from an `estimate_depth_noise` model (linear between bin centres,
    constant beyond the ends), at least `floor` metres. An empty model gives `floor` everywhere."""
    zc, sc = model
    z = np.asarray(z, dtype=np.float64)
    if len(zc) == 0:
        return np.full(z.shape, floor)
    return np.maximum(np.interp(z, zc, sc), floor)


def estimate_lidar_noise(points: np.ndarray, origin: np.ndarray, *, min_samples: int = 200,
                         max_points: int = 200_000) -> float | None:
    """Range-noise std (m) of one LiDAR sweep, from the sweep itself (no ground truth), or None when
    too few samples qualify.

    points: [N, 3] world; origin: [3] sensor position. The depth-image estimator's idea along the
    scan lines: on a plane, inverse range is a smooth function of the beam direction, so for a
    point and its two angular neighbours on opposite sides at equal spacing (the previous and next
    return of its ring: a spinning LiDAR's azimuth step is finer than its ring spacing), the second
    difference of 1/r is zero up to noise and sigma_r ~= r^2 |e| / sqrt(6). A robust median ignores
    edges and curved surfaces. The origin need not be exact: a few centimetres off barely changes
    the directions of returns metres away.
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points, np.float64)[:, :3]
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) > max_points:
        p = p[np.random.default_rng(0).choice(len(p), max_points, replace=False)]
    rel = p - np.asarray(origin, np.float64)[:3]
    r = np.linalg.norm(rel, axis=1)
    keep = r > 1e-3
    rel, r = rel[keep], r[keep]
    if len(r) < 3:
        return None
    d = rel / r[:, None]
    dist, nn = cKDTree(d).query(d, k=3)
    a, b = nn[:, 1], nn[:, 2]
    da, db = d[a] - d, d[b] - d
    # opposite sides (the ring's previous and next return) at nearly equal angular steps
    opposite = np.einsum("ij,ij->i", da, db) < -0.9 * dist[:, 1] * dist[:, 2]
    even = dist[:, 2] < 1.25 * dist[:, 1]
    ok = opposite & even & (dist[:, 1] > 0)
    if ok.sum() < min_samples:
        return None
    w = 1.0 / r
    e = w[a[ok]] - 2.0 * w[ok] + w[b[ok]]
    s = r[ok] ** 2 * np.abs(e) / np.sqrt(6.0)
    return float(_MAD_TO_STD * np.median(s))
