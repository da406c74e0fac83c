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

    def objects(self, up: str = "auto", **kw):
        """Per-object meshes, metres, in the gravity-aligned world frame (Z-up: the capture turned by
        the rotation `up` gives, psimap.exporters.pipeline.gravity_aligned; "+z" keeps the capture's
        frame as it is). psimap.exporters.objects.extract_objects does the work."""
        from psimap.exporters.objects import extract_objects
        from psimap.exporters.pipeline import gravity_aligned

        scene, _ = gravity_aligned(self, up)
        return extract_objects(scene, **kw)
