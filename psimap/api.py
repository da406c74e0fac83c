"""The Python API the README documents: `psimap.load(path)` returns a `Scene` whose `objects()`
runs the export stage.

Like `psimap.cli`, this is an entry point: it may import any stage and no stage imports it. The
stages pass `psimap.scene.Scene` around (training builds one, export reads one); this subclass only
adds the views of it that belong to later stages, so psimap.scene never imports the exporters.
"""
from __future__ import annotations

from psimap import scene


class Scene(scene.Scene):
    """A trained scene (`psimap.scene.Scene`) with its per-object assets one call away."""

    def objects(self, up: str = "auto", *, static_classes=None, min_coverage: float | None = None, **kw):
        """Per-object meshes, metres, in the gravity-aligned world frame (Z-up: the capture turned by
        the rotation `up` gives, psimap.exporters.pipeline.gravity_aligned; "+z" keeps the capture's
        frame as it is). psimap.exporters.objects.extract_objects does the work.

        Each SceneObject carries its mesh, collider (`collision`), mass properties (`physics`) and
        class (`label`), and the role the export gives it by the same rules
        (exporters.pipeline.assign_roles): static for a static class (static_classes: None = the
        default furniture list, exporters.physics.STATIC_CLASSES) or an object seen less than
        `min_coverage` (None = the export's MIN_COVERAGE), dynamic otherwise. Only the export's
        settle check can still pin an object static (its report.json says which)."""
        from psimap.exporters.objects import extract_objects
        from psimap.exporters.pipeline import MIN_COVERAGE, assign_roles, gravity_aligned
        from psimap.exporters.roles import Reason, Role

        scene, _ = gravity_aligned(self, up)
        objs = extract_objects(scene, static_classes=static_classes, **kw)
        assign_roles([o for o in objs if o.role is not Role.SKIPPED and o.reason is not Reason.ENVIRONMENT],
                     static_classes, MIN_COVERAGE if min_coverage is None else min_coverage)
        return objs


def predicted_objects(path, up: str = "auto", *, completion: str = "auto", progress: bool = False) -> list:
    """The objects `psimap export` makes of checkpoint `path`, for the object metrics
    (psimap.metrics.objects.PredictedObject: name, class, mesh), in the capture's frame (that of the
    checkpoint and of its DATA): extracted Z-up as the export does (`up`), then turned back.

    Skipped objects come without a mesh, with the reason. Roles are left "n/a": the export decides
    them (static furniture, too little evidence, the settle check's pins); the mass is the export's.
    """
    import numpy as np

    from psimap.exporters.objects import extract_scene
    from psimap.exporters.pipeline import gravity_aligned
    from psimap.exporters.roles import Reason, Role
    from psimap.metrics.objects import PredictedObject

    turned, est = gravity_aligned(scene.load_scene(path), up)
    objs, _, _ = extract_scene(turned, completion=completion, progress=progress)
    out = []
    for o in objs:
        if o.reason is Reason.ENVIRONMENT:
            continue
        if o.role is Role.SKIPPED:
            out.append(PredictedObject(o.name, o.label, None, role="skipped", reason=o.why))
            continue
        mesh = o.mesh.copy()
        mesh.vertices = np.asarray(mesh.vertices, np.float64) @ np.asarray(est.rotation, np.float64)  # R^T v
        out.append(PredictedObject(o.name, o.label, mesh, mass_kg=o.mass if o.physics is not None else None,
                                   observed_coverage=o.measured.coverage if o.measured.coverage >= 0 else None))
    return out
