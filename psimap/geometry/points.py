"""4D point clouds (x, y, z world metres, grey intensity in [0, 1]) for the SOGMM prior.

Sources: back-projected depth frames (grey from the registered RGB image) and LiDAR sweeps
([N, 4] x, y, z, intensity). Everything here is plain numpy so it stays cheap to import.
"""
from __future__ import annotations

from typing import Iterable

import numpy as np

from psimap import PsimapError

# ITU-R BT.601 luma weights: the usual grey conversion of an sRGB image.
_GREY = np.array([0.299, 0.587, 0.114], dtype=np.float32)


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
    d = depth[::stride, ::stride].astype(np.float64)
    valid = np.isfinite(d) & (d > 0)
    if max_depth is not None:
        valid &= d <= max_depth
    v, u = np.nonzero(valid)
    z = d[v, u]
    # pixel centres of the strided grid in full-resolution pixel units
    px = u * stride + 0.0
    py = v * stride + 0.0
    x = (px - K[0, 2]) / K[0, 0] * z
    y = (py - K[1, 2]) / K[1, 1] * z
    cam = np.stack([x, y, z], axis=1)
    world = cam @ c2w[:3, :3].T + c2w[:3, 3]
    if rgb is None:
        grey = np.full(len(z), 0.5, dtype=np.float32)
    else:
        img = np.asarray(rgb)
        if img.shape[:2] != depth.shape:
            raise PsimapError(f"colour image {img.shape[:2]} and depth {depth.shape} differ in size")
        img = img[::stride, ::stride][v, u, :3].astype(np.float32)
        if np.asarray(rgb).dtype == np.uint8:
            img /= 255.0
        grey = np.clip(img @ _GREY, 0.0, 1.0)
    return np.concatenate([world.astype(np.float32), grey[:, None]], axis=1)


def frames_to_points(frames: Iterable, *, max_depth: float | None = None, stride: int = 1,
                     voxel: float | None = None) -> np.ndarray:
    """Back-project every frame (objects with .rgb [H,W,3], .depth [H,W], .K, .c2w, optional .lidar
    [N,4]) and concatenate, LiDAR included. Frames with no valid depth contribute nothing.
    voxel: if given, voxel-downsample the union. Returns [N, 4] float32 (x, y, z, grey)."""
    parts = []
    for f in frames:
        parts.append(backproject_frame(f.rgb, f.depth, f.K, f.c2w, max_depth=max_depth, stride=stride))
        lidar = getattr(f, "lidar", None)
        if lidar is not None and len(lidar):
            parts.append(lidar_points(lidar))
    pts = np.concatenate(parts, axis=0) if parts else np.zeros((0, 4), np.float32)
    if voxel is not None and len(pts):
        pts = voxel_downsample(pts, voxel)
    return pts


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


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Average every column of `points` [N, D] (x, y, z first) over occupied cubes of side `voxel`.

    Quantise, sort by cell key, and average each run with np.add.reduceat: O(N log N), no Python
    loop. Output rows are ordered by cell key, so the result is deterministic. Returns [M, D].
    """
    points = np.asarray(points)
    if len(points) == 0:
        return points.copy()
    if not (voxel > 0 and np.isfinite(voxel)):
        raise PsimapError(f"voxel size must be a positive number, got {voxel}")
    xyz = points[:, :3].astype(np.float64)
    cell = np.floor((xyz - xyz.min(axis=0)) / voxel).astype(np.int64)
    dims = cell.max(axis=0) + 1
    if np.prod(dims.astype(np.float64)) < 2 ** 62:
        key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
        order = np.argsort(key, kind="stable")
        skey = key[order]
        starts = np.flatnonzero(np.r_[True, skey[1:] != skey[:-1]])
    else:  # astronomically large extent / voxel ratio: fall back to row-wise unique
        _, inverse = np.unique(cell, axis=0, return_inverse=True)
        order = np.argsort(inverse.ravel(), kind="stable")
        sinv = inverse.ravel()[order]
        starts = np.flatnonzero(np.r_[True, sinv[1:] != sinv[:-1]])
    sums = np.add.reduceat(points[order].astype(np.float64), starts, axis=0)
    counts = np.diff(np.r_[starts, len(points)])
    return (sums / counts[:, None]).astype(points.dtype if points.dtype.kind == "f" else np.float32)
