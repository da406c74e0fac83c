"""Observed free space from depth frames.

A point x is known-free when some camera sees it in front of the observed surface: x projects inside
the image, the depth at the pixel whose centre is nearest (`pixel_floor_K`) is valid, and x's depth along the optical axis is smaller than the
observed depth by more than `tolerance`. Pixels with no depth (0 / NaN) say nothing. The tests run
in the renderer's native module where it is built (psimap.render.native.depth_test: one pass per
camera over the points not yet decided); the numpy forms `known_free_reference` and
`seen_on_surface_reference` are the readable references, vectorised per camera, and give the same
answers (the same operations in the same order).
"""
from __future__ import annotations

import numpy as np

from psimap import PsimapError
from psimap.transforms import PIXEL_CENTER


def pixel_floor_K(K: np.ndarray) -> np.ndarray:
    """K [3, 3] with its principal point moved so that floor(fx x / z + cx) is the pixel whose
    centre is nearest (pixel u spans [u + PIXEL_CENTER - 0.5, u + PIXEL_CENTER + 0.5): OpenCV's
    centres at integers), as psimap.camera.nearest_pixels rounds. The depth tests floor (the
    native kernel's cast truncates); with K itself they read the pixel half a pixel up and left."""
    K = np.array(K, np.float64)
    K[:2, 2] += 0.5 - PIXEL_CENTER
    return K


def check_cameras(cameras, depths) -> list[tuple[np.ndarray, np.ndarray, int, int, np.ndarray]]:
    """Validate (K [3,3], c2w [4,4] OpenCV, W, H) and depth [H, W] pairs. Returns a list of tuples."""
    cameras = list(cameras or [])
    depths = list(depths or [])
    if len(cameras) != len(depths):
        raise PsimapError(f"completion context: {len(cameras)} cameras but {len(depths)} depth maps")
    out = []
    for i, (cam, d) in enumerate(zip(cameras, depths)):
        K, c2w, w, h = cam
        K = np.asarray(K, dtype=np.float64)
        c2w = np.asarray(c2w, dtype=np.float64)
        d = np.asarray(d, dtype=np.float64)
        if K.shape != (3, 3) or c2w.shape != (4, 4) or not (np.isfinite(K).all() and np.isfinite(c2w).all()):
            raise PsimapError(f"completion context: camera {i} needs a finite K [3,3] and c2w [4,4]")
        if d.shape != (int(h), int(w)):
            raise PsimapError(f"completion context: depth {i} has shape {d.shape}, camera says {(h, w)}")
        out.append((K, c2w, int(w), int(h), d))
    return out


def cameras_seeing(cameras, lo: np.ndarray, hi: np.ndarray):
    """The cameras whose image contains some corner or the centre of the box [lo, hi] in front of
    them: only those can say anything about the object's surroundings (a scan has hundreds)."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    corners = np.concatenate([corners, [0.5 * (lo + hi)]])
    keep = []
    for cam in cameras:
        K, c2w, w, h, _ = cam
        pc = (corners - c2w[:3, 3]) @ c2w[:3, :3]
        z = pc[:, 2]
        front = z > 1e-6
        if not front.any():
            continue
        Kp = pixel_floor_K(K)
        u = Kp[0, 0] * pc[front, 0] / z[front] + Kp[0, 2]
        v = Kp[1, 1] * pc[front, 1] / z[front] + Kp[1, 2]
        if ((u >= 0) & (u < w) & (v >= 0) & (v < h)).any():
            keep.append(cam)
    return keep


def _depth_at(points: np.ndarray, cam) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(z [Q], observed depth d [Q], valid [Q]) of world points [Q, 3] in one camera (K, c2w, w, h,
    depth): z their own z-depth, d the depth map at their pixel; valid = in front, inside the image,
    a finite positive depth there (invalid returns are 0 or non-finite)."""
    K, c2w, w, h, depth = cam
    K = pixel_floor_K(K)
    # world -> camera: R^T (x - t), each coordinate summed in the native kernel's order (a BLAS
    # product may fuse or reorder the sums: a point on a pixel border could land on the other side)
    R = c2w[:3, :3]
    with np.errstate(invalid="ignore", over="ignore"):      # non-finite points come out invalid
        dx, dy, dz = (points - c2w[:3, 3]).T
        z = dx * R[0, 2] + dy * R[1, 2] + dz * R[2, 2]
        ok = z > 1e-6
        zs = np.where(ok, z, 1.0)
        u = np.floor(K[0, 0] * (dx * R[0, 0] + dy * R[1, 0] + dz * R[2, 0]) / zs + K[0, 2])
        v = np.floor(K[1, 1] * (dx * R[0, 1] + dy * R[1, 1] + dz * R[2, 1]) / zs + K[1, 2])
        ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    # one gather for every point, those outside the image (or not finite) at pixel 0: they are
    # invalid anyway (a masked gather and scatter took a third of the time)
    flat = np.where(ok, v * w + u, 0.0).astype(np.int64)
    d = depth.ravel().take(flat)
    ok &= np.isfinite(d) & (d > 0)
    d[~ok] = 0.0
    return z, d, ok


def _native_depth_test():
    """psimap.render.native.depth_test where the native module is built, else None."""
    from psimap.render.api import native_available

    if not native_available():
        return None
    from psimap.render.native import depth_test

    return depth_test


def _any_camera(points: np.ndarray, cameras, tolerance: float, surface: bool, test) -> np.ndarray:
    state = np.zeros(len(points), dtype=np.uint8)
    if len(state):
        points = np.ascontiguousarray(points, dtype=np.float64)
        for K, c2w, _, _, depth in cameras:
            test(points, c2w, pixel_floor_K(K), depth, tolerance, surface, state)
    return state.view(bool)


def known_free(points: np.ndarray, cameras, tolerance: float) -> np.ndarray:
    """points [Q, 3] world; cameras from `check_cameras`. Returns [Q] bool: seen empty by a camera
    (in front of its depth by more than `tolerance`). The native kernel where it is built (a real
    capture's completion asked ~300k grid points of 16 cameras ~270 times: ~12 s of numpy), else
    `known_free_reference`."""
    test = _native_depth_test()
    if test is None:
        return known_free_reference(points, cameras, tolerance)
    return _any_camera(points, cameras, tolerance, False, test)


def seen_on_surface(points: np.ndarray, cameras, tolerance: float) -> np.ndarray:
    """points [Q, 3] that some camera saw as surface: they project inside its image onto a valid
    depth within `tolerance` of their own depth. Returns [Q] bool (native where built, else
    `seen_on_surface_reference`)."""
    test = _native_depth_test()
    if test is None:
        return seen_on_surface_reference(points, cameras, tolerance)
    return _any_camera(points, cameras, tolerance, True, test)


def known_free_reference(points: np.ndarray, cameras, tolerance: float) -> np.ndarray:
    """`known_free` in numpy, vectorised per camera: each camera only tests the points no earlier
    one saw empty (the answer is an "any")."""
    points = np.asarray(points, dtype=np.float64)
    free = np.zeros(len(points), dtype=bool)
    todo = np.arange(len(points))
    for cam in cameras:
        if len(todo) == 0:
            break
        z, d, ok = _depth_at(points[todo], cam)
        hit = ok & (z < d - tolerance)
        free[todo[hit]] = True
        todo = todo[~hit]
    return free


def seen_on_surface_reference(points: np.ndarray, cameras, tolerance: float) -> np.ndarray:
    """`seen_on_surface` in numpy, vectorised per camera."""
    points = np.asarray(points, dtype=np.float64)
    seen = np.zeros(len(points), dtype=bool)
    for cam in cameras:
        z, d, ok = _depth_at(points, cam)
        seen |= ok & (np.abs(z - d) <= tolerance)
    return seen


def free_votes(points: np.ndarray, cameras, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """(free [Q] int, valid [Q] int) of points [Q, 3]: how many of `cameras` (check_cameras) see each
    point empty (in front of their depth by more than `tolerance`), and how many have a valid depth
    at its pixel at all. A ratio over the cameras, unlike `known_free`'s "any": a single view through
    a pinhole of a reconstructed surface does not make the space behind it empty."""
    points = np.asarray(points, dtype=np.float64)
    free = np.zeros(len(points), dtype=np.int64)
    valid = np.zeros(len(points), dtype=np.int64)
    for cam in cameras:
        z, d, ok = _depth_at(points, cam)
        free += ok & (z < d - tolerance)
        valid += ok
    return free, valid


def free_space_share(mesh, free_fn, pitch: float) -> float:
    """Share of the cells (of `pitch`, coarser past meshops.CUT_CELLS) inside closed `mesh` that
    free_fn (q [Q, 3] -> bool [Q]) says a camera saw empty; 0 when no cell lies inside."""
    from .meshops import CUT_CELLS, grid_points, inside

    g, _, _, _ = grid_points(mesh.bounds[0], mesh.bounds[1], pitch, max_cells=CUT_CELLS)
    g = g[inside(g, mesh)]
    return float(free_fn(g).mean()) if len(g) else 0.0


def free_fraction(mesh, cameras, tolerance: float, pitch: float) -> float:
    """Share of the volume of closed `mesh` that lies in known free space (grid at `pitch`)."""
    if not cameras or mesh is None:
        return 0.0
    return free_space_share(mesh, lambda q: known_free(q, cameras, tolerance), pitch)
