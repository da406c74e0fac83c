"""Self-organising Gaussian mixture (SOGMM) prior of paper §3.2: a 4D (x, y, z, grey) mixture fitted
by recursive splitting, whose components are small planar patches.

Fit: voxel-downsample, seed one component per coarse grid cell, then level by level split every
component that is too large, not planar enough, or fits its points worse than the point-to-plane
budget, along its major axis; a few hard-EM steps restricted to each split pair move points to the
better child. Given each point's depth-noise std, a component whose residual the noise explains
stops splitting (noisy planes stay large, well-averaged patches). Points marked as detail (on
things, from the 2D masks) also split until their patch is no wider than a given extent, so objects
get patches at the scale their surfels resolve while walls stay coarse. All components of a level are
processed at once (moments by np.bincount), so a level costs O(N) and the fit O(N log N). A final
pass reassigns every point among its nearest components.

Training queries (torch): nearest component of a surfel (`SOGMMIndex`), point-to-plane distance
d(mu_i, M_k) = |(mu_i - mu_k) . n_k|, normal term 1 - |n_i . n_k|, and L_geo.
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from psimap import PsimapError
from psimap.geometry.points import drop_nonfinite, voxel_downsample
from psimap.transforms import rotmat_to_quat

# Auto voxel keeps at most this many points after downsampling: it bounds fit time on big clouds.
_AUTO_MAX_POINTS = 250_000
# Grey intensity variance floor: texture only separates components across a >~10 % grey contrast.
_GREY_VAR_FLOOR = 0.01
# A component splits only when its residual exceeds this x the mean |noise| its points carry: the
# sample mean |noise| of >= 16 points has a relative std <= 0.19, so 1.5 is ~2.6 std above it.
_NOISE_MARGIN = 1.5
# Candidates per point for the final reassignment / `assign`.
_CANDIDATES = 6
_MAX_LEVELS = 64
_ARRAY_FIELDS = ("means", "covs", "weights", "normals", "tangents", "eigvals", "counts")


@dataclass
class SOGMM:
    """A fitted mixture. K components; spatial quantities in world metres.

    means [K, 4] (x, y, z, grey); covs [K, 4, 4] (regularised); weights [K] (sum 1);
    normals [K, 3] (unit, smallest spatial eigenvector); tangents [K, 2, 3] (major, minor axis;
    [t0, t1, n] is a right-handed rotation); eigvals [K, 3] spatial eigenvalues, descending;
    counts [K] points per component; fit_stats: K, residual_mean (mean point-to-plane distance of
    the fitted points, m), time_s, n_points (after downsampling), and the settings used.
    detail [K] share of each component's points marked as detail (None when the fit had no marks;
    not saved by as_arrays). footprint [K] mean of its points' `footprint` values (metres per pixel
    at each point's viewing distance; None when the fit was given none; not saved by as_arrays).
    """

    means: np.ndarray
    covs: np.ndarray
    weights: np.ndarray
    normals: np.ndarray
    tangents: np.ndarray
    eigvals: np.ndarray
    counts: np.ndarray
    fit_stats: dict = field(default_factory=dict)
    detail: np.ndarray | None = None
    footprint: np.ndarray | None = None

    @property
    def K(self) -> int:
        return int(self.means.shape[0])

    def extents(self) -> np.ndarray:
        """[K, 2] side lengths along the two tangent axes: sqrt(12 lambda), exact for a uniform patch."""
        return np.sqrt(12.0 * np.maximum(self.eigvals[:, :2], 0.0))

    def as_arrays(self) -> dict:
        """Plain arrays (for saving next to a checkpoint); `SOGMM.from_arrays` inverts it."""
        return {f: np.asarray(getattr(self, f)) for f in _ARRAY_FIELDS}

    @classmethod
    def from_arrays(cls, arrays: dict, fit_stats: dict | None = None) -> "SOGMM":
        missing = [f for f in _ARRAY_FIELDS if f not in arrays]
        if missing:
            raise PsimapError(f"SOGMM arrays lack {', '.join(missing)}")
        return cls(**{f: np.asarray(arrays[f], dtype=np.int64 if f == "counts" else np.float64)
                      for f in _ARRAY_FIELDS}, fit_stats=dict(fit_stats or {}))

    def assign(self, points: np.ndarray, candidates: int = _CANDIDATES) -> np.ndarray:
        """Most likely component of each point [N, 3] (or [N, 4]) among its `candidates` nearest
        component means (spatial Gaussian log-likelihood). Returns [N] int64."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] < 3:
            raise PsimapError(f"points must be [N, 3] or [N, 4], got shape {pts.shape}")
        return _assign_spatial(pts[:, :3], self.means[:, :3], self.covs[:, :3, :3], self.weights,
                               candidates)


# ----------------------------------------------------------------------------------------------
# moments and eigen-frames, vectorised over components


def _moments(X: np.ndarray, labels: np.ndarray, K: int):
    """Counts [K], means [K, D], covariances [K, D, D] of X [N, D] grouped by labels [N] in 0..K-1.

    Two passes (mean, then centred products) so large coordinates do not cancel."""
    D = X.shape[1]
    counts = np.bincount(labels, minlength=K).astype(np.float64)
    safe = np.maximum(counts, 1.0)
    means = np.stack([np.bincount(labels, X[:, d], minlength=K) for d in range(D)], axis=1) / safe[:, None]
    Y = X - means[labels]
    covs = np.empty((K, D, D))
    for i in range(D):
        for j in range(i, D):
            c = np.bincount(labels, Y[:, i] * Y[:, j], minlength=K) / safe
            covs[:, i, j] = c
            covs[:, j, i] = c
    return counts, means, covs, Y


def _regularise(covs: np.ndarray, eps_xyz: float) -> np.ndarray:
    """Add eps to the spatial diagonal and floor the grey variance: keeps every covariance SPD for
    duplicate, collinear and 2-point clusters."""
    covs = covs.copy()
    covs[:, 0, 0] += eps_xyz
    covs[:, 1, 1] += eps_xyz
    covs[:, 2, 2] += eps_xyz
    if covs.shape[1] == 4:
        covs[:, 3, 3] = np.maximum(covs[:, 3, 3], 0.0) + _GREY_VAR_FLOOR
    return covs


def _frames(spatial_covs: np.ndarray):
    """Eigen-frames of [K, 3, 3] SPD matrices -> eigvals [K, 3] descending, normals [K, 3],
    tangents [K, 2, 3]. Signs are made deterministic (largest-|.| coordinate positive) and the
    minor tangent is n x t0 so [t0, t1, n] is a proper rotation even for degenerate spectra."""
    w, V = np.linalg.eigh(spatial_covs)            # ascending
    normals = _canonical_sign(V[:, :, 0])
    t0 = _canonical_sign(V[:, :, 2])
    t1 = np.cross(normals, t0)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    eigvals = w[:, ::-1].copy()
    return eigvals, normals, np.stack([t0, t1], axis=1)


def _canonical_sign(v: np.ndarray) -> np.ndarray:
    idx = np.argmax(np.abs(v), axis=1)
    s = np.sign(v[np.arange(len(v)), idx])
    s[s == 0] = 1.0
    v = v * s[:, None]
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _gauss_terms(covs: np.ndarray, weights: np.ndarray):
    """Inverse covariances and the constant part of the log-likelihood (log w - 0.5 log det)."""
    inv = np.linalg.inv(covs)
    _, logdet = np.linalg.slogdet(covs)
    return inv, np.log(np.maximum(weights, 1e-300)) - 0.5 * logdet


def _loglik(d: np.ndarray, inv: np.ndarray, const: np.ndarray, comp: np.ndarray) -> np.ndarray:
    """Log-likelihood (up to a constant) of offsets d [..., D] under components comp [...]:
    const[comp] - 0.5 d^T inv[comp] d, with inv [K, D, D] symmetric, const [K]. The quadratic form
    is expanded entry by entry so only [...]-sized columns are gathered, never [..., D, D]."""
    D = d.shape[-1]
    q = np.zeros(d.shape[:-1])
    for i in range(D):
        q += inv[:, i, i][comp] * d[..., i] * d[..., i]
        for j in range(i + 1, D):
            q += 2.0 * inv[:, i, j][comp] * d[..., i] * d[..., j]
    return const[comp] - 0.5 * q


def _assign_spatial(pts, means, covs, weights, candidates, exclude=None, chunk=100_000):
    """Best component of each point among its nearest means (chunked so memory stays bounded)."""
    from scipy.spatial import cKDTree

    K = len(means)
    if K == 1:
        return np.zeros(len(pts), np.int64)
    valid = np.ones(K, bool) if exclude is None else ~exclude
    ids = np.flatnonzero(valid)
    tree = cKDTree(means[ids])
    k = min(candidates, len(ids))
    inv, const = _gauss_terms(covs[ids], weights[ids])
    out = np.empty(len(pts), np.int64)
    for s in range(0, len(pts), chunk):
        p = pts[s:s + chunk]
        _, nn = tree.query(p, k=k)
        nn = nn.reshape(len(p), k)
        ll = _loglik(p[:, None, :] - means[ids][nn], inv, const, nn)
        out[s:s + chunk] = ids[nn[np.arange(len(p)), np.argmax(ll, axis=1)]]
    return out


# ----------------------------------------------------------------------------------------------
# fitting


def _auto_voxel(xyz: np.ndarray, diag: float) -> float:
    """Voxel from the cloud's density: estimate the surface area from the occupancy of a coarse
    grid (a surface of area A fills ~A / v^2 cells of side v), take the mean point spacing
    sqrt(A / N), and grow it where needed so that at most _AUTO_MAX_POINTS points remain.
    The grid is coarsened until cells hold >= 4 points on average: with fewer, occupancy counts
    points rather than area and the spacing would be underestimated."""
    v0 = diag / 256.0
    lo = xyz.min(axis=0)
    for _ in range(8):
        cell = np.floor((xyz - lo) / v0).astype(np.int64)
        n_cells = int(diag / v0) + 2
        key = (cell[:, 0] * n_cells + cell[:, 1]) * n_cells + cell[:, 2]
        occupied = len(np.unique(key))
        if len(xyz) >= 4 * occupied:
            break
        v0 *= 2.0
    area = occupied * v0 * v0
    spacing = math.sqrt(area / len(xyz))
    return max(spacing, math.sqrt(area / _AUTO_MAX_POINTS))


def _compact(labels: np.ndarray, K: int) -> np.ndarray:
    """Renumber labels [N] in 0..K-1 to 0..K'-1 over the labels present, keeping their order (O(N))."""
    present = np.bincount(labels, minlength=K) > 0
    return (np.cumsum(present) - 1)[labels].astype(np.int64)


def _seed_labels(xyz: np.ndarray, cell_size: float, min_points: int) -> np.ndarray:
    """One component per occupied grid cell of side `cell_size`; cells with fewer than
    `min_points` points are merged into the nearest populous cell."""
    cell = np.floor((xyz - xyz.min(axis=0)) / cell_size).astype(np.int64)
    dims = cell.max(axis=0) + 1
    if np.prod(dims.astype(np.float64)) < 2 ** 62:
        key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
        _, labels = np.unique(key, return_inverse=True)
    else:
        _, labels = np.unique(cell, axis=0, return_inverse=True)
    labels = labels.ravel()
    counts = np.bincount(labels)
    small = counts < min_points
    if small.any() and not small.all():
        from scipy.spatial import cKDTree

        K = len(counts)
        centres = np.stack([np.bincount(labels, xyz[:, d], minlength=K) for d in range(3)], 1)
        centres /= counts[:, None]
        big = np.flatnonzero(~small)
        moved = small[labels]
        _, nn = cKDTree(centres[big]).query(xyz[moved])
        labels = labels.copy()
        labels[moved] = big[nn]
        labels = _compact(labels, K)
    elif small.all():
        labels = np.zeros(len(xyz), np.int64)
    return labels.astype(np.int64)


def fit_sogmm(points: np.ndarray, *, intensity: np.ndarray | None = None, voxel: float | None = None,
              max_extent: float | None = None, planarity: float = 0.02, residual: float | None = None,
              min_points: int = 8, em_iters: int = 3, noise: np.ndarray | None = None,
              detail: np.ndarray | None = None, detail_extent: float | None = None,
              footprint: np.ndarray | None = None, seed: int = 0, progress: bool | None = None) -> SOGMM:
    """Fit the SOGMM prior to a point cloud.

    points: [N, 3] or [N, 4] (x, y, z world metres[, grey in [0, 1]]); intensity: [N] grey, overrides
      column 3; without either the grey channel is constant 0.5. Rows with NaN / inf are dropped
      (the count is in fit_stats["n_dropped_nonfinite"]).
    voxel: downsampling cube side (m); None = from the cloud's density (see _auto_voxel); 0 = none
      (the automatic settings below then still use the density-derived length).
    max_extent: largest allowed side length of a component (m); None = max(16 voxel, diag / 64), so
      nearest-mean queries in training stay local.
    planarity: split while lambda_min / lambda_mid exceeds this (scale-free flatness test). It only
      applies while the component's mean residual is above a quarter of the budget: below that the
      thickness is sensor noise, and splitting a noisy patch only makes the ratio worse.
    residual: point-to-plane error budget (m): split while the mean |(x - mu_k) . n_k| exceeds it;
      None = half the length unit (voxel, or the density-derived spacing). Set it above the
      sensor's mean |noise|: below that, patches only stop splitting at min_points. Where data is
      too sparse to split further (min_points), the reported residual can exceed the budget.
    min_points: never create a component with fewer points (tiny clusters stop splitting).
    em_iters: hard-EM steps per split pair. seed: kept for API symmetry; the fit has no randomness.
    noise: [N] depth-noise std (m) of each input point, or None. A component whose residual sensor
      noise explains (mean |noise| of its voxel-averaged points, x _NOISE_MARGIN) stops splitting:
      both the residual budget and the planarity test then ask for more than noise, so a noisy
      plane stays one large, well-averaged patch instead of splitting down to min_points.
    detail: [N] bool (or weights in [0, 1]) marking the points where the map needs detail (on
      things), or None. A component whose points are mostly detail also splits while its side
      exceeds `detail_extent` (m; required with `detail`), whatever its noise: a small object seen
      through noise is otherwise one or two flat patches. None gives exactly the fit without it.
    footprint: [N] metres per pixel at each point's own viewing distance (its depth / the focal
      length of the view it came from), or None. It does not steer the fit: each component reports
      the mean over its points (.footprint [K]), what the views resolve there, from which training
      sets the surfel spacing per component. None gives exactly the fit without it.
    Returns SOGMM (with .detail [K] when `detail` was given, .footprint [K] with `footprint`). Raises PsimapError on empty / malformed input.
    """
    del seed  # the fit is deterministic by construction (no sampling)
    t_start = time.perf_counter()
    try:
        pts = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise PsimapError(f"SOGMM input is not a numeric point array: {e}") from None
    if pts.ndim != 2 or pts.shape[1] not in (3, 4):
        raise PsimapError(f"SOGMM input must be an [N, 3] or [N, 4] point array, got shape {pts.shape}")
    if intensity is not None:
        inten = np.asarray(intensity, dtype=np.float64).reshape(-1)
        if len(inten) != len(pts):
            raise PsimapError(f"intensity has {len(inten)} values for {len(pts)} points")
        pts = np.concatenate([pts[:, :3], inten[:, None]], axis=1)
    elif pts.shape[1] == 3:
        pts = np.concatenate([pts, np.full((len(pts), 1), 0.5)], axis=1)
    n_input = len(pts)
    if noise is not None:
        noise = np.asarray(noise, dtype=np.float64).reshape(-1)
        if len(noise) != len(pts):
            raise PsimapError(f"noise has {len(noise)} values for {len(pts)} points")
        # carried as a variance column through the NaN filter and the voxel averaging
        pts = np.concatenate([pts, np.nan_to_num(noise, nan=0.0, posinf=0.0)[:, None] ** 2], axis=1)
    if footprint is not None:
        footprint = np.asarray(footprint, dtype=np.float64).reshape(-1)
        if len(footprint) != n_input:
            raise PsimapError(f"footprint has {len(footprint)} values for {n_input} points")
        # carried as a column (before detail's) through the NaN filter and the voxel averaging
        pts = np.concatenate([pts, np.nan_to_num(footprint, nan=0.0, posinf=0.0)[:, None]], axis=1)
    if detail is not None:
        detail = np.asarray(detail, dtype=np.float64).reshape(-1)
        if len(detail) != n_input:
            raise PsimapError(f"detail has {len(detail)} values for {n_input} points")
        if detail_extent is None or not (detail_extent > 0 and np.isfinite(detail_extent)):
            raise PsimapError(f"detail_extent must be a positive length with detail, got {detail_extent}")
        # carried as the last column through the NaN filter and the voxel averaging (a share per voxel)
        pts = np.concatenate([pts, np.clip(np.nan_to_num(detail, nan=0.0), 0.0, 1.0)[:, None]], axis=1)
    pts, n_dropped = drop_nonfinite(pts)
    if len(pts) == 0:
        why = f" (all {n_input} points were NaN/inf)" if n_input else ""
        raise PsimapError(f"cannot fit a SOGMM to an empty point cloud{why}")
    if min_points < 1 or planarity <= 0 or em_iters < 0:
        raise PsimapError("fit_sogmm: min_points must be >= 1, planarity > 0 and em_iters >= 0")

    centre = pts[:, :3].mean(axis=0)
    pts[:, :3] -= centre                            # fit in centred coordinates (precision)
    lo, hi = pts[:, :3].min(axis=0), pts[:, :3].max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    scale = diag if diag > 0 else 1.0               # all points coincide: any positive unit works
    if voxel is not None and (voxel < 0 or not np.isfinite(voxel)):
        raise PsimapError(f"voxel must be >= 0, got {voxel}")
    # length unit of the automatic settings: the given voxel, else the density-derived one
    unit = voxel if voxel else (_auto_voxel(pts[:, :3], diag) if diag > 0 else scale * 1e-3)
    if voxel is None:
        voxel = unit
    counts_in = np.ones(len(pts), np.int64)
    if voxel > 0:
        pts, counts_in = voxel_downsample(pts, voxel, return_counts=True)
    point_detail = None
    if detail is not None:
        point_detail = pts[:, -1]
        pts = pts[:, :-1]
    point_footprint = None
    if footprint is not None:
        point_footprint = pts[:, -1]
        pts = pts[:, :-1]
    point_var = None
    if noise is not None:
        # an average of m independent readings has 1/m of their mean variance
        point_var = pts[:, 4] / np.maximum(counts_in, 1)
        pts = pts[:, :4]
    if max_extent is None:
        max_extent = max(16.0 * unit, diag / 64.0)
    if residual is None:
        residual = 0.5 * unit
    if not (max_extent > 0 and residual > 0):
        raise PsimapError("fit_sogmm: max_extent and residual must be positive")
    noise_floor = 0.25 * residual
    # spatial regulariser: 5 % of the voxel (or 1e-6 of the extent) as a standard deviation
    eps_xyz = max((0.05 * unit) ** 2, (1e-6 * scale) ** 2)

    X = pts                                        # [N, 4] float64
    N = len(X)
    # seed cells a bit smaller than max_extent so a full square cell is not split at once
    labels = _seed_labels(X[:, :3], max_extent / math.sqrt(2.0), min_points)
    K = int(labels.max()) + 1
    active = np.ones(K, bool)                      # components that may still split

    bar = None
    if progress is None:
        progress = sys.stderr.isatty()
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=None, desc="SOGMM fit", unit="level", leave=False)
    levels = 0
    for levels in range(1, _MAX_LEVELS + 1):
        pidx = np.flatnonzero(active[labels])
        if len(pidx) == 0:
            break
        act_ids = np.flatnonzero(active)
        remap = np.full(K, -1, np.int64)
        remap[act_ids] = np.arange(len(act_ids))
        lab = remap[labels[pidx]]
        Xa = X[pidx]
        counts, means, covs, Y = _moments(Xa, lab, len(act_ids))
        covs = _regularise(covs, eps_xyz)
        eigvals, normals, tangents = _frames(covs[:, :3, :3])
        resid = np.bincount(lab, np.abs(np.einsum("ij,ij->i", Y[:, :3], normals[lab])),
                            minlength=len(act_ids)) / np.maximum(counts, 1)
        extent = np.sqrt(12.0 * eigvals[:, 0])
        ratio = eigvals[:, 2] / eigvals[:, 1]
        budget, floor = residual, noise_floor
        if point_var is not None:
            # E|noise| = sqrt(2 / pi) sigma for a normal: what the residual is without any misfit
            noise_abs = np.sqrt(2.0 / np.pi * np.bincount(lab, point_var[pidx], minlength=len(act_ids))
                                / np.maximum(counts, 1))
            budget = np.maximum(residual, _NOISE_MARGIN * noise_abs)
            floor = np.maximum(noise_floor, _NOISE_MARGIN * noise_abs)
        want = (extent > max_extent) | (resid > budget) | ((ratio > planarity) & (resid > floor))
        if point_detail is not None:
            share = np.bincount(lab, point_detail[pidx], minlength=len(act_ids)) / np.maximum(counts, 1)
            want |= (share > 0.5) & (extent > detail_extent)
        split = want & (counts >= 2 * min_points)
        active[act_ids[~split]] = False
        if not split.any():
            break
        # split along the major axis through the mean, then hard EM within each pair
        sp = np.flatnonzero(split)                 # compact ids of splitting components
        pair_of = np.full(len(act_ids), -1, np.int64)
        pair_of[sp] = np.arange(len(sp))
        in_split = pair_of[lab] >= 0
        q = np.flatnonzero(in_split)
        pair = pair_of[lab[q]]                      # [Q] pair index of each point
        side = (np.einsum("ij,ij->i", Y[q, :3], tangents[lab[q], 0]) > 0).astype(np.int64)
        Xq = Xa[q]
        S = len(sp)
        for _ in range(em_iters):
            child = 2 * pair + side
            c_counts, c_means, c_covs, _ = _moments(Xq, child, 2 * S)
            if (c_counts == 0).any():
                break                              # a child emptied: keep the last assignment
            c_covs = _regularise(c_covs, eps_xyz)
            inv, const = _gauss_terms(c_covs, c_counts / np.repeat(c_counts.reshape(S, 2).sum(1), 2))
            ll0 = _loglik(Xq - c_means[2 * pair], inv, const, 2 * pair)
            ll1 = _loglik(Xq - c_means[2 * pair + 1], inv, const, 2 * pair + 1)
            new_side = (ll1 > ll0).astype(np.int64)
            if np.array_equal(new_side, side):
                break
            side = new_side
        n1 = np.bincount(pair, side, minlength=S)
        n0 = np.bincount(pair, minlength=S) - n1
        ok = (n0 >= min_points) & (n1 >= min_points)
        # pairs whose smaller child would be tiny are not split: the parent becomes final
        active[act_ids[sp[~ok]]] = False
        good = ok[pair] & (side == 1)
        new_id = np.full(S, -1, np.int64)
        new_id[ok] = K + np.arange(int(ok.sum()))
        labels[pidx[q[good]]] = new_id[pair[good]]
        K += int(ok.sum())
        active = np.concatenate([active, np.ones(int(ok.sum()), bool)])
        if bar is not None:
            bar.update(1)
            bar.set_postfix(K=K, splitting=int(ok.sum()))
    if bar is not None:
        bar.close()

    # final pass: every point to its most likely nearby component (fixes early split boundaries)
    counts, means, covs, _ = _moments(X, labels, K)
    covs = _regularise(covs, eps_xyz)
    if K > 1 and em_iters > 0:
        labels = _assign_spatial(X[:, :3], means[:, :3], covs[:, :3, :3], counts / N, _CANDIDATES)
        counts = np.bincount(labels, minlength=K)
        small = (counts > 0) & (counts < min_points)
        if small.any() and (counts >= min_points).any():
            moved = small[labels]
            labels[moved] = _assign_spatial(X[moved, :3], means[:, :3], covs[:, :3, :3], counts / N,
                                            _CANDIDATES, exclude=counts < min_points)
        labels = _compact(labels, K)                     # drop emptied components
        K = int(labels.max()) + 1
        counts, means, covs, _ = _moments(X, labels, K)
        covs = _regularise(covs, eps_xyz)

    eigvals, normals, tangents = _frames(covs[:, :3, :3])
    comp_detail = comp_footprint = None
    if point_detail is not None:
        comp_detail = np.bincount(labels, point_detail, minlength=K) / np.maximum(counts, 1)
    if point_footprint is not None:
        comp_footprint = np.bincount(labels, point_footprint, minlength=K) / np.maximum(counts, 1)
    d = np.abs(np.einsum("ij,ij->i", X[:, :3] - means[labels, :3], normals[labels]))
    means[:, :3] += centre
    stats = {
        "K": K,
        "residual_mean": float(d.mean()),
        "time_s": time.perf_counter() - t_start,
        "n_points": N,
        "n_input": n_input,
        "n_dropped_nonfinite": n_dropped,
        "voxel": float(voxel),
        "max_extent": float(max_extent),
        "residual_budget": float(residual),
        "planarity": float(planarity),
        "noise_aware": point_var is not None,
        "levels": levels,
    }
    if comp_detail is not None:
        stats["detail_extent"] = float(detail_extent)
        stats["K_detail"] = int((comp_detail > 0.5).sum())
    return SOGMM(means=means, covs=covs, weights=counts / N, normals=normals, tangents=tangents,
                 eigvals=eigvals, counts=counts.astype(np.int64), fit_stats=stats, detail=comp_detail,
                 footprint=comp_footprint)


# ----------------------------------------------------------------------------------------------
# surfel initialisation


def _allocate(areas: np.ndarray, n_total: int) -> np.ndarray:
    """Integer counts summing to n_total, proportional to areas (largest remainder)."""
    if n_total <= 0 or areas.sum() <= 0:
        return np.zeros(len(areas), np.int64)
    exact = areas / areas.sum() * n_total
    n = np.floor(exact).astype(np.int64)
    rest = n_total - int(n.sum())
    if rest > 0:
        order = np.lexsort((np.arange(len(areas)), -(exact - n)))   # stable tie-break by index
        n[order[:rest]] += 1
    return n


def sample_surfels(sogmm: SOGMM, n_total: int | None = None, *, density: float | None = None,
                   relative_density: np.ndarray | None = None, seed: int = 0):
    """Initial surfels drawn from the mixture.

    Each component gets a number of surfels proportional to its tangent area 12 sqrt(l0 l1) (so the
    coverage per m^2 is uniform), either `n_total` in all or `density` surfels per m^2 (default:
    one per component scaled so the mean component gets ~4). relative_density [K] (> 0) scales a
    component's surfels per m^2 against the others' (None = uniform), within the same n_total. Positions are uniform over the
    component's tangent rectangle (side sqrt(12 lambda)) on its plane; rotation is the tangent
    frame [t0, t1, n]; scales split the rectangle among its surfels (sigma = half the spacing along
    each axis); intensity is the 4D Gaussian's grey conditioned on the position.
    Returns (means [S, 3] f32, quats [S, 4] f32 (w, x, y, z), scales [S, 2] f32, intensity [S] f32).
    """
    rng = np.random.default_rng(seed)
    side = sogmm.extents()                                # [K, 2]
    areas = side[:, 0] * side[:, 1]
    if n_total is None:
        if density is None:
            density = 4.0 * sogmm.K / max(float(areas.sum()), 1e-12)
        n_total = int(round(float(areas.sum()) * density))
    if relative_density is not None:
        rel = np.asarray(relative_density, dtype=np.float64).reshape(-1)
        if len(rel) != sogmm.K or not (np.isfinite(rel).all() and (rel > 0).all()):
            raise PsimapError(f"relative_density must be {sogmm.K} positive numbers")
        per = _allocate(areas * rel, int(n_total))
    else:
        per = _allocate(areas, int(n_total))
    comp = np.repeat(np.arange(sogmm.K), per)             # [S]
    S = len(comp)
    uv = (rng.random((S, 2)) - 0.5) * side[comp]
    t = sogmm.tangents[comp]                              # [S, 2, 3]
    means = sogmm.means[comp, :3] + uv[:, :1] * t[:, 0] + uv[:, 1:] * t[:, 1]
    R = np.stack([t[:, 0], t[:, 1], sogmm.normals[comp]], axis=2)   # columns: t_u, t_v, n
    quats = rotmat_to_quat(R)
    spacing = side[comp] / np.sqrt(np.maximum(per[comp], 1))[:, None]
    floor = 1e-6 * max(float(np.abs(sogmm.means[:, :3]).max()) if sogmm.K else 1.0, 1.0)
    scales = np.maximum(0.5 * spacing, floor)
    # E[g | x] = mu_g + Sigma_gx Sigma_xx^-1 (x - mu_x): the texture gradient inside the patch
    cov = sogmm.covs
    gain = np.linalg.solve(cov[:, :3, :3], cov[:, :3, 3:4])[..., 0]   # [K, 3]
    grey = sogmm.means[comp, 3] + np.einsum("ij,ij->i", gain[comp], means - sogmm.means[comp, :3])
    return (means.astype(np.float32), quats.astype(np.float32), scales.astype(np.float32),
            np.clip(grey, 0.0, 1.0).astype(np.float32))


# ----------------------------------------------------------------------------------------------
# training-time queries (torch)


class SOGMMIndex:
    """Component lookup for surfel centres during training.

    Why the nearest *mean* (the default): components are small planar patches of bounded extent
    (max_extent), so the closest mean is the patch a surfel sits on, except within about half a
    patch of a crease, where it may be the neighbouring face's patch. `candidates > 1` fixes that
    at k x the cost: among the k nearest means it takes the most likely component under the
    spatial Gaussians (thin along the normal, so the patch whose plane holds the surfel wins), the
    same rule as `SOGMM.assign`. The KD-tree is over the K fixed component means, not over the
    surfels: surfels moving or being cloned/pruned never needs a rebuild, and a rebuild (new
    SOGMM) costs O(K log K). Queries run on CPU (scipy cKDTree) without gradients; the loss terms
    that use the result are differentiable torch.
    """

    def __init__(self, sogmm: SOGMM):
        import torch
        from scipy.spatial import cKDTree

        if sogmm.K == 0:
            raise PsimapError("SOGMMIndex needs a SOGMM with at least one component")
        self.sogmm = sogmm
        self._tree = cKDTree(np.asarray(sogmm.means[:, :3], dtype=np.float64))
        self._inv, self._const = _gauss_terms(sogmm.covs[:, :3, :3], sogmm.weights)
        self.means = torch.as_tensor(sogmm.means[:, :3], dtype=torch.float32)      # [K, 3]
        self.normals = torch.as_tensor(sogmm.normals, dtype=torch.float32)         # [K, 3]

    def nearest(self, mu, candidates: int = 1):
        """mu: torch.Tensor [M, 3] -> idx [M] long (on mu's device): the nearest component mean, or
        with candidates = k > 1 the most likely of the k nearest components."""
        import torch

        pts = mu.detach().to("cpu", torch.float64).numpy().reshape(-1, 3)
        if not np.isfinite(pts).all():
            raise PsimapError("SOGMMIndex.nearest: surfel positions contain NaN/inf")
        k = min(int(candidates), self.sogmm.K)
        if k <= 1 or len(pts) == 0:
            _, idx = self._tree.query(pts, k=1)
        else:
            _, nn = self._tree.query(pts, k=k)
            ll = _loglik(pts[:, None, :] - self.sogmm.means[nn, :3], self._inv, self._const, nn)
            idx = nn[np.arange(len(pts)), np.argmax(ll, axis=1)]
        return torch.as_tensor(np.asarray(idx, dtype=np.int64).reshape(-1), device=mu.device)


def point_to_plane(mu, sogmm_means, sogmm_normals):
    """d(mu_i, M_k) = |(mu_i - mu_k) . n_k|. mu, sogmm_means, sogmm_normals: [M, 3] -> [M]."""
    return ((mu - sogmm_means) * sogmm_normals).sum(-1).abs()


def normal_alignment(n, n_ref):
    """1 - |n . n_ref| for unit n, n_ref [M, 3] -> [M]; 0 when parallel or antiparallel."""
    return 1.0 - (n * n_ref).sum(-1).abs()


def geo_loss(means, normals, index: SOGMMIndex, lambda_n: float = 0.1, reduction: str = "mean",
             candidates: int = 1):
    """L_geo = sum_i d(mu_i, M_k(i)) + lambda_n (1 - |n_i . n_k(i)|), k(i) = index.nearest(mu_i,
    candidates) (nearest mean, or the most likely of the `candidates` nearest; see SOGMMIndex).

    means, normals: [N, 3] surfel centres and unit normals (torch). reduction "mean" (default,
    keeps the weight independent of the surfel count) or "sum" (the paper's form). Returns a scalar.
    """
    import torch

    if means.shape[0] == 0:
        return means.sum() * 0.0
    idx = index.nearest(means, candidates)
    ref_m = index.means.to(means.device, means.dtype)[idx]
    ref_n = index.normals.to(means.device, means.dtype)[idx]
    per = point_to_plane(means, ref_m, ref_n) + lambda_n * normal_alignment(normals, ref_n)
    if reduction == "sum":
        return per.sum()
    if reduction != "mean":
        raise ValueError(f"reduction must be 'mean' or 'sum', got {reduction!r}")
    return torch.mean(per)
