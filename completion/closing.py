"""Watertight closing of the observed shell: screened Poisson reconstruction (Open3D) on oriented
observed points. Suited to objects seen from most sides with holes to bridge; for a half-seen
object the Poisson surface bulges into the unseen half, which the chooser then rejects on the
free-space and fit checks. Octree depth comes from the tolerance (finest cell ~ tolerance).
"""
from __future__ import annotations

import numpy as np


def oriented_normals(points: np.ndarray, partial, spacing: float) -> np.ndarray:
    """Normals [P, 3] for points [P, 3]: from the partial mesh's nearest face when it has faces,
    else PCA normals flipped away from the points' centre."""
    if partial is not None and len(getattr(partial, "faces", [])) > 0:
        import trimesh

        _, _, fid = trimesh.proximity.closest_point(partial, points)
        n = partial.face_normals[fid]
        if partial.volume < 0:
            n = -n
        return n
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * spacing, max_nn=30))
    n = np.asarray(pcd.normals)
    out = points - points.mean(0)
    return np.where(((n * out).sum(1) < 0)[:, None], -n, n)


def poisson_closing(points: np.ndarray, normals: np.ndarray, tolerance: float):
    """Closed mesh from oriented points, or None when Poisson gives no closed surface."""
    import open3d as o3d

    from .meshops import as_trimesh, is_solid

    extent = float(np.ptp(points, axis=0).max())
    depth = int(np.clip(np.ceil(np.log2(max(extent, 1e-6) / max(tolerance, 1e-6))) + 1, 4, 9))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.normals = o3d.utility.Vector3dVector(normals)
    mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth, scale=1.2)
    tm = as_trimesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    if len(tm.faces) == 0:
        return None
    parts = tm.split(only_watertight=True)
    if len(parts) == 0:
        return None
    tm = max(parts, key=lambda m: abs(m.volume))
    if tm.volume < 0:
        tm.invert()
    return tm if is_solid(tm) else None
