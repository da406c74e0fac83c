"""4D point clouds (x, y, z world metres, grey intensity in [0, 1]) for the SOGMM prior.

Sources: back-projected depth frames (grey from the registered RGB image) and LiDAR sweeps
([N, 4] x, y, z, intensity). Everything here is plain numpy so it stays cheap to import.
"""
from __future__ import annotations

import sys
from typing import Iterable

import numpy as np

from psimap import PsimapError
from psimap.transforms import depth_to_world

# ITU-R BT.601 luma weights: the usual grey conversion of an sRGB image.
_GREY = np.array([0.299, 0.587, 0.114], dtype=np.float32)


def rgb_to_grey(rgb: np.ndarray) -> np.ndarray:
    """Grey [...] in [0, 1] of colours [..., 3] in [0, 1] (BT.601 luma)."""
    return np.clip(np.asarray(rgb, np.float32) @ _GREY, 0.0, 1.0)


def drop_nonfinite(points: np.ndarray) -> tuple[np.ndarray, int]:
    """Remove rows of `points` [N, D] holding NaN or inf. Returns (kept [M, D], number dropped)."""
    finite = np.isfinite(points).all(axis=1)
    return points[finite], int(points.shape[0] - finite.sum())


def backproject_frame(rgb: np.ndarray | None, depth: np.ndarray, K: np.ndarray, c2w: np.ndarray, *,
                      max_depth: float | None = None, stride: int = 1) -> np.ndarray:
    """Back-project one depth image to world points with grey intensity.

    rgb: [H, W, 3] float in [0, 1] (or uint8) or None (intensity 0.5); depth: [H, W] metres, 0 or
    non-finite = invalid; K: [3, 3]; c2w: [4, 4] camera-to-world, OpenCV (x right, y down, z fwd).
    max_depth: drop pixels farther than this (sensor noise grows with depth); stride: pixel step.
    Returns [M, 4] float32 (x, y, z, grey).
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise PsimapError(f"depth image must be [H, W], got shape {depth.shape}")
    K = np.asarray(K, dtype=np.float64)
    c2w = np.asarray(c2w, dtype=np.float64)
    if K.shape != (3, 3) or c2w.shape != (4, 4) or not (np.isfinite(K).all() and np.isfinite(c2w).all()):
        raise PsimapError("camera intrinsics must be a finite [3, 3] and the pose a finite [4, 4] matrix")
    world, v, u = depth_to_world(depth, K, c2w, stride=stride, max_depth=max_depth)
    if rgb is None:
        grey = np.full(len(world), 0.5, dtype=np.float32)
    else:
        img = np.asarray(rgb)
        if img.shape[:2] != depth.shape:
            raise PsimapError(f"colour image {img.shape[:2]} and depth {depth.shape} differ in size")
        img = img[v, u, :3].astype(np.float32)
        if np.asarray(rgb).dtype == np.uint8:
            img /= 255.0
        grey = rgb_to_grey(img)
    return np.concatenate([world.astype(np.float32), grey[:, None]], axis=1)


def frames_to_points(frames: Iterable, *, max_depth: float | None = None, stride: int = 1,
                     voxel: float | None = None, progress: bool | None = None) -> np.ndarray:
    """Back-project every frame (objects with .rgb [H,W,3], .depth [H,W], .K, .c2w, optional .lidar
    [N,4]) and concatenate, LiDAR included. Frames with no valid depth contribute nothing.

    voxel: if given, the union is voxel-averaged; this is done frame by frame into a running
    per-cell sum, so memory stays proportional to the occupied cells, not to pixels x frames (150
    VGA frames are 46 M points). Returns [N, 4] float32 (x, y, z, grey).
    """
    if progress is None:
        progress = sys.stderr.isatty()
    if progress:
        from tqdm import tqdm

        frames = tqdm(frames, desc="back-projecting", unit="frame", leave=False)
    parts, acc = [], _CellAccumulator(voxel) if voxel is not None else None
    for f in frames:
        chunk = [backproject_frame(f.rgb, f.depth, f.K, f.c2w, max_depth=max_depth, stride=stride)]
        lidar = getattr(f, "lidar", None)
        if lidar is not None and len(lidar):
            chunk.append(lidar_points(lidar))
        if acc is None:
            parts.extend(chunk)
        else:
            for c in chunk:
                acc.add(c)
    if acc is not None:
        return acc.result()
    return np.concatenate(parts, axis=0) if parts else np.zeros((0, 4), np.float32)


class _CellAccumulator:
    """Running per-voxel sums of [N, 4] points on a fixed world grid (cell = floor(x / voxel))."""

    def __init__(self, voxel: float):
        if not (voxel > 0 and np.isfinite(voxel)):
            raise PsimapError(f"voxel size must be a positive number, got {voxel}")
        self.voxel = float(voxel)
        self.cells = np.zeros((0, 3), np.int64)
        self.sums = np.zeros((0, 4), np.float64)
        self.counts = np.zeros(0, np.int64)
        self.pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.pending_rows = 0

    def add(self, pts: np.ndarray) -> None:
        pts, _ = drop_nonfinite(np.asarray(pts))
        if len(pts) == 0:
            return
        cells = np.floor(pts[:, :3].astype(np.float64) / self.voxel).astype(np.int64)
        self.pending.append(_reduce_cells(cells, pts.astype(np.float64), np.ones(len(pts), np.int64)))
        self.pending_rows += len(self.pending[-1][0])
        if self.pending_rows > 4_000_000:
            self._merge()

    def _merge(self) -> None:
        if not self.pending:
            return
        cells = np.concatenate([self.cells] + [p[0] for p in self.pending])
        sums = np.concatenate([self.sums] + [p[1] for p in self.pending])
        counts = np.concatenate([self.counts] + [p[2] for p in self.pending])
        self.cells, self.sums, self.counts = _reduce_cells(cells, sums, counts)
        self.pending, self.pending_rows = [], 0

    def result(self) -> np.ndarray:
        self._merge()
        return (self.sums / np.maximum(self.counts, 1)[:, None]).astype(np.float32)


def _reduce_cells(cells: np.ndarray, sums: np.ndarray, counts: np.ndarray):
    """Merge rows sharing a cell [N, 3] int64: sums [N, D] and counts [N] are added. Sorted by cell."""
    lo = cells.min(axis=0)
    rel = cells - lo
    dims = rel.max(axis=0) + 1
    if np.prod(dims.astype(np.float64)) < 2 ** 62:
        key = (rel[:, 0] * dims[1] + rel[:, 1]) * dims[2] + rel[:, 2]
        order = np.argsort(key, kind="stable")
        k = key[order]
        starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    else:
        order = np.lexsort((rel[:, 2], rel[:, 1], rel[:, 0]))
        r = rel[order]
        starts = np.flatnonzero(np.r_[True, (r[1:] != r[:-1]).any(axis=1)])
    return (cells[order][starts], np.add.reduceat(sums[order], starts, axis=0),
            np.add.reduceat(counts[order], starts))


def lidar_points(lidar: np.ndarray) -> np.ndarray:
    """LiDAR sweep [N, 3] or [N, 4] (x, y, z, raw intensity) -> [M, 4] float32 with intensity in
    [0, 1]. Raw intensities have sensor-specific ranges (KITTI 0..1, Ouster 0..65535): values
    already in [0, 1] are kept, otherwise they are divided by their 99th percentile and clipped,
    so a few specular returns do not flatten the rest. Non-finite rows are dropped."""
    pts = np.asarray(lidar, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] not in (3, 4):
        raise PsimapError(f"LiDAR points must be [N, 3] or [N, 4], got shape {pts.shape}")
    if pts.shape[1] == 3:
        pts = np.concatenate([pts, np.full((len(pts), 1), 0.5, np.float32)], axis=1)
    pts, _ = drop_nonfinite(pts)
    pts = pts.copy()
    inten = pts[:, 3]
    if len(inten) and (inten.min() < 0 or inten.max() > 1):
        lo = min(float(inten.min()), 0.0)
        hi = float(np.percentile(inten, 99))
        scale = hi - lo if hi > lo else max(float(inten.max()) - lo, 1.0)
        pts[:, 3] = np.clip((inten - lo) / scale, 0.0, 1.0)
    return pts


def voxel_downsample(points: np.ndarray, voxel: float, *, return_counts: bool = False):
    """Average every column of `points` [N, D] (x, y, z first) over occupied cubes of side `voxel`
    on the world grid floor(x / voxel) (the same grid as `frames_to_points`, so results agree).

    Sort by cell key and average each run with np.add.reduceat: O(N log N), no Python loop. Rows
    come out in lexicographic cell order, so the result is deterministic. Returns [M, D], and with
    return_counts also the number of input points per cube [M] int64.
    """
    points = np.asarray(points)
    if len(points) == 0:
        return (points.copy(), np.zeros(0, np.int64)) if return_counts else points.copy()
    if not (voxel > 0 and np.isfinite(voxel)):
        raise PsimapError(f"voxel size must be a positive number, got {voxel}")
    cells = np.floor(points[:, :3].astype(np.float64) / voxel).astype(np.int64)
    _, sums, counts = _reduce_cells(cells, points.astype(np.float64), np.ones(len(points), np.int64))
    out = (sums / counts[:, None]).astype(points.dtype if points.dtype.kind == "f" else np.float32)
    return (out, counts.astype(np.int64)) if return_counts else out
