"""psimap.completion: collision-aware completion of partially observed objects.

Installed as `psimap.completion`; the export pipeline calls `complete(partial, context)` once per
object (step 3) unless `--completion none`. It works offline on a CPU, with no model weights, and
says what it did: `CompletionResult.method` names the method and `reason` says why.

The context is a `CompletionContext` (methods.py: every field and what it means). The methods are
one table (methods.py: name, tier, fit, parametric or not), extended by packages through the
entry-point group `psimap.completion`. In `auto` they are tried in tiers of increasing generality;
the first tier with a candidate whose fit passes (>= 90 % of observed points within the tolerance
of its surface, after free-space carving and collision removal; parametric shapes also need an RMS
<= half a voxel) wins; inside a tier the lowest residual wins, weighted by complexity (primitives
1.0, revolution 1.25). The built-in tiers: plugin -> primitives (sphere / cylinder / box,
`primitives.py`) and rotational symmetry (`symmetry.py`) -> watertight Poisson closing of the shell
(`closing.py`, only when most directions were seen) -> reflective symmetry (`symmetry.py`) ->
support-aware closing (`support.py`, always available as the fallback).
Parts of the observation a fitted shape leaves outside (a mug's handle) are added back as convex
pieces.
Constraints (`constraints.py`) and free space (`freespace.py`) apply to every result.
"""
from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

from psimap import PsimapError
from psimap.completion.methods import CompletionContext, Method, Observation, methods

MIN_POINTS = 50               # fewer observed points do not constrain any shape
ACCEPT_INLIERS = 0.9          # share of observed points within tolerance of a candidate surface
PARAMETRIC_RMS = 0.5          # a parametric shape must also fit tightly: RMS <= this x voxel
# A closed result with more handles than a mug's is a sponge, not an object: Poisson closing of a
# fused shell whose two skins disagree in orientation came out with genus 17 on a 20 cm box (43 %
# of its volume missing, its convex hull 7 cm off), and every collider after it chased the holes.
# Handles up to two voxels wide are sealed (Poisson leaves sub-voxel ones on a plain ball); a
# candidate with wider ones is rejected.
MAX_GENUS = 1
FREE_CARVE = 0.01             # carve a candidate when more than this share of it is known-free
# A candidate the constraints cut apart no longer describes one object: a room's bottle boxed down
# to its shelf board lost a 3 mm slab to a neighbour's solid 2.4 cm above the board; its foot
# and its body were two pieces, the decimation kept the body and the bottle hovered, fell in the
# settle check and was pinned static. Pieces holding this share of the volume count
SPLIT_SHARE = 0.02


@dataclass
class CompletionResult:
    mesh: object            # trimesh.Trimesh, metres, world frame
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


def _observed_points(partial, context: CompletionContext):
    """[P, 3] finite observed points: context.points, else samples of the partial mesh's surface."""
    import numpy as np

    pts = context.points
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


def complete(partial, context: CompletionContext | Mapping | None = None) -> CompletionResult:
    """Complete a partially observed object.

    partial: trimesh.Trimesh of the observed object (metres, world frame; may be open) or None when
    context.points is given. context: a CompletionContext (a mapping of its field names is taken
    too). Returns a CompletionResult whose mesh is the completed closed mesh, or `partial` unchanged
    (completed=False) with the reason. Raises PsimapError for malformed input (wrong shapes,
    non-finite cameras, an unknown method).

    context.method "auto" tries the registered methods tier by tier (module doc); a fully observed
    object comes back unchanged. A method's name runs that method alone, on every object (a fully
    observed one too), and never another in its place:
    - its closed shape that survives the constraints (free space, neighbours, walls, genus) is
      used, also when it fails the fit test `auto` applies (the reason then says "forced: ...");
    - when it gives no such shape (it declines or fails, finds no closed fit, nothing is left after
      the constraints, or it cannot run, as "plugin" without a plugin callable), `partial` comes
      back unchanged (completed False, method "none") and the reason says what went wrong.
    """
    import numpy as np

    t0 = time.perf_counter()
    context = CompletionContext.of(context)
    if partial is not None and not hasattr(partial, "vertices"):
        raise PsimapError(f"completion: partial must be a trimesh.Trimesh or None, got {type(partial).__name__}")
    forced = context.method or "auto"
    table = methods()
    if forced != "auto":
        if forced not in {m.name for m in table}:
            raise PsimapError(f"completion: unknown method {forced!r} (auto, {', '.join(m.name for m in table)})")
        table = [m for m in table if m.name == forced]
    points = _observed_points(partial, context)
    if len(points) == 0:
        return _unchanged(partial, "skipped", "empty partial: no observed points",
                          seconds=time.perf_counter() - t0)
    from .coverage import directional_coverage, point_spacing, surface_coverage

    spacing = point_spacing(points)
    voxel = context.voxel_size
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
    from .freespace import cameras_seeing, check_cameras, free_space_share, known_free, seen_on_surface
    from .meshops import genus, is_solid, seal_handles, significant_pieces, solids_near, to_manifold
    from .support import normalise_planes, planes_from_background, support_below

    # Context is validated before any early return so malformed input always fails loudly.
    centre = 0.5 * (points.min(0) + points.max(0))
    background = context.background
    planes = normalise_planes(context.support_planes, centre)
    cams = check_cameras(context.cameras, context.depths)
    note = ""
    if context.points is None and cams:
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
    threshold = float(context.coverage_threshold)
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
    near = [m for m in (context.neighbours or []) if m is not None and len(m.faces)
            and not ((m.bounds[1] < lo).any() or (m.bounds[0] > hi).any())]
    # the neighbours' solids only where they are near, at this object's pitch, the open ones as one
    obstacles = solids_near(near, (lo, hi), 0.5 * tol)
    if background is not None and is_solid(background):
        obstacles.append(background)
    obstacle_manifolds = [to_manifold(o) for o in obstacles]    # converted once, used per candidate
    obs = Observation(points=points, normals=normals, tolerance=tol, spacing=spacing, coverage=coverage,
                      support=support, blocking=blocking, free=free_fn, context=context)
    if forced == "auto":
        table = [m for m in table if m.when is None or m.when(obs)]
    tiers: dict[int, list[Method]] = {}
    for m in table:             # tier order, table order inside a tier
        tiers.setdefault(m.tier, []).append(m)

    candidates: dict[str, dict] = {}
    chosen = None
    fallback = None
    for tier in tiers.values():
        best = None
        for method in tier:
            name = method.name
            try:
                out = method.fit(obs)
            except RuntimeError as e:       # a method declining (a plugin failure): reported, the next runs
                candidates[name] = {"accepted": False, "why": str(e)}
                continue
            stats = {}
            if isinstance(out, tuple):
                out, stats = out
            if out is None or not is_solid(out):
                candidates[name] = {"accepted": False, "why": stats.get("reason", "no closed fit")}
                continue
            mesh = out
            if method.adds_outliers:
                mesh, n_parts = attach_outliers(mesh, points, tol)
                stats["parts_added"] = n_parts
            unconstrained = mesh                                # what the constraints must not cut apart
            if free_fn is not None:
                # only the free-space share of each candidate: the whole `check` also measured a fit
                # that the loop measures again after the constraints
                frac = free_space_share(mesh, free_fn, tol)
                if frac > FREE_CARVE:
                    mesh = carve_free(mesh, points, free_fn, tol)
            if mesh is not None and (obstacles or blocking):
                mesh = subtract_obstacles(mesh, obstacles, blocking, points, obstacle_manifolds)
            if mesh is None or not len(mesh.faces):
                candidates[name] = {"accepted": False, "why": "nothing left after the constraints"}
                continue
            if mesh is not unconstrained and significant_pieces(mesh, SPLIT_SHARE) > max(
                    significant_pieces(unconstrained, SPLIT_SHARE), 1):
                candidates[name] = {"accepted": False, "why": "the constraints cut it apart"}
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
            passed = inl >= ACCEPT_INLIERS and (not method.parametric or rms <= PARAMETRIC_RMS * tol)
            ok = passed or forced == name
            candidates[name] = {"accepted": bool(ok), "fit_rms": rms, "inliers": inl, **stats,
                                "why": "" if passed else (f"only {inl:.0%} of points within {tol * 1000:.1f} mm"
                                                         if inl < ACCEPT_INLIERS else
                                                         f"RMS {rms * 1000:.1f} mm > {PARAMETRIC_RMS:g} voxel")}
            if method.fallback:
                fallback = (method, mesh, rms, inl)
            if ok and (best is None or rms * method.complexity < best[2] * best[0].complexity):
                best = (method, mesh, rms, inl)
        if best is not None:
            chosen = best
            break
    seconds = time.perf_counter() - t0
    if chosen is None and fallback is not None:
        chosen = fallback
    if chosen is None:
        why = "no method produced a closed shape that meets the constraints"
        if forced != "auto":
            why = f"{forced} (asked for) gave no closed shape that meets the constraints: " + (
                candidates.get(forced, {}).get("why") or "not run")
        return _unchanged(partial, "none", why, coverage=coverage, tolerance=tol, seconds=seconds,
                          candidates=candidates)
    method, mesh, rms, inl = chosen
    name = method.name
    surf_cov = surface_coverage(mesh, points, 2 * tol, tol)
    state = check(mesh, points, tol, obstacles=obstacles, planes=blocking, free_fn=free_fn, pitch=tol)
    why = (f"coverage {coverage:.2f} < {threshold:.2f}" if forced == "auto" else
           f"{name} asked for (coverage {coverage:.2f})")
    why += f"; {name} fits {inl:.0%} of observed points (RMS {rms * 1000:.1f} mm){note}"
    if forced != "auto" and candidates[name]["why"]:
        why += f"; forced: {candidates[name]['why']}"
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


__all__ = ["CompletionContext", "CompletionResult", "Method", "Observation", "complete"]
