"""Radial-tangential lens distortion (OpenCV / COLMAP `OPENCV` model, nerfstudio's k1..k4, p1, p2):
how far it moves pixels, and undistortion of an image to the pinhole camera with the same K.

The model maps a normalised pinhole point (x, y) to the distorted one:
    r2 = x^2 + y^2,  d = 1 + k1 r2 + k2 r2^2 + k3 r2^3 + k4 r2^4
    xd = x d + 2 p1 x y + p2 (r2 + 2 x^2),   yd = y d + 2 p2 x y + p1 (r2 + 2 y^2)
Undistorting an image needs exactly this forward map (for every output pixel, where in the
distorted image to sample), so no iterative inversion is involved; scipy resamples.
"""
from __future__ import annotations

import numpy as np

from psimap.transforms import PIXEL_CENTER

COEFFS = ("k1", "k2", "k3", "k4", "p1", "p2")


def distort(x: np.ndarray, y: np.ndarray, coeffs: dict) -> tuple[np.ndarray, np.ndarray]:
    """Distorted normalised coordinates of pinhole ones x, y [...]; coeffs: {k1..k4, p1, p2}."""
    k1, k2, k3, k4, p1, p2 = (float(coeffs.get(k, 0.0)) for k in COEFFS)
    r2 = x * x + y * y
    d = 1.0 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
    xd = x * d + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * d + 2.0 * p2 * x * y + p1 * (r2 + 2.0 * y * y)
    return xd, yd


def _source_pixels(K: np.ndarray, shape: tuple[int, int], coeffs: dict, step: int = 1):
    """(u, v) of every `step`-th output pixel and the distorted-image position it samples."""
    h, w = shape
    v, u = np.mgrid[0:h:step, 0:w:step].astype(np.float64)
    x = (u + PIXEL_CENTER - K[0, 2]) / K[0, 0]
    y = (v + PIXEL_CENTER - K[1, 2]) / K[1, 1]
    xd, yd = distort(x, y, coeffs)
    return u, v, K[0, 0] * xd + K[0, 2] - PIXEL_CENTER, K[1, 1] * yd + K[1, 2] - PIXEL_CENTER


def max_displacement(K: np.ndarray, shape: tuple[int, int], coeffs: dict) -> float:
    """The largest shift (pixels) the distortion applies to a pixel of an image of `shape` (H, W)
    seen through K [3, 3]: radial distortion peaks at the borders, so a coarse grid that includes
    them is enough."""
    h, w = shape
    step = max(1, min(h, w) // 32)
    u, v, us, vs = _source_pixels(K, shape, coeffs, step)
    # The grid's last row / column may stop short of the border: add the four corners.
    cu = np.array([0.0, w - 1.0, 0.0, w - 1.0])
    cv = np.array([0.0, 0.0, h - 1.0, h - 1.0])
    cx, cy = distort((cu + PIXEL_CENTER - K[0, 2]) / K[0, 0], (cv + PIXEL_CENTER - K[1, 2]) / K[1, 1], coeffs)
    corner = np.hypot(K[0, 0] * cx + K[0, 2] - PIXEL_CENTER - cu, K[1, 1] * cy + K[1, 2] - PIXEL_CENTER - cv)
    return float(max(np.hypot(us - u, vs - v).max(initial=0.0), corner.max()))


def undistort(image: np.ndarray, K: np.ndarray, coeffs: dict, order: int) -> np.ndarray:
    """image [H, W] or [H, W, C] taken through K [3, 3] with distortion `coeffs` -> the image a
    pinhole camera with the same K sees. order 1 (bilinear) for colour, 0 (nearest) for depth and
    labels, whose values must not be blended. Pixels that map outside the source are 0 (invalid)."""
    from scipy.ndimage import map_coordinates

    h, w = image.shape[:2]
    _, _, us, vs = _source_pixels(np.asarray(K, np.float64), (h, w), coeffs)
    coords = np.stack([vs, us])
    if image.ndim == 2:
        return map_coordinates(image, coords, order=order, mode="constant", cval=0).astype(image.dtype)
    return np.stack([map_coordinates(image[..., c], coords, order=order, mode="constant", cval=0)
                     for c in range(image.shape[2])], axis=-1).astype(image.dtype)
