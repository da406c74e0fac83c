"""LiDAR in training: sweeps as SOGMM prior input and as a range term of the losses (paper §3.2: the
prior is LiDAR-driven; here LiDAR joins whatever depth images the capture has, or replaces them).

A sweep is world points [N, 3] with the sensor position. The renderer is a pinhole rasteriser, so
each sweep is seen through virtual pinhole cameras at its origin: the six faces of a cube (90° each),
each cropped to the pixels its returns fall on, at the sweep's own angular resolution. The range term
compares the rendered depth, sampled bilinearly at each return's exact sub-pixel position (no
quantisation to pixel centres), with the return's depth along that camera's axis. Each return is
weighted by the ratio of the depth images' noise at its range (psimap.geometry.depth_noise, the model
the prior already uses) to the LiDAR's own range noise, estimated from the sweep, at most 1: near
returns, where a depth camera is more precise, count less than its pixels; far ones count as much.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

# Virtual views: pixels per side at most (a face covers 90°), and at least; a face needs this many
# returns to become a view (fewer: a few stray points, not worth a render).
VIEW_MAX_SIDE = 256
VIEW_MIN_SIDE = 16
VIEW_MIN_RETURNS = 64
# A view's pixel spans this many angular steps of the sweep: a spinning LiDAR's rings are several
# azimuth steps apart, so finer pixels are mostly empty; the rendered depth is sampled bilinearly at
# each return's exact position anyway. 2 renders a quarter of the pixels of 1, at the same speed per
# pixel (a render of a view costs about what a 160x120 frame does at 1).
VIEW_PIXEL_STEPS = 2.0
# Range noise assumed when a sweep is too sparse to measure its own (a typical spinning LiDAR).
DEFAULT_RANGE_NOISE = 0.02
# A return's weight (depth-image noise at its range / range noise) is kept within these bounds: a
# return never counts more than a depth pixel. Above 1 the range term overrode the depth and colour
# terms wherever the depth camera is poor and the map got worse (benchmarks/lidar.py, seed 0: F1@5cm
# 0.955 vs 0.965 with the default depth sensor, 0.943 vs 0.960 with one 3x as noisy); the floor keeps
# near returns, where a depth camera is far more precise, from vanishing.
WEIGHT_RANGE = (0.1, 1.0)

# The cube's faces: camera-to-sensor rotations whose third column (the optical axis) is +-x, +-y, +-z.
_AXES = np.eye(3)


def _face_rotations() -> list[np.ndarray]:
    out = []
    for i in range(3):
        for sign in (1.0, -1.0):
            z = sign * _AXES[i]
            helper = _AXES[(i + 1) % 3]
            x = np.cross(helper, z)
            x /= np.linalg.norm(x)
            y = np.cross(z, x)
            out.append(np.stack([x, y, z], axis=1))
    return out


@dataclass
class Sweep:
    """One LiDAR sweep: points [N, 3] world metres, intensity [N] in [0, 1], origin [3] world."""

    points: np.ndarray
    intensity: np.ndarray
    origin: np.ndarray
    name: str = ""


@dataclass
class LidarView:
    """A virtual pinhole camera at a sweep's origin and the returns it sees.

    K [3, 3] float32 tensor, viewmat [4, 4] float32 world-to-camera, c2w [4, 4] float64 numpy,
    width / height (pixels); uv [M, 2] float32 sub-pixel image coordinates of the returns, z [M]
    their depths along the optical axis and r [M] their ranges (metres); w [M] the range term's
    weight of each (range_weight; ones until the trainer sets them)."""

    name: str
    K: torch.Tensor
    viewmat: torch.Tensor
    c2w: np.ndarray
    width: int
    height: int
    uv: torch.Tensor
    z: torch.Tensor
    r: np.ndarray
    w: torch.Tensor


def sweep_of(frame, name: str = "") -> Sweep | None:
    """The Sweep of a frame's `lidar` [N, 3|4] (None when it has none). The sensor origin is the
    frame's `lidar_origin` [3] when the loader gives one, else its camera centre (a head-mounted or
    hand-held rig's LiDAR is centimetres from the camera, and the virtual views only need the
    returns' directions to be about right)."""
    from psimap.geometry.points import lidar_points

    raw = getattr(frame, "lidar", None)
    if raw is None or len(raw) == 0:
        return None
    pts = lidar_points(raw)
    if len(pts) == 0:
        return None
    origin = getattr(frame, "lidar_origin", None)
    if origin is None:
        origin = np.asarray(frame.c2w, np.float64)[:3, 3]
    return Sweep(points=pts[:, :3].astype(np.float64), intensity=pts[:, 3].astype(np.float32),
                 origin=np.asarray(origin, np.float64), name=name)


def angular_step(sweep: Sweep) -> float:
    """Median angle (rad) between a return and its nearest neighbour in direction: the sweep's
    finest angular resolution (the azimuth step of a spinning LiDAR)."""
    from scipy.spatial import cKDTree

    d = sweep.points - sweep.origin
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    if len(d) < 2:
        return float(np.pi / 2)
    sub = d[:: max(1, len(d) // 20_000)]
    dist, _ = cKDTree(d).query(sub, k=2)
    return float(max(np.median(dist[:, 1]), 1e-4))


def lidar_views(sweep: Sweep, max_depth: float = 0.0) -> list[LidarView]:
    """Virtual cube-face views of one sweep (those with at least VIEW_MIN_RETURNS returns), each
    cropped to the pixel box of its returns. Pixel size: VIEW_PIXEL_STEPS of the sweep's angular
    steps at the face centre, VIEW_MIN_SIDE..VIEW_MAX_SIDE pixels per 90°."""
    from psimap.transforms import camera_to_pixels

    side = int(np.clip(np.ceil(2.0 / (VIEW_PIXEL_STEPS * angular_step(sweep))), VIEW_MIN_SIDE, VIEW_MAX_SIDE))
    f = side / 2.0
    rel = sweep.points - sweep.origin
    if max_depth > 0:
        rel = rel[np.linalg.norm(rel, axis=1) <= max_depth]
    # each return belongs to one face: the one its direction's largest component points through
    dom = np.argmax(np.abs(rel), axis=1)
    positive = rel[np.arange(len(rel)), dom] > 0
    views = []
    for k, R in enumerate(_face_rotations()):
        mine = (dom == k // 2) & (positive == (k % 2 == 0))
        if mine.sum() < VIEW_MIN_RETURNS:
            continue
        xc, yc, zc = (rel[mine] @ R).T                  # world offsets -> face camera
        u, v = camera_to_pixels(xc, yc, zc, np.array([[f, 0, f - 0.5], [0, f, f - 0.5], [0, 0, 1]]))
        u0, v0 = int(np.floor(u.min())), int(np.floor(v.min()))
        u1, v1 = int(np.ceil(u.max())), int(np.ceil(v.max()))
        w, h = u1 - u0 + 1, v1 - v0 + 1
        K = np.array([[f, 0.0, f - 0.5 - u0], [0.0, f, f - 0.5 - v0], [0.0, 0.0, 1.0]])
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = R, sweep.origin
        views.append(LidarView(
            name=f"{sweep.name}/face{k}", K=torch.as_tensor(K, dtype=torch.float32),
            viewmat=torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32), c2w=c2w, width=w, height=h,
            uv=torch.as_tensor(np.stack([u - u0, v - v0], 1), dtype=torch.float32),
            z=torch.as_tensor(zc, dtype=torch.float32), r=np.linalg.norm(rel[mine], axis=1),
            w=torch.ones(len(zc))))
    return views


def sample_depth(depth: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear samples [M] of a depth map [H, W] at sub-pixel image coordinates uv [M, 2] (pixel
    (u, v) centred at integer coordinates, psimap.transforms.PIXEL_CENTER = 0); differentiable."""
    H, W = depth.shape
    gx = 2.0 * uv[:, 0] / max(W - 1, 1) - 1.0
    gy = 2.0 * uv[:, 1] / max(H - 1, 1) - 1.0
    grid = torch.stack([gx, gy], -1).view(1, 1, -1, 2)
    return torch.nn.functional.grid_sample(depth[None, None], grid, mode="bilinear",
                                           align_corners=True).view(-1)


def range_l1(depth: torch.Tensor, view: LidarView, weighted: bool = True) -> torch.Tensor:
    """Mean |rendered depth - measured depth| over the returns of a view (metres), each times its
    weight view.w when `weighted`; depth [H, W]."""
    if view.z.numel() == 0:
        return depth.sum() * 0.0
    err = (sample_depth(depth, view.uv) - view.z).abs()
    return (err * view.w).mean() if weighted else err.mean()


def range_noise(sweeps: list[Sweep]) -> float:
    """The LiDAR's range-noise std (m): the median of the sweeps' own estimates
    (psimap.geometry.depth_noise.estimate_lidar_noise), DEFAULT_RANGE_NOISE when none is measurable."""
    from psimap.geometry.depth_noise import estimate_lidar_noise

    est = [s for s in (estimate_lidar_noise(sw.points, sw.origin) for sw in sweeps) if s is not None]
    return float(np.median(est)) if est else DEFAULT_RANGE_NOISE


def range_weight(depth_sigma, lidar_sigma: float):
    """Weight of a return in the range term beside the depth-image term (both L1 per metre): the
    depth images' noise at its range over the LiDAR's range noise, within WEIGHT_RANGE. depth_sigma:
    a float or [M] array; None (no depth images) gives 1: the range term is then the only geometry
    data term and takes the depth term's place."""
    if depth_sigma is None:
        return 1.0
    ratio = np.asarray(depth_sigma, np.float64) / max(lidar_sigma, 1e-5)
    out = np.clip(np.where(np.isfinite(ratio) & (ratio > 0), ratio, 1.0), *WEIGHT_RANGE)
    return float(out) if out.ndim == 0 else out


def colour_returns(sweeps: list[Sweep], frames) -> tuple[np.ndarray, np.ndarray]:
    """World points [P, 3] and colours [P, 3] in [0, 1] of every return. A return takes the colour of
    the first training frame that sees it (in view, and not behind the frame's own observed depth
    where it has one); a return no camera sees is grey at its intensity, so the prior's grey channel
    still separates bright and dark materials."""
    pts = np.concatenate([s.points for s in sweeps]) if sweeps else np.zeros((0, 3))
    inten = np.concatenate([s.intensity for s in sweeps]) if sweeps else np.zeros(0, np.float32)
    cols = np.repeat(inten[:, None], 3, 1).astype(np.float32)
    todo = np.ones(len(pts), bool)
    for fr in frames:
        if not todo.any():
            break
        idx = np.flatnonzero(todo)
        sel, ui, vi, z = in_view(pts[idx], fr)
        d = fr.depth.numpy()[vi, ui]
        # an occluded return (behind the observed surface by more than a few cm) keeps looking
        visible = (d <= 0) | (z <= d * 1.03 + 0.02)
        sel, ui, vi = sel[visible], ui[visible], vi[visible]
        cols[idx[sel]] = fr.rgb.numpy()[vi, ui]
        todo[idx[sel]] = False
    return pts, cols


def in_view(points: np.ndarray, fr) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The points [P, 3] (world) a training frame sees: (indices [M], pixel column [M], row [M],
    depth along its optical axis [M]), nearest pixel, in front of the camera and inside the image."""
    from psimap.transforms import camera_to_pixels, transform_points

    cam = transform_points(points, np.linalg.inv(fr.c2w))
    ok = np.flatnonzero(cam[:, 2] > 1e-3)
    u, v = camera_to_pixels(cam[ok, 0], cam[ok, 1], cam[ok, 2], fr.K.numpy().astype(np.float64))
    ui, vi = np.round(u).astype(np.int64), np.round(v).astype(np.int64)
    inside = (ui >= 0) & (ui < fr.width) & (vi >= 0) & (vi < fr.height)
    return ok[inside], ui[inside], vi[inside], cam[ok[inside], 2]


def depths_in_frames(sweeps: list[Sweep], frames) -> np.ndarray:
    """Depths [M] (along each frame's optical axis) of the returns in view of the frames: what the
    cameras would have measured, for a capture without depth images."""
    pts = np.concatenate([s.points for s in sweeps])
    out = [in_view(pts, fr)[3] for fr in frames]
    return np.concatenate(out) if out else np.zeros(0)


def prior_returns(sweeps: list[Sweep], frames, budget: int) -> np.ndarray:
    """The returns as SOGMM input [P, 4] (x, y, z, grey): colour from the frames (colour_returns),
    grey by the same weights as the depth pixels, at most `budget` returns (evenly subsampled)."""
    from psimap.geometry.points import rgb_to_grey

    pts, cols = colour_returns(sweeps, frames)
    step = max(1, int(np.ceil(len(pts) / max(budget, 1))))
    pts, cols = pts[::step], cols[::step]
    return np.concatenate([pts, rgb_to_grey(cols)[:, None]], 1).astype(np.float32)
