"""`report.json` of an export folder: per object what was made and measured, plus the sim check.

Deterministic (sorted keys, rounded floats, no timestamps or timings) so that exporting twice gives
identical files; timings go to `timings.json`.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from psimap.exporters.roles import Reason, Role


def _r(x, digits: int = 6):
    if isinstance(x, dict):
        return {str(k): _r(v, digits) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_r(v, digits) for v in x]
    if isinstance(x, np.ndarray):
        return _r(x.tolist(), digits)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        v = float(x)
        if not np.isfinite(v):
            return None
        return float(f"{v:.{digits}g}")
    return x


def object_entry(obj, files: dict) -> dict:
    """Report entry of one SceneObject; files: {"mesh": ..., "collision": [...]} relative paths."""
    m = obj.measured
    e = {
        "name": obj.name, "instance_id": int(obj.instance_id), "class": obj.label,
        "semantic_id": int(obj.semantic_id), "static": obj.role is Role.STATIC,
        # the environment is static without a reason to give
        "static_reason": obj.why if obj.role is Role.STATIC and obj.reason is not Reason.ENVIRONMENT else None,
        "surfels": int(obj.surfel_count), "skipped": obj.why if obj.role is Role.SKIPPED else None,
        "observed_coverage": m.coverage,
        "faces_before": int(m.faces_before), "faces_after": int(m.faces_after), "face_budget": int(m.face_budget),
        "decimation_error_m": m.decimation_error, "decimation_mean_error_m": m.decimation_mean_error,
        "decimation_budget_m": m.decimation_budget,
        "watertight": bool(m.watertight), "completed": bool(m.completed),
        "completion_method": m.completion_method, "repair": list(m.repair_steps),
        "texture": obj.texture_source, "texture_coverage": obj.texture_coverage,
    }
    if obj.mesh is not None and len(getattr(obj.mesh, "vertices", [])):
        e["bounds"] = np.asarray(obj.mesh.bounds, np.float64)
    if files:
        e["files"] = files
    if obj.collision is not None:
        c = obj.collision
        e["collision"] = {"kind": c.kind, "hull_count": c.hull_count, "error_m": c.error,
                          "tolerance_m": c.tolerance,
                          "max_hull_vertices": max((len(p.vertices) for p in c.parts), default=0)
                          if not c.is_primitive else 0}
        if c.is_primitive:
            e["collision"]["size"] = c.size
    if obj.physics is not None:
        p = obj.physics
        e["physics"] = {"mass_kg": p.mass, "volume_m3": p.volume, "density_kg_m3": p.density,
                        "density_key": p.density_key, "friction": p.friction, "com": p.com,
                        "principal_inertia": p.principal_inertia, "mass_model": p.model,
                        "mass_range_kg": list(p.mass_range)}
        if p.model == "shell":
            e["physics"]["areal_density_kg_m2"] = p.areal_density
    return e


def write_report(path: str | Path, report: dict) -> None:
    Path(path).write_text(json.dumps(_r(report), indent=2, sort_keys=True) + "\n")
