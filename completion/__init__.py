"""psimap.completion: collision-aware completion of partially observed objects.

Installed as `psimap.completion`; the export pipeline calls `complete(partial, context)` once per
object (step 3) unless `--completion none`. It works offline on a CPU, with no model weights, and
says what it did: `CompletionResult.method` names the method and `reason` says why.

`context` keys read (all optional; pass what is known):
- "label": str, class name (only handed to the plugin).
- "points": [P, 3] observed surface points of the object (world, metres). Without them the partial
  mesh's surface is sampled; with cameras + depths only the samples some depth map confirms count
  as observed (surface a repair added is not), without cameras all of it does.
- "voxel_size": float, TSDF voxel (metres): the tolerance for "observed points stay on the result",
  the free-space margin and the voxel pitch of carving. Default: 2 x the median point spacing.
- "support_planes": list of (normal [3], offset) planes {x : normal·x = offset} (floor, table top,
  walls); oriented towards the object here. An up-facing one under the object is its support.
- "background": trimesh of the static scene: planes are read off it by rays from the object, and,
  when it is closed, it is subtracted like a neighbour.
- "neighbours": list of trimesh of the other objects (open scans are turned into closed surface
  bands); the result never intersects them.
- "cameras": list of (K [3,3], c2w [4,4] OpenCV camera-to-world, width, height) and "depths": list
  of [H, W] depth maps in metres (0 = no return): observed free space, which stays free.
- "images": list of [H, W, 3] float RGB (only handed to the plugin).
- "plugin": callable (points [P,3], images, label) -> trimesh: a generative model's proposal, tried
  first, aligned to the points, then post-processed like every other method.
- "coverage_threshold": float, default 0.95: objects whose directional coverage reaches it are
  returned unchanged (an object on a table seen from all sides still misses its underside, ~0.9,
  and is closed down to the table).
- "method": "auto" (default) or one of "plugin", "sphere", "cylinder", "box", "revolution",
  "closing", "mirror", "support" to force a method.

Methods (one module each), tried in tiers of increasing generality; the first tier with a candidate
whose fit passes (>= 90 % of observed points within the tolerance of its surface, after free-space
carving and collision removal; parametric shapes also need an RMS <= half a voxel) wins; inside a tier the lowest residual wins, weighted by
complexity (primitives 1.0, revolution 1.25):
plugin -> primitives (sphere / cylinder / box, `primitives.py`) and rotational symmetry
(`symmetry.py`) -> watertight Poisson closing of the shell (`closing.py`, only when most
directions were seen) -> reflective symmetry: the observation mirrored about up to two credible
planes, then closed like the fallback (`symmetry.py`) -> support-aware closing (`support.py`,
always available as the fallback).
Parts of the observation a fitted shape leaves outside (a mug's handle) are added back as convex
pieces.
Constraints (`constraints.py`) and free space (`freespace.py`) apply to every result.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from psimap import PsimapError

MIN_POINTS = 50               # fewer observed points do not constrain any shape
COVERAGE_THRESHOLD = 0.95     # directional coverage at which an object counts as fully observed
CLOSING_COVERAGE = 0.8        # Poisson closing only for mostly seen objects: it bulges into big holes
ACCEPT_INLIERS = 0.9          # share of observed points within tolerance of a candidate surface
PARAMETRIC_RMS = 0.5          # a parametric shape must also fit tightly: RMS <= this x voxel
_PARAMETRIC = ("sphere", "cylinder", "box", "revolution")
# A closed result with more handles than a mug's is a sponge, not an object: Poisson closing of a
# fused shell whose two skins disagree in orientation came out with genus 17 on a 20 cm box (43 %
# of its volume missing, its convex hull 7 cm off), and every collider after it chased the holes.
# Handles up to two voxels wide are sealed (Poisson leaves sub-voxel ones on a plain ball); a
# candidate with wider ones is rejected.
MAX_GENUS = 1
FREE_CARVE = 0.01             # carve a candidate when more than this share of it is known-free
# Residual weights inside a tier: a simpler shape wins unless clearly worse (a bottle fits a
# cylinder, but a surface of revolution better).
_COMPLEXITY = {"plugin": 0.8, "sphere": 1.0, "cylinder": 1.0, "box": 1.0, "revolution": 1.25,
               "closing": 1.5, "mirror": 1.5, "support": 1.5}
METHODS = ("plugin", "sphere", "cylinder", "box", "revolution", "closing", "mirror", "support")


@dataclass
class CompletionResult:
    mesh: Any            # trimesh.Trimesh, metres, world frame
    completed: bool      # True only when geometry was actually added
    method: str          # name of the method that ran ("none" when left unchanged)
    reason: str          # why it was (not) completed, one line
    coverage: float = math.nan            # directional coverage of the observed points (0..1)
    surface_coverage: float = math.nan    # share of the result's surface that was observed
    fit_residual: float = math.nan        # RMS distance of observed points to the result (m)
    observed_on_surface: float = math.nan  # share of observed points within tolerance of result
    collision_volume: float = 0.0         # m³ of the result inside neighbours / background
    free_space_fraction: float = math.nan  # share of the result's volume seen empty by a camera
    tolerance: float = math.nan           # metres (voxel size)
    seconds: float = 0.0
    candidates: dict = field(default_factory=dict)   # method -> its fit numbers or why not


def _observed_points(partial, context) -> np.ndarray:
    pts = context.get("points")
    if pts is not None:
        pts = np.asarray(pts, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise PsimapError(f"completion context: points must be [P, 3], got shape {pts.shape}")
    elif partial is not None and len(partial.vertices):
        from .coverage import point_spacing
        from .meshops import sample_surface

        v = np.asarray(partial.vertices, dtype=np.float64)
        v = v[np.isfinite(v).all(1)]
        if len(partial.faces) and len(v) >= 3 and partial.area > 0:
            # Vertex spacing says nothing for a low-poly mesh: sample ~10k points over its area,
            # or at the vertex spacing when that is finer (a TSDF mesh's own resolution).
            spacing = min(point_spacing(v) or np.inf, float(np.sqrt(partial.area / 5000.0)))
            pts = sample_surface(partial, spacing, max_points=30_000)
        else:
            pts = v
    else:
        pts = np.zeros((0, 3))
    return pts[np.isfinite(pts).all(1)]


def _unchanged(partial, method, reason, **kw) -> CompletionResult:
    return CompletionResult(mesh=partial, completed=False, method=method, reason=reason, **kw)


def complete(partial, context: dict | None = None) -> CompletionResult:
    """Complete a partially observed object.

    partial: trimesh.Trimesh of the observed object (metres, world frame; may be open) or None when
    context["points"] is given. context: see the module doc. Returns a CompletionResult whose mesh
    is the completed closed mesh, or `partial` unchanged (completed=False) with the reason.
    Raises PsimapError for malformed input (wrong shapes, non-finite cameras).
    """
    t0 = time.perf_counter()
    context = dict(context or {})
    if partial is not None and not hasattr(partial, "vertices"):
        raise PsimapError(f"completion: partial must be a trimesh.Trimesh or None, got {type(partial).__name__}")
    forced = context.get("method", "auto") or "auto"
    if forced != "auto" and forced not in METHODS:
        raise PsimapError(f"completion: unknown method {forced!r} (auto, {', '.join(METHODS)})")
    points = _observed_points(partial, context)
    if len(points) == 0:
        return _unchanged(partial, "skipped", "empty partial: no observed points",
                          seconds=time.perf_counter() - t0)
    from .coverage import directional_coverage, point_spacing, surface_coverage

    spacing = point_spacing(points)
    voxel = context.get("voxel_size")
    tol = float(voxel) if voxel is not None else 2.0 * spacing
    if not (np.isfinite(tol) and tol > 0):
        if len(points) < MIN_POINTS:
            return _unchanged(partial, "skipped", f"tiny partial: {len(points)} observed points (< {MIN_POINTS})",
                              seconds=time.perf_counter() - t0)
        raise PsimapError(f"completion context: voxel_size must be positive, got {voxel}")
    extent = float(np.ptp(points, axis=0).max())
    if len(points) < MIN_POINTS or extent < 3 * tol:
        what = (f"{len(points)} observed points (< {MIN_POINTS})" if len(points) < MIN_POINTS
                else f"extent {extent:.4f} m < 3 voxels ({3 * tol:.4f} m)")
        return _unchanged(partial, "skipped", f"tiny partial: {what}", tolerance=tol,
                          seconds=time.perf_counter() - t0)
    from .constraints import attach_outliers, blocking_planes, carve_free, check, subtract_obstacles
    from .freespace import cameras_seeing, check_cameras, known_free, seen_on_surface
    from .meshops import genus, is_solid, seal_handles, solidify, to_manifold
    from .support import normalise_planes, planes_from_background, support_below

    # Context is validated before any early return so malformed input always fails loudly.
    centre = 0.5 * (points.min(0) + points.max(0))
    background = context.get("background")
    planes = normalise_planes(context.get("support_planes"), centre)
    cams = check_cameras(context.get("cameras"), context.get("depths"))
    note = ""
    if context.get("points") is None and cams:
        # A mesh-only observation may carry surface no camera saw (a repair capped its holes):
        # keep the samples some depth map confirms, so coverage counts only what was seen.
        seen = seen_on_surface(points, cams, 2 * tol)
        if seen.sum() >= MIN_POINTS:
            if not seen.all():
                note = f"; {1 - seen.mean():.0%} of the mesh surface unseen by any camera ignored"
            points = points[seen]
        else:
            note = "; no camera confirms the mesh surface: all of it taken as observed"
    from .closing import oriented_normals

    normals = oriented_normals(points, partial, spacing or tol,
                               viewpoints=[c[1][:3, 3] for c in cams] if cams else None)
    coverage = directional_coverage(points, normals)
    threshold = float(context.get("coverage_threshold", COVERAGE_THRESHOLD))
    if coverage >= threshold and forced == "auto":
        return _unchanged(partial, "none", f"fully observed: coverage {coverage:.2f} >= {threshold:.2f}{note}",
                          coverage=coverage, tolerance=tol, seconds=time.perf_counter() - t0)

    planes += planes_from_background(background, points, reach=2.0 * extent, radius=max(4 * tol, 0.02))
    support = support_below(planes, points, reach=1.5 * extent + 3 * tol, tolerance=3 * tol)
    blocking = blocking_planes(planes, points, tol)
    # Only what is near the object matters: cameras that see its surroundings, neighbours whose
    # bounds come within one object extent (the export pipeline passes all of them).
    lo, hi = points.min(0) - extent, points.max(0) + extent
    cams = cameras_seeing(cams, lo, hi)
    free_fn = (lambda q: known_free(q, cams, 2 * tol)) if cams else None
    near = [m for m in (context.get("neighbours") or []) if m is not None and len(m.faces)
            and not ((m.bounds[1] < lo).any() or (m.bounds[0] > hi).any())]
    obstacles = [solidify(m, 0.5 * tol) for m in near]
    if background is not None and is_solid(background):
        obstacles.append(background)
    obstacles = [o for o in obstacles if o is not None]
    obstacle_manifolds = [to_manifold(o) for o in obstacles]    # converted once, used per candidate

    from . import closing, primitives, symmetry
    from .support import support_closing

    def tiers():
        plugin = context.get("plugin")
        if plugin is not None:
            from .plugin import align_to_points, run_plugin

            def _plugin():
                return align_to_points(run_plugin(plugin, points, context.get("images"), context.get("label")),
                                       points, tol, spacing or tol)
            yield [("plugin", _plugin)]
        yield [("sphere", lambda: primitives.fit_sphere(points, tol)),
               ("cylinder", lambda: primitives.fit_cylinder(points, tol, support)),
               ("box", lambda: primitives.fit_box(points, tol, support, blocking)),
               ("revolution", lambda: symmetry.fit_revolution(points, tol, support))]
        if coverage >= CLOSING_COVERAGE or forced == "closing":
            yield [("closing", lambda: closing.poisson_closing(
                points, normals, tol))]
        def _mirror():
            planes_m, stats = symmetry.mirror_planes(points, tol, support, free_fn)
            if not planes_m:
                return None, {**stats, "reason": "no mirror plane with agreeing, uncontradicted halves"}
            return support_closing(symmetry.mirrored_points(points, planes_m), 0.5 * tol, support, free_fn,
                                   keep=points), stats
        yield [("mirror", _mirror)]
        yield [("support", lambda: support_closing(points, 0.5 * tol, support, free_fn))]

    candidates: dict[str, dict] = {}
    chosen = None
    fallback = None
    for tier in tiers():
        best = None
        for name, fit in tier:
            if forced != "auto" and name != forced:
                continue
            try:
                out = fit()
            except RuntimeError as e:       # plugin failure: reported, next tier runs
                candidates[name] = {"accepted": False, "why": str(e)}
                continue
            stats = {}
            if isinstance(out, tuple):
                out, stats = out
            if out is None or not is_solid(out):
                candidates[name] = {"accepted": False, "why": stats.get("reason", "no closed fit")}
                continue
            mesh = out
            if name in ("sphere", "cylinder", "box", "revolution", "plugin"):
                mesh, n_parts = attach_outliers(mesh, points, tol)
                stats["parts_added"] = n_parts
            if free_fn is not None:
                frac = check(mesh, points, tol, free_fn=free_fn, pitch=tol)["free_space_fraction"]
                if frac > FREE_CARVE:
                    mesh = carve_free(mesh, points, free_fn, tol)
            if mesh is not None and (obstacles or blocking):
                mesh = subtract_obstacles(mesh, obstacles, blocking, points, obstacle_manifolds)
            if mesh is None or not len(mesh.faces):
                candidates[name] = {"accepted": False, "why": "nothing left after the constraints"}
                continue
            if genus(mesh) > MAX_GENUS:
                sealed = seal_handles(mesh, tol)
                if sealed is None or not is_solid(sealed) or genus(sealed) > MAX_GENUS:
                    candidates[name] = {"accepted": False,
                                        "why": f"genus {genus(mesh)}: tunnels through the solid"}
                    continue
                mesh = sealed
            from .coverage import fit_quality

            rms, inl = fit_quality(mesh, points, tol)
            ok = inl >= ACCEPT_INLIERS and (name not in _PARAMETRIC or rms <= PARAMETRIC_RMS * tol)
            ok = ok or forced == name
            candidates[name] = {"accepted": bool(ok), "fit_rms": rms, "inliers": inl, **stats,
                                "why": "" if ok else (f"only {inl:.0%} of points within {tol * 1000:.1f} mm"
                                                     if inl < ACCEPT_INLIERS else
                                                     f"RMS {rms * 1000:.1f} mm > {PARAMETRIC_RMS:g} voxel")}
            if name == "support":
                fallback = (name, mesh, rms, inl)
            if ok and (best is None or rms * _COMPLEXITY[name] < best[2] * _COMPLEXITY[best[0]]):
                best = (name, mesh, rms, inl)
        if best is not None:
            chosen = best
            break
    seconds = time.perf_counter() - t0
    if chosen is None and fallback is not None:
        chosen = fallback
    if chosen is None:
        return _unchanged(partial, "none", "no method produced a closed shape that meets the constraints",
                          coverage=coverage, tolerance=tol, seconds=seconds, candidates=candidates)
    name, mesh, rms, inl = chosen
    surf_cov = surface_coverage(mesh, points, 2 * tol, tol)
    state = check(mesh, points, tol, obstacles=obstacles, planes=blocking, free_fn=free_fn, pitch=tol)
    why = (f"coverage {coverage:.2f} < {threshold:.2f}; {name} fits {inl:.0%} of observed points "
           f"(RMS {rms * 1000:.1f} mm){note}")
    if candidates.get(name, {}).get("accepted") is False:
        why += "; no method passed the fit test, fallback used"
    rejected = [f"{k}: {v['why']}" for k, v in candidates.items() if not v["accepted"] and v.get("why")]
    if rejected:
        why += "; rejected " + ", ".join(rejected)
    return CompletionResult(
        mesh=mesh, completed=True, method=name, reason=why, coverage=coverage,
        surface_coverage=surf_cov, fit_residual=state["fit_rms"],
        observed_on_surface=state["observed_on_surface"], collision_volume=state["collision_volume"],
        free_space_fraction=state.get("free_space_fraction", math.nan), tolerance=tol,
        seconds=time.perf_counter() - t0, candidates=candidates)


__all__ = ["CompletionResult", "complete", "METHODS"]
