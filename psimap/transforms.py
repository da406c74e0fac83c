"""Camera, rotation and surface-sampling maths every stage shares: plain functions over plain arrays.

The conventions live here once, so fixing one for every caller is a one-line change:
- pixels (`PIXEL_CENTER`): OpenCV, pixel (u, v) is centred at integer image coordinates; a
  camera point (x, y, z) (x right, y down, z forward) is at u = fx x / z + cx, v = fy y / z + cy.
- quaternions (`_wxyz`, `_from_wxyz`): (w, x, y, z), scalar first, any non-zero norm (normalised
  inside), w >= 0 when produced here.
- rigid transforms: [4, 4] matrices acting on row vectors, points [..., 3] @ R.T + t.

numpy functions return float64. `*_torch` functions are the same maths on torch tensors, for
callers that need autograd or keep their data in torch; they use the dtype they are given.
numpy is the only import at module level (torch and scipy load inside the functions that need
them), so every stage can import this module cheaply.
"""
from __future__ import annotations

import numpy as np

# Image coordinate of the centre of pixel index 0 (OpenCV: 0.0; a half-pixel convention is 0.5).
PIXEL_CENTER = 0.0


# ---- pixels <-> camera ------------------------------------------------------------------------

def _camera_xy(u, v, z, K):
    """Camera x, y of pixels (u, v) at z-depth z: operators only, so numpy and torch share it."""
    x = (u + PIXEL_CENTER - K[0, 2]) / K[0, 0] * z
    y = (v + PIXEL_CENTER - K[1, 2]) / K[1, 1] * z
    return x, y


def pixels_to_camera(u, v, z, K) -> np.ndarray:
    """Camera points [..., 3] of pixel indices u, v [...] (int or float) at z-depth z [...] metres.

    K: [3, 3] pinhole intrinsics. float64 throughout (indices and depths are converted).
    """
    K = np.asarray(K, np.float64)
    z = np.asarray(z, np.float64)
    x, y = _camera_xy(np.asarray(u), np.asarray(v), z, K)
    return np.stack([x, y, z], axis=-1)


def pixels_to_camera_torch(u, v, z, K):
    """torch `pixels_to_camera`: u, v [...] float tensors (pass them in the dtype wanted: integer
    indices would be promoted to float32), z [...] (gradients flow through it), K [3, 3] tensor."""
    import torch

    x, y = _camera_xy(u, v, z, K)
    return torch.stack([x, y, z], dim=-1)


def camera_to_pixels(x, y, z, K):
    """Image coordinates (u [...], v [...]) of camera points (x, y, z) [...]: pixel index u is the
    pixel whose centre is nearest (round them). z must be non-zero (callers mask points behind)."""
    u = K[0, 0] * x / z + K[0, 2] - PIXEL_CENTER
    v = K[1, 1] * y / z + K[1, 2] - PIXEL_CENTER
    return u, v


def scale_intrinsics(K, s: float) -> np.ndarray:
    """K [3, 3] of the same view resampled to s times as many pixels per side (s > 1 finer).

    Pixel edges scale, centres do not: pixel u spans [u + PIXEL_CENTER - 0.5, u + PIXEL_CENTER +
    0.5), so the principal point moves by (0.5 - PIXEL_CENTER) (s - 1). Returns a new float64 array.
    """
    K = np.array(K, np.float64)
    K[:2, :] *= s
    K[:2, 2] += (0.5 - PIXEL_CENTER) * (s - 1)
    return K


def transform_points(points, T):
    """points [..., 3] mapped by the rigid transform T [4, 4] (e.g. camera-to-world): p @ R.T + t.

    Operators only: numpy arrays and torch tensors (same dtype as T) alike. A numpy [P, 3] @ [3, 3]
    product goes to OpenBLAS, whose worker threads spin-wait for a CPU: on a busy 2-core machine
    700k points took 180 ms a call and 9 s of an export's texture bake (the same einsum: 12 ms, one
    thread, equal to 1 ulp).
    """
    if isinstance(points, np.ndarray):
        return np.einsum("pj,ij->pi", points.reshape(-1, 3), T[:3, :3]).reshape(points.shape) + T[:3, 3]
    return points @ T[:3, :3].T + T[:3, 3]


def depth_to_world(depth: np.ndarray, K: np.ndarray, c2w: np.ndarray, *, stride: int = 1,
                   max_depth: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points of every `stride`-th valid pixel of a depth image.

    depth: [H, W] metres (0 or non-finite = no return); K: [3, 3]; c2w: [4, 4] camera-to-world
    (OpenCV axes); max_depth: pixels farther than this are dropped too.
    Returns (points [P, 3] float64, v [P], u [P]): the row and column of each point's pixel in the
    full-resolution image (multiples of stride), in row-major order.
    """
    d = np.asarray(depth)[::stride, ::stride].astype(np.float64)
    valid = np.isfinite(d) & (d > 0)
    if max_depth is not None:
        valid &= d <= max_depth
    v, u = np.nonzero(valid)
    z = d[v, u]
    v, u = v * stride, u * stride
    cam = pixels_to_camera(u, v, z, K)
    return transform_points(cam, np.asarray(c2w, np.float64)), v, u


# ---- quaternions <-> rotations ----------------------------------------------------------------

def _wxyz(c):
    """Components (w, x, y, z) from the four slices c along the quaternion axis (this module's order)."""
    return c[0], c[1], c[2], c[3]


def _from_wxyz(w, x, y, z) -> np.ndarray:
    """Quaternions [..., 4] in this module's order from their components."""
    return np.stack([w, x, y, z], axis=-1)


def _rotation_entries(w, x, y, z) -> list:
    """The nine entries of the rotation matrix of the unit quaternion (w, x, y, z), row by row."""
    return [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]


def quat_to_rotmat(quats) -> np.ndarray:
    """Quaternions [..., 4] (w, x, y, z) -> rotation matrices [..., 3, 3] float64 (columns = the
    rotated axes; for a surfel, its two tangents and its normal). The quaternions are normalised
    first; a zero quaternion gives the identity."""
    q = np.asarray(quats, np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    q = q / np.where(norm > 0, norm, 1.0)
    R = np.stack(_rotation_entries(*_wxyz(np.moveaxis(q, -1, 0))), axis=-1)
    return R.reshape(q.shape[:-1] + (3, 3))


def quat_to_rotmat_torch(quats):
    """torch `quat_to_rotmat`: quats [..., 4] tensor (any dtype; differentiable) -> [..., 3, 3]."""
    import torch

    norm = quats.norm(dim=-1, keepdim=True)
    q = quats / torch.where(norm > 0, norm, torch.ones_like(norm))
    R = torch.stack(_rotation_entries(*_wxyz(q.unbind(-1))), dim=-1)
    return R.reshape(quats.shape[:-1] + (3, 3))


def rotmat_to_quat(R) -> np.ndarray:
    """Rotation matrices [..., 3, 3] -> unit quaternions [..., 4] (w, x, y, z) float64 with w >= 0
    (q and -q are the same rotation; one sign makes outputs reproducible). scipy's conversion."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, np.float64)
    xyzw = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    q = _from_wxyz(xyzw[:, 3], xyzw[:, 0], xyzw[:, 1], xyzw[:, 2])
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(R.shape[:-2] + (4,))


# ---- surfaces ---------------------------------------------------------------------------------

def sample_surface(mesh, count: int, seed: int = 0, *, with_vertices: bool = False) -> np.ndarray:
    """`count` points [count, 3] float64 uniformly distributed over the area of a triangle mesh
    (anything with .triangles [F, 3, 3], .area_faces [F], .vertices [V, 3], e.g. trimesh.Trimesh),
    from numpy's default_rng(seed): the same seed gives the same points.

    with_vertices: append every vertex [V, 3] (so corners and thin spikes are never missed).
    A mesh without area gives its vertices only.
    """
    rng = np.random.default_rng(seed)
    tri = np.asarray(mesh.triangles, np.float64)                   # [F, 3, 3]
    area = np.asarray(mesh.area_faces, np.float64)
    vertices = np.asarray(mesh.vertices, np.float64)
    if not area.sum() > 0:
        return vertices
    face = rng.choice(len(tri), size=count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    # uniform barycentric coordinates: fold the unit square onto the triangle with a square root
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    pts = np.einsum("nk,nkd->nd", w, tri[face])
    return np.concatenate([pts, vertices]) if with_vertices else pts
