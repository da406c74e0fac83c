"""Export formats: the scene value every writer reads, and the registry of writers.

A writer is one function with one signature:

    write_xxx(scene: ExportScene, out_dir: Path) -> Path     # the main file it wrote

It writes its files under `out_dir` (the export folder being built; `assets/` is shared by the
writers) and reads everything from `scene`: the objects (dynamic or static, never skipped), the
static environment, the floor height and the settle nudges. It never edits the objects, decides
nothing about them and moves nothing: the export pipeline (exporters.pipeline) has fixed their
roles and found the nudges before any writer runs, so every format shows the same scene.

Adding a format (URDF, SDF, ...) is one new module with its writer, and its line in FORMATS below.
The registry names writers by "module:function" strings and imports a writer only when it runs:
this module stays standard-library only, so `psimap --help` can read the format names from it
(psimap.options) without importing numpy, trimesh or pxr.
"""
from __future__ import annotations

import importlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

from psimap import PsimapError


@dataclass(frozen=True)
class ExportScene:
    """The scene as exported, one value for every writer.

    objects: SceneObject (exporters.objects) with Role.DYNAMIC or Role.STATIC, world frame, metres,
    in export order. background: what the static world looks like (floor, walls, unlabelled
    surfaces) as a visual SceneObject, or None. floor_z: height of the floor plane that carries
    contacts. nudges: {object name: [dx, dy, dz]} metres from the MuJoCo settle check (out of a
    penetration along its contact normal, down onto a support); writers place object `o` at its
    reconstructed pose moved by `offset(o)`. environment: the static world's colliders
    (exporters.environment.StaticEnvironment: supports, walls, ceilings, clutter; every writer that
    simulates emits all of them), or None.
    """

    objects: tuple
    background: object | None
    floor_z: float
    nudges: Mapping[str, Sequence[float]] = field(default_factory=dict)
    environment: object | None = None

    def offset(self, obj):
        """[3] translation (metres) of `obj` from its reconstructed place: its settle nudge."""
        import numpy as np

        return np.array(self.nudges.get(obj.name, (0.0, 0.0, 0.0)), dtype=np.float64).reshape(3)

    def nudged(self, nudges: Mapping[str, Sequence[float]]) -> ExportScene:
        """This scene with the settle check's nudges applied (one place for every writer)."""
        return replace(self, nudges=dict(nudges))


@dataclass(frozen=True)
class Format:
    """One export format: `writer` and `validator` are "module:function" strings."""

    name: str               # `psimap export --format NAME`
    title: str              # as messages name it
    writer: str             # (scene: ExportScene, out_dir: Path) -> Path of the main file
    validator: str = ""     # (main file: Path) -> {"errors": [str], ...}, kept in report.json as
                            # "<name>_validation"; an error fails the export
    summary: str = ""


# Writers run in this order. MJCF and USD both write the texture of an object to assets/<name>.png;
# the later one's file is the one kept.
FORMATS: dict[str, Format] = {f.name: f for f in (
    Format("mjcf", "MJCF", "psimap.exporters.mjcf:write_mjcf", summary="scene.xml + assets/ for MuJoCo"),
    Format("usd", "USD", "psimap.exporters.usd:write_usd", "psimap.exporters.usd:validate_usd",
           summary="scene.usda + assets/ (OpenUSD with UsdPhysics)"),
    Format("glb", "GLB", "psimap.exporters.glb:write_glb", summary="scene.glb: the visual meshes, for any viewer"),
)}


def format_names(format: str | list[str]) -> list[str]:
    """The registered formats `format` names ("all", one name or a list), in FORMATS order;
    PsimapError for an unknown one."""
    wanted = list(FORMATS) if format == "all" else ([format] if isinstance(format, str) else list(format))
    bad = [f for f in wanted if f not in FORMATS]
    if bad:
        raise PsimapError(f"unknown export format {bad[0]!r} (choose from {', '.join(FORMATS)}, all)")
    return [f for f in FORMATS if f in wanted]


def load(ref: str):
    """The function a "module:function" string names (imported now)."""
    module, func = ref.split(":")
    return getattr(importlib.import_module(module), func)
