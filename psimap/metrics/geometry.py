"""Geometry metrics (docs/metrics.md): accuracy, completeness, Chamfer-L1, precision / recall / F1.

Points are sampled area-weighted on each mesh; each point's distance to the *other mesh* is the exact
point-to-triangle distance (Open3D's BVH `compute_distance`), so no sample-spacing bias enters the
numbers and identical meshes give exactly 0. The number of samples is chosen by an error budget:
sampling doubles until the Monte-Carlo standard error of every reported figure is within budget
(capped at `max_samples`).

Ground-truth culling: completeness and recall only use GT surface seen by at least one camera
(`visible_faces`: faces hit by some pixel ray; `CameraVisibility.points_seen` then drops samples on
the unseen part of a partly seen face); accuracy and precision use the whole GT mesh.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psimap import PsimapError
from psimap.transforms import transform_points

# A camera: (K [3,3], c2w [4,4] OpenCV camera-to-world, width, height).
Camera = tuple


def load_mesh(path, what: str = ""):
    """A mesh file -> trimesh.Trimesh (scenes are flattened with their transforms); one PsimapError
    naming the file (and `what` it is) when it is missing, unreadable or holds no triangles."""
    import trimesh

    path = Path(path)
    of = f" ({what})" if what else ""
    if not path.is_file():
        raise PsimapError(f"missing mesh file: {path}{of}")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types on malformed files
        raise PsimapError(f"cannot read mesh {path}{of}: {type(e).__name__}: {e}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise PsimapError(f"mesh {path}{of} has no triangles")
    return mesh


def _mesh_arrays(mesh, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [V,3] f64 and faces [F,3] i64 of a trimesh-like object (or a (V, F) pair), checked."""
    if isinstance(mesh, tuple):
        vertices, faces = mesh
    else:
        vertices, faces = getattr(mesh, "vertices", None), getattr(mesh, "faces", None)
    if vertices is None or faces is None:
        raise PsimapError(f"{what}: not a triangle mesh")
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        raise PsimapError(f"{what}: mesh has no faces")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise PsimapError(f"{what}: face indices out of range (0..{len(vertices) - 1})")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise PsimapError(f"{what}: {int(bad.sum())} vertices are not finite (NaN/inf)")
    return vertices, faces


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangle areas [F] of vertices [V,3], faces [F,3]."""
    tri = vertices[faces]
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator,
                   face_mask: np.ndarray | None = None, return_faces: bool = False):
    """n points [n,3] uniformly distributed over the area of the faces [F,3] (optionally only faces
    where face_mask [F] is True); with return_faces also the face index [n] of each point."""
    areas = face_areas(vertices, faces)
    if face_mask is not None:
        areas = np.where(face_mask, areas, 0.0)
    total = areas.sum()
    if not total > 0:
        raise PsimapError("cannot sample a surface of zero area")
    cdf = np.cumsum(areas) / total
    idx = np.minimum(np.searchsorted(cdf, rng.random(n), side="right"), len(faces) - 1)
    # Uniform barycentric coordinates via the square-root fold.
    r1 = np.sqrt(rng.random(n))
    r2 = rng.random(n)
    tri = vertices[faces[idx]]
    pts = ((1 - r1)[:, None] * tri[:, 0] + (r1 * (1 - r2))[:, None] * tri[:, 1]
           + (r1 * r2)[:, None] * tri[:, 2])
    return (pts, idx) if return_faces else pts


def raycasting_scene(vertices: np.ndarray, faces: np.ndarray):
    """Open3D's BVH over triangles (vertices [V,3], faces [F,3]): ray casts and exact point-to-mesh
    distances (`compute_distance`)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)),
                        o3d.core.Tensor(faces.astype(np.uint32)))
    return scene


def camera_rays(K: np.ndarray, c2w: np.ndarray, width: int, height: int) -> np.ndarray:
    """Rays [H*W, 6] (origin, direction) through every pixel centre of an OpenCV camera.

    Directions are K^-1 [u, v, 1] rotated to world, i.e. *not* normalised: the ray parameter of a hit
    is then the z-depth of the hit in that camera.
    """
    K = np.asarray(K, dtype=np.float64)
    c2w = np.asarray(c2w, dtype=np.float64)
    if K.shape != (3, 3) or c2w.shape != (4, 4):
        raise PsimapError(f"camera: K must be 3x3 and c2w 4x4, got {K.shape} and {c2w.shape}")
    if not (np.isfinite(K).all() and np.isfinite(c2w).all()):
        raise PsimapError("camera: K or c2w is not finite")
    # direction = A [u, v, 1] with A = R K^-1: two broadcast outer products, no [3, H*W] solve.
    A = (c2w[:3, :3] @ np.linalg.inv(K)).astype(np.float32)
    u = (np.arange(width, dtype=np.float32) + 0.5)[None, :, None]
    v = (np.arange(height, dtype=np.float32) + 0.5)[:, None, None]
    rays = np.empty((height, width, 6), dtype=np.float32)
    rays[..., :3] = c2w[:3, 3].astype(np.float32)
    rays[..., 3:] = u * A[:, 0] + v * A[:, 1] + A[:, 2]
    return rays.reshape(-1, 6)


class CameraVisibility:
    """What the cameras see of a mesh: the first hit of every pixel ray of every camera.

    mesh: trimesh-like (or (vertices [V,3], faces [F,3])); cameras: iterable of
    (K [3,3], c2w [4,4] OpenCV camera-to-world, width, height). max_depth: ignore hits farther than
    this z-depth (a depth sensor's range).
    """

    def __init__(self, mesh, cameras, *, max_depth: float | None = None, progress: bool = False):
        self.vertices, self.faces = _mesh_arrays(mesh, "visibility mesh")
        self.cameras = []
        for K, c2w, w, h in cameras:
            camera_rays(K, c2w, 1, 1)  # validates K and c2w
            self.cameras.append((np.asarray(K, np.float64), np.asarray(c2w, np.float64), int(w), int(h)))
        self.max_depth = max_depth
        self.progress = progress
        self._scene = raycasting_scene(self.vertices, self.faces)

    def _cast(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hit face [N] int64 (-1 = none or beyond max_depth) and hit z-depth [N] of rays [N, 6]."""
        out = self._scene.cast_rays(rays)
        ids = out["primitive_ids"].numpy().astype(np.int64)
        ids[ids == 0xFFFFFFFF] = -1  # RaycastingScene.INVALID_ID
        depth = out["t_hit"].numpy()
        if self.max_depth is not None:
            ids[depth > self.max_depth] = -1
        return ids, depth

    def _views(self, desc: str):
        from tqdm import tqdm

        return tqdm(range(len(self.cameras)), desc=desc, unit="view",
                    disable=None if self.progress else True)

    def faces_seen(self) -> np.ndarray:
        """[F] bool: faces that are the first hit of at least one pixel ray."""
        seen = np.zeros(len(self.faces), dtype=bool)
        for i in self._views("visibility"):
            ids = self._cast(camera_rays(*self.cameras[i]))[0]
            seen[ids[ids >= 0]] = True
        return seen

    def points_seen(self, points: np.ndarray, point_faces: np.ndarray) -> np.ndarray:
        """[N] bool: which surface points [N,3] (lying on faces point_faces [N]) some camera sees.

        A face hit by a ray may be only partly seen (a wall behind a shelf), so each point is
        tested on its own: it projects into a camera's image, and the ray through that pixel's
        centre hits the point's own face, or a surface within two pixel footprints of the point's
        depth (a neighbouring face, not an occluder). Only the rays of those pixels are cast.
        """
        seen = np.zeros(len(points), dtype=bool)
        for i in self._views("visible points"):
            todo = np.flatnonzero(~seen)
            if todo.size == 0:
                break
            K, c2w, w, h = self.cameras[i]
            pc = transform_points(points[todo], np.linalg.inv(c2w))
            z = pc[:, 2]
            front = z > 1e-9
            zs = np.where(front, z, 1.0)
            pix = np.stack([pc[:, 0] / zs, pc[:, 1] / zs, np.ones_like(zs)]).T @ K.T
            u, v = np.floor(pix[:, 0]), np.floor(pix[:, 1])
            inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            if not inside.any():
                continue
            idx, z_in = todo[inside], z[inside]
            centres = np.stack([u[inside] + 0.5, v[inside] + 0.5, np.ones(idx.size)])    # [3, n]
            d_world = (c2w[:3, :3] @ np.linalg.solve(K, centres)).T
            rays = np.concatenate([np.broadcast_to(c2w[:3, 3], d_world.shape), d_world], axis=1)
            hit_face, hit_z = self._cast(rays.astype(np.float32))
            tol = 2.0 * z_in / min(K[0, 0], K[1, 1])
            ok = (hit_face == point_faces[idx]) | ((hit_face >= 0) & (np.abs(hit_z - z_in) <= tol))
            seen[idx[ok]] = True
        return seen


def visible_faces(mesh, cameras, *, max_depth: float | None = None, progress: bool = False) -> np.ndarray:
    """Which faces of `mesh` are the first hit of at least one pixel ray of at least one camera.

    mesh: trimesh-like (or (vertices [V,3], faces [F,3])); cameras: iterable of
    (K [3,3], c2w [4,4] OpenCV camera-to-world, width, height). max_depth: ignore hits farther than
    this z-depth. Returns [F] bool.
    """
    return CameraVisibility(mesh, cameras, max_depth=max_depth, progress=progress).faces_seen()


@dataclass
class SurfaceDistances:
    """Exact point-to-mesh distances of area-uniform samples, both directions (metres)."""

    pred_to_gt: np.ndarray      # [Np] distance of points sampled on the prediction to the GT mesh
    gt_to_pred: np.ndarray      # [Ng] distance of points sampled on seen GT surface to the prediction
    gt_seen_fraction: float = 1.0   # share of GT area the GT -> pred samples were drawn from


def _adaptive_distances(vertices, faces, other_scene, rng, face_mask, point_filter, thresholds,
                        max_samples, min_samples, rel_tol, abs_tol, frac_tol):
    """Sample on one mesh (faces where face_mask, points where point_filter(points, faces)) and
    measure exact distances to the other, doubling the sample count until the standard error of the
    mean distance is within max(rel_tol * mean, abs_tol) and that of every below-threshold fraction
    within frac_tol (or max_samples is reached). Returns (distances [n], accepted share of draws)."""
    import open3d as o3d

    chunks: list[np.ndarray] = []
    kept = drawn = 0
    target = min(min_samples, max_samples)
    while True:
        # Rejection keeps the samples area-uniform over the accepted surface; draw enough extra.
        rate = kept / drawn if kept else 1.0
        n = int(np.ceil((target - kept) / max(rate, 0.02)))
        pts, fid = sample_surface(vertices, faces, n, rng, face_mask, return_faces=True)
        drawn += n
        if point_filter is not None:
            pts = pts[point_filter(pts, fid)]
            if kept == 0 and len(pts) == 0 and drawn >= 50 * max(min_samples, 1000):
                raise PsimapError("no ground-truth surface is seen by any camera")
        pts = pts[: target - kept]
        if len(pts):
            chunks.append(other_scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32)))
                          .numpy().astype(np.float64))
            kept += len(pts)
        if kept < target:
            continue
        d = np.concatenate(chunks)
        mean_se = d.std() / np.sqrt(kept)
        frac_ok = all(np.sqrt(max(p * (1 - p), 1.0 / kept) / kept) <= frac_tol
                      for p in ((d < t).mean() for t in thresholds))
        if (mean_se <= max(rel_tol * d.mean(), abs_tol) and frac_ok) or target >= max_samples:
            return d, kept / drawn
        target = min(2 * target, max_samples)


def surface_distances(pred, gt, *, gt_visible: np.ndarray | None = None, gt_point_filter=None,
                      thresholds=(0.05,), max_samples: int = 200_000, min_samples: int = 10_000,
                      seed: int = 0, rel_tol: float = 0.01, abs_tol: float = 1e-4,
                      frac_tol: float = 0.0025) -> SurfaceDistances:
    """Distances of points sampled on `pred` to `gt` and on the seen part of `gt` to `pred`.

    pred, gt: trimesh-like meshes (or (vertices, faces)). The GT -> pred samples are drawn from GT
    faces where gt_visible [F_gt] bool (None = all) and kept where gt_point_filter(points [N,3],
    faces [N]) -> [N] bool (None = all), e.g. `CameraVisibility.points_seen`. Error budget: see the
    module doc.
    """
    pv, pf = _mesh_arrays(pred, "predicted mesh")
    gv, gf = _mesh_arrays(gt, "ground-truth mesh")
    if not face_areas(pv, pf).sum() > 0:
        raise PsimapError("predicted mesh: all faces have zero area")
    gt_areas = face_areas(gv, gf)
    if not gt_areas.sum() > 0:
        raise PsimapError("ground-truth mesh: all faces have zero area")
    if gt_visible is not None:
        gt_visible = np.asarray(gt_visible, dtype=bool)
        if gt_visible.shape != (len(gf),):
            raise PsimapError(f"gt_visible has shape {gt_visible.shape}, expected ({len(gf)},)")
        if not gt_areas[gt_visible].sum() > 0:
            raise PsimapError("no ground-truth surface is seen by any camera")
    if max_samples < 1:
        raise PsimapError(f"max_samples must be positive, got {max_samples}")
    rng = np.random.default_rng(seed)
    budget = dict(thresholds=tuple(thresholds), max_samples=max_samples, min_samples=min_samples,
                  rel_tol=rel_tol, abs_tol=abs_tol, frac_tol=frac_tol)
    d_pg, _ = _adaptive_distances(pv, pf, raycasting_scene(gv, gf), rng, None, None, **budget)
    d_gp, rate = _adaptive_distances(gv, gf, raycasting_scene(pv, pf), rng, gt_visible,
                                     gt_point_filter, **budget)
    seen_area = gt_areas[gt_visible].sum() if gt_visible is not None else gt_areas.sum()
    return SurfaceDistances(pred_to_gt=d_pg, gt_to_pred=d_gp,
                            gt_seen_fraction=float(seen_area * rate / gt_areas.sum()))


def summarize(dist: SurfaceDistances, threshold: float = 0.05) -> dict:
    """accuracy, completeness, chamfer_l1 (metres), precision, recall, f1 (fractions) at
    `threshold`, sample counts and the seen share of GT area."""
    acc = float(dist.pred_to_gt.mean())
    comp = float(dist.gt_to_pred.mean())
    precision = float((dist.pred_to_gt < threshold).mean())
    recall = float((dist.gt_to_pred < threshold).mean())
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {"accuracy": acc, "completeness": comp, "chamfer_l1": 0.5 * (acc + comp),
            "precision": precision, "recall": recall, "f1": float(f1), "threshold": float(threshold),
            "n_pred_points": int(dist.pred_to_gt.size), "n_gt_points": int(dist.gt_to_pred.size),
            "gt_seen_fraction": dist.gt_seen_fraction}


def geometry_metrics(pred, gt, *, threshold: float = 0.05, cameras=None,
                     gt_visible: np.ndarray | None = None, max_samples: int = 200_000,
                     seed: int = 0, max_depth: float | None = None, progress: bool = False,
                     return_distances: bool = False):
    """Geometry metrics of mesh `pred` against mesh `gt` (both trimesh-like, metres).

    GT culling: pass `cameras` (list of (K [3,3], c2w [4,4] OpenCV, width, height); max_depth =
    sensor range) to restrict the GT side of completeness / recall to surface seen by some camera:
    samples are drawn on faces hit by a pixel ray and kept if a camera sees the point itself (a hit
    face may be only partly visible); or pass a precomputed `gt_visible` [F_gt] bool face mask.
    With neither, the whole GT mesh is used. Accuracy / precision always use the whole GT mesh.
    Returns the dict of `summarize`, and the `SurfaceDistances` too when return_distances.
    """
    if not (threshold > 0 and np.isfinite(threshold)):
        raise PsimapError(f"threshold must be positive, got {threshold}")
    point_filter = None
    if gt_visible is None and cameras is not None:
        vis = CameraVisibility(gt, cameras, max_depth=max_depth, progress=progress)
        gt_visible = vis.faces_seen()
        point_filter = vis.points_seen
    dist = surface_distances(pred, gt, gt_visible=gt_visible, gt_point_filter=point_filter,
                             thresholds=(threshold,), max_samples=max_samples, seed=seed)
    out = summarize(dist, threshold)
    return (out, dist) if return_distances else out


def plot_geometry(dist: SurfaceDistances, path, threshold: float = 0.05) -> None:
    """PNG: precision / recall / F1 against the distance threshold, and both distance histograms."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from psimap.io_utils import save_figure

    top = max(4 * threshold, float(np.quantile(np.concatenate([dist.pred_to_gt, dist.gt_to_pred]), 0.99)))
    ts = np.linspace(0, top, 200)[1:]
    p = (dist.pred_to_gt[None, :] < ts[:, None]).mean(axis=1)
    r = (dist.gt_to_pred[None, :] < ts[:, None]).mean(axis=1)
    f = np.where(p + r > 0, 2 * p * r / np.maximum(p + r, 1e-12), 0.0)
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    a.plot(ts * 100, p, label="precision")
    a.plot(ts * 100, r, label="recall")
    a.plot(ts * 100, f, label="F1")
    a.axvline(threshold * 100, color="grey", ls="--", lw=1)
    a.set_xlabel("threshold [cm]")
    a.set_ylim(0, 1.02)
    a.legend()
    a.set_title("precision / recall / F1")
    bins = np.linspace(0, top, 60) * 100
    b.hist(np.minimum(dist.pred_to_gt, top) * 100, bins=bins, alpha=0.6, label="pred→GT (accuracy)")
    b.hist(np.minimum(dist.gt_to_pred, top) * 100, bins=bins, alpha=0.6, label="GT→pred (completeness)")
    b.set_xlabel("distance [cm]")
    b.set_yscale("log")
    b.legend()
    b.set_title("distance histograms")
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)
