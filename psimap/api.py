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

    def objects(self, **kw):
        """Per-object meshes, metres, world frame (psimap.exporters.objects.extract_objects)."""
        from psimap.exporters.objects import extract_objects

        return extract_objects(self, **kw)
