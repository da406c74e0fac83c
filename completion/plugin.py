"""Hook for a generative completion model.

Any callable `plugin(points [P,3] world metres, images list of [H,W,3] float, label str) ->
trimesh.Trimesh` may propose the complete object. Its output is aligned to the observed points
(similarity ICP: rotation, translation and uniform scale, from the observed points onto the
proposal's surface, started from matching bounding-box centres when the proposal is off) and then
goes through the same free-space / collision post-processing and fit checks as every built-in
method.
"""
from __future__ import annotations

import numpy as np

from psimap import PsimapError


def run_plugin(plugin, points: np.ndarray, images, label: str | None):
    """Call the plugin and validate its output. Returns a trimesh."""
    import trimesh

    try:
        mesh = plugin(points, images, label)
    except PsimapError:
        raise
    except Exception as e:      # a model failing must not kill the export: report it
        raise RuntimeError(f"completion plugin failed: {type(e).__name__}: {e}") from e
    if isinstance(mesh, trimesh.Scene):
        mesh = mesh.dump(concatenate=True)
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise RuntimeError("completion plugin returned no mesh")
    if not np.isfinite(mesh.vertices).all():
        raise RuntimeError("completion plugin returned non-finite vertices")
    return mesh


def align_to_points(mesh, points: np.ndarray, tolerance: float, spacing: float):
    """Similarity transform of `mesh` so the observed points [P, 3] lie on it. Returns a new mesh."""
    import open3d as o3d

    from .meshops import sample_surface

    mesh = mesh.copy()
    p_lo, p_hi = points.min(0), points.max(0)
    m_lo, m_hi = mesh.bounds
    ratio = float(np.ptp(points, axis=0).max() / max(np.ptp(mesh.vertices, axis=0).max(), 1e-12))
    if not 0.5 <= ratio <= 2.0 or (p_hi < m_lo).any() or (p_lo > m_hi).any():
        # Proposal in its own frame / units: start from matched box centres and sizes.
        mesh.apply_translation(-0.5 * (m_lo + m_hi))
        mesh.apply_scale(ratio)
        mesh.apply_translation(0.5 * (p_lo + p_hi))
    target = sample_surface(mesh, spacing, max_points=60_000)
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    init = np.eye(4)
    extent = float(np.ptp(points, axis=0).max())
    est = o3d.pipelines.registration.TransformationEstimationPointToPoint(with_scaling=True)
    crit = o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=60)
    reg = o3d.pipelines.registration.registration_icp(src, tgt, max(0.25 * extent, 4 * tolerance),
                                                      init, est, crit)
    reg = o3d.pipelines.registration.registration_icp(src, tgt, 2 * tolerance, reg.transformation,
                                                      est, crit)
    # reg maps points -> mesh frame; the mesh goes the other way.
    mesh.apply_transform(np.linalg.inv(reg.transformation))
    return mesh
