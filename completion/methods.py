"""Completion methods: the one table of them, what a method's fit receives, and the typed context.

A method is a `Method`: a name, a tier, a fit function and whether the shape it fits is parametric.
`psimap.completion.complete` runs the tiers in increasing order; inside a tier every method whose
`when` holds proposes a candidate, each candidate goes through the same constraints and fit test,
and the lowest residual (weighted by `complexity`) among the accepted ones wins; the first tier
with a winner ends the search (module doc of psimap.completion).

Adding a method is one module that defines a fit and a `Method`:

    from psimap.completion.methods import Method

    def fit_blob(obs):                      # obs: Observation
        ...                                 # a closed trimesh, (mesh or None, {stats}), or None;
        return mesh                         # raise RuntimeError to decline with the reason

    METHOD = Method("blob", tier=15, fit=fit_blob, parametric=False)

registered in the package's metadata under the entry-point group `psimap.completion`, the name
being the method's:

    [project.entry-points."psimap.completion"]
    blob = "my_package.blob:METHOD"

Installed, it takes part in `auto` in its tier and `psimap export --completion blob` runs it alone.
Built-in methods live in the table below (BUILTIN); their fits are the adapters after it.

Standard library only at import: `psimap --help` reads the method names from here
(psimap.options); the fits import numpy and the rest when they run.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields

from psimap import PsimapError

ENTRY_POINT_GROUP = "psimap.completion"
COVERAGE_THRESHOLD = 0.95     # directional coverage at which an object counts as fully observed
CLOSING_COVERAGE = 0.8        # Poisson closing only for mostly seen objects: it bulges into big holes


@dataclass(frozen=True, eq=False)
class CompletionContext:
    """What is known around one object; every field is optional (pass what is known).

    points: [P, 3] observed surface points of the object (world, metres). Without them the partial
      mesh's surface is sampled; with cameras + depths only the samples some depth map confirms
      count as observed (surface a repair added is not), without cameras all of it does.
    voxel_size: TSDF voxel (metres): the tolerance for "observed points stay on the result", the
      free-space margin and the voxel pitch of carving. Default: 2 x the median point spacing.
    support_planes: (normal [3], offset) planes {x : normal·x = offset} (floor, table top, walls);
      oriented towards the object here. An up-facing one under the object is its support.
    background: trimesh of the static scene: planes are read off it by rays from the object, and,
      when it is closed, it is subtracted like a neighbour.
    neighbours: trimesh of the other objects (open scans are turned into closed surface bands);
      the result never intersects them.
    cameras: (K [3,3], c2w [4,4] OpenCV camera-to-world, width, height) and depths: [H, W] depth
      maps in metres (0 = no return), one per camera: observed free space, which stays free.
    images: [H, W, 3] float RGB and label: the class name (both only handed to the plugin).
    plugin: callable (points [P,3], images, label) -> trimesh: a generative model's proposal, tried
      first, aligned to the points, then post-processed like every other method.
    coverage_threshold: objects whose directional coverage reaches it are returned unchanged in
      `auto` (an object on a table seen from all sides still misses its underside, ~0.9, and is
      closed down to the table).
    method: "auto" or the name of one registered method (`complete` says what forcing one means).
    """

    points: object = None
    voxel_size: float | None = None
    support_planes: Sequence = ()
    background: object = None
    neighbours: Sequence = ()
    cameras: Sequence = ()
    depths: Sequence = ()
    images: Sequence | None = None
    label: str | None = None
    plugin: Callable | None = None
    coverage_threshold: float = COVERAGE_THRESHOLD
    method: str = "auto"

    @classmethod
    def of(cls, value: CompletionContext | Mapping | None) -> CompletionContext:
        """`value` as a context: a CompletionContext as is, a mapping of its field names (an unknown
        key is a PsimapError: nothing is silently ignored), None as the empty context."""
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(value) - known)
        if unknown:
            raise PsimapError(f"completion context: unknown key {unknown[0]!r} (known: {', '.join(sorted(known))})")
        return cls(**value)


@dataclass(frozen=True, eq=False)
class Observation:
    """What a method's fit receives about one object (built by `complete`)."""

    points: object                 # [P, 3] observed surface points, world metres
    normals: object                # [P, 3] their outward normals
    tolerance: float            # metres (the voxel): how close observed points must stay
    spacing: float              # median spacing of the points (metres; 0 when unknown)
    coverage: float             # directional coverage of the points, 0..1
    support: object                # the up-facing plane under the object, (normal [3], offset), or None
    blocking: list              # planes (normal [3], offset) the result may not cross
    free: Callable | None       # free(q [Q, 3]) -> bool [Q]: seen empty by some camera; None: no cameras
    context: CompletionContext  # everything else (label, images, plugin, ...)


@dataclass(frozen=True)
class Method:
    """One completion method.

    tier: tiers run in increasing order; the first one with an accepted candidate ends the search.
    fit: (obs: Observation) -> closed trimesh, or (trimesh or None, stats dict), or None (no
      closed fit; stats["reason"] says why). Raising RuntimeError declines with its message (the
      next candidate runs); any other exception is a bug and propagates.
    parametric: a fitted closed-form shape; besides the fit test (>= 90 % of the observed points
      within the voxel) its RMS must stay within half a voxel.
    whole: it proposes the whole object (not a closure of the observation): observed parts its
      shape leaves outside (a mug's handle) are added back as convex pieces. Parametric implies it.
    complexity: weight on the residual inside a tier (a simpler shape wins unless clearly worse).
    when: `auto` tries the method only when this holds for the observation; a forced method runs.
    fallback: the last resort: its closed result is used, failing the fit test or not, when no
      method is accepted.
    selectable: offered by `psimap export --completion` (the plugin hook needs a Python callable).
    """

    name: str
    tier: int
    fit: Callable[[Observation], object]
    parametric: bool = False
    whole: bool = False
    complexity: float = 1.5
    when: Callable[[Observation], bool] | None = None
    fallback: bool = False
    selectable: bool = True

    @property
    def adds_outliers(self) -> bool:
        return self.whole or self.parametric


# ---------------------------------------------------------------- built-in fits (adapters)

def _plugin(obs: Observation):
    from .plugin import align_to_points, run_plugin

    if obs.context.plugin is None:
        raise RuntimeError("no plugin callable in the completion context")
    proposal = run_plugin(obs.context.plugin, obs.points, obs.context.images, obs.context.label)
    return align_to_points(proposal, obs.points, obs.tolerance, obs.spacing or obs.tolerance)


def _sphere(obs: Observation):
    from .primitives import fit_sphere

    return fit_sphere(obs.points, obs.tolerance)


def _cylinder(obs: Observation):
    from .primitives import fit_cylinder

    return fit_cylinder(obs.points, obs.tolerance, obs.support)


def _box(obs: Observation):
    from .primitives import fit_box

    return fit_box(obs.points, obs.tolerance, obs.support, obs.blocking)


def _revolution(obs: Observation):
    from .symmetry import fit_revolution

    return fit_revolution(obs.points, obs.tolerance, obs.support)


def _closing(obs: Observation):
    from .closing import poisson_closing

    return poisson_closing(obs.points, obs.normals, obs.tolerance)


def _mirror(obs: Observation):
    from .support import support_closing
    from .symmetry import mirror_planes, mirrored_points

    planes, stats = mirror_planes(obs.points, obs.tolerance, obs.support, obs.free)
    if not planes:
        return None, {**stats, "reason": "no mirror plane with agreeing, uncontradicted halves"}
    return support_closing(mirrored_points(obs.points, planes), 0.5 * obs.tolerance, obs.support, obs.free,
                           keep=obs.points), stats


def _support(obs: Observation):
    from .support import support_closing

    return support_closing(obs.points, 0.5 * obs.tolerance, obs.support, obs.free)


def _has_plugin(obs: Observation) -> bool:
    return obs.context.plugin is not None


def _mostly_seen(obs: Observation) -> bool:
    return obs.coverage >= CLOSING_COVERAGE


# Tiers of increasing generality: a generative model's proposal -> primitives (sphere / cylinder /
# box, `primitives.py`) and rotational symmetry (`symmetry.py`) -> watertight Poisson closing of
# the shell (`closing.py`, only when most directions were seen) -> reflective symmetry: the
# observation mirrored about up to two credible planes, then closed like the fallback
# (`symmetry.py`) -> support-aware closing (`support.py`, always available as the fallback).
# Tiers are spaced by 10 so a registered method can go between two.
BUILTIN: tuple[Method, ...] = (
    Method("plugin", 0, _plugin, whole=True, complexity=0.8, when=_has_plugin, selectable=False),
    Method("sphere", 10, _sphere, parametric=True, complexity=1.0),
    Method("cylinder", 10, _cylinder, parametric=True, complexity=1.0),
    Method("box", 10, _box, parametric=True, complexity=1.0),
    Method("revolution", 10, _revolution, parametric=True, complexity=1.25),
    Method("closing", 20, _closing, when=_mostly_seen),
    Method("mirror", 30, _mirror),
    Method("support", 40, _support, fallback=True),
)


# ---------------------------------------------------------------- the registry

def _entry_points():
    import importlib.metadata      # ~50 ms to import: only when the installed methods are asked for

    return importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)


def method_names(selectable: bool = False, installed: bool = True) -> list[str]:
    """Names of the built-in methods and, with `installed`, of those packages add (by their
    entry-point name, without importing them); selectable: only those `psimap export --completion`
    offers."""
    names = [m.name for m in BUILTIN if m.selectable or not selectable]
    return names + ([ep.name for ep in _entry_points()] if installed else [])


def methods() -> list[Method]:
    """Every method, built-in then installed (entry-point group `psimap.completion`, loaded now),
    in tier order (table order inside a tier). PsimapError for an entry point that does not load
    or is not a Method of its own name, and for a name taken twice."""
    table = list(BUILTIN)
    for ep in _entry_points():
        try:
            m = ep.load()
        except Exception as e:
            raise PsimapError(f"completion method {ep.name!r} ({ep.value}) failed to load: "
                              f"{type(e).__name__}: {e}") from None
        if not isinstance(m, Method) or m.name != ep.name:
            raise PsimapError(f"entry point {ep.name!r} ({ep.value}) of {ENTRY_POINT_GROUP} is not a "
                              f"psimap.completion.methods.Method named {ep.name!r}")
        if any(t.name == m.name for t in table):
            raise PsimapError(f"completion method {m.name!r} ({ep.value}) is registered twice")
        table.append(m)
    return sorted(table, key=lambda m: m.tier)


class Choices:
    """`psimap export --completion` choices (auto, none, every selectable method), listed when
    argparse checks a value: reading the installed entry points costs ~0.1 s that `psimap --help`
    need not pay (give argparse a metavar, or it lists the choices while building the parser)."""

    def __iter__(self):
        return iter(["auto", "none", *method_names(selectable=True)])

    def __contains__(self, name) -> bool:
        return name in list(self)
