"""Camera helpers shared by every stage (OpenCV convention: x right, y down, z forward; world Z-up)."""
from __future__ import annotations

import numpy as np

from psimap.transforms import camera_to_pixels, scale_intrinsics, transform_points


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world [4, 4] (OpenCV axes) at `eye` looking at `target`.

    When the view direction is parallel to `up` (looking straight down or up), the image x axis is
    taken along world x so the pose is still well defined.
    """
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return c2w


def orbit(n: int, radius: float, height: float, target=(0.0, 0.0, 0.0)) -> list[np.ndarray]:
    """n camera-to-world poses evenly spaced on a horizontal circle, all looking at `target`."""
    t = np.asarray(target, dtype=np.float64)
    return [look_at(t + np.array([radius * np.cos(a), radius * np.sin(a), height]), t)
            for a in np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)]


def camera_rig(c2ws, width: int, height: int, focal: float) -> dict:
    """The cameras of a scene (psimap.scene.Scene / checkpoint format): one pinhole of `focal`
    pixels, principal point at the image centre, for every camera-to-world pose in c2ws [M, 4, 4];
    named c0, c1, ..."""
    c2ws = np.asarray(c2ws, np.float64).reshape(-1, 4, 4)
    K = np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    return {"K": np.stack([K] * len(c2ws)), "c2w": c2ws, "width": int(width), "height": int(height),
            "names": [f"c{i}" for i in range(len(c2ws))]}


def supersample_intrinsics(K, ss: int) -> np.ndarray:
    """K [3, 3] of an image with ss x ss samples per pixel of the image K describes.

    With pixel centres at integers (OpenCV, psimap.transforms.PIXEL_CENTER) the samples of pixel x
    sit at x + (i + 0.5) / ss - 0.5, i.e. at X = ss x + (ss - 1) / 2 in the fine image. ss must be
    a positive integer (PsimapError).
    """
    from psimap import PsimapError

    if int(ss) != ss or ss < 1:
        raise PsimapError(f"supersample must be a positive integer, got {ss}")
    return scale_intrinsics(K, int(ss))


def nearest_pixels(points: np.ndarray, K: np.ndarray, c2w: np.ndarray, width: int, height: int,
                   near: float = 1e-6) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Project world points [P, 3] into a pinhole view (K [3, 3], c2w [4, 4] OpenCV camera-to-world):
    (u [P], v [P]) int64 nearest pixel, clipped into the image so it can index it; z [P] camera
    depth; inside [P] bool: in front (z > near) and within the image before clipping."""
    pc = transform_points(np.asarray(points, np.float64), np.linalg.inv(np.asarray(c2w, np.float64)))
    z = pc[:, 2]
    front = z > near
    u, v = camera_to_pixels(pc[:, 0], pc[:, 1], np.where(front, z, 1.0), K)
    u, v = np.round(u).astype(np.int64), np.round(v).astype(np.int64)
    inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return u.clip(0, width - 1), v.clip(0, height - 1), z, inside
