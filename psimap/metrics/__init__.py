"""psimap.metrics: geometry (accuracy / completeness / Chamfer / F1 with camera culling), panoptic
(scene-level PQ / SQ / RQ, mIoU, mAcc, mCov, mW-Cov) and object (psimap.metrics.objects: GT things
found, F-score at 1 / 2.5 cm, role, mass) metrics; `psimap.metrics.evaluate.evaluate` (and `psimap
eval`) evaluates a mesh, checkpoint, export folder or label folder against a scene folder's gt/.

Only numpy is imported here; Open3D / trimesh load when a geometry metric runs.
"""
from psimap.metrics.geometry import geometry_metrics, summarize, surface_distances, visible_faces
from psimap.metrics.panoptic import PanopticAccumulator, panoptic_metrics

__all__ = ["geometry_metrics", "surface_distances", "summarize", "visible_faces",
           "PanopticAccumulator", "panoptic_metrics"]
