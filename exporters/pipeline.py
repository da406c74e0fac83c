"""`export_scene`: objects (or a trained scene) -> an export folder, written atomically.

OUT/
  scene.xml + assets/    (format "mjcf")     scene.usda + assets/ (format "usd")    scene.glb ("glb")
                                    (the writers: exporters.formats.FORMATS)
  meshes/<name>.obj (+ .mtl, .png)  visual mesh of every object, world frame
  collision/<name>_<k>.obj          convex collision parts (world frame; primitives as meshes)
  report.json                       per object + the simulation check (deterministic)
  preview.png, report.html          the scene before / after the settle, a page per export (below)
  timings.json                      wall / user / system seconds per step (exporters.clock; the only
                                    file that differs between runs)
The folder is built in a temporary directory and renamed at the end: never half written.
"""
from __future__ import annotations

import json
import shutil
import time
from contextlib import ExitStack
from dataclasses import replace
from pathlib import Path

import numpy as np

from psimap import PsimapError
from psimap.exporters import clock
from psimap.exporters.roles import Reason, Role

# A thing whose surface the views saw less than this share of (its bottom left out: the support
# decides it) is exported static, with the reason: its shape, so how it rests, is a guess. Measured
# per object (objects.observed_coverage), whatever number of surfels represents it: on the demo
# checkpoint the bottles and boxes held by 10-23 surfels are 86-98 % seen, the furniture 45-56 %.
MIN_COVERAGE = 0.3

# The export fails (report["outcome"]) when fewer than this share of the things that should move
# come out dynamic (pinned, skipped, cut away, too little evidence); 0 = never.
MIN_DYNAMIC = 0.5

# settle checks after pinning the objects that moved: an object resting on a pinned one may have
# moved only because its support did (those are pinned a round after their supports, if they
# still move)
PIN_ROUNDS = 3


def floor_height(objects, environment=None) -> float:
    """Floor z: the static environment's floor (its observed floor, where objects were cut; or the
    safety plane under everything when no floor was seen), unless objects reach more than 1 cm below
    it; else the lowest object's bottom."""
    lows = [float(o.mesh.bounds[0, 2]) for o in objects]
    z = min(lows) if lows else 0.0
    zf = environment.floor_z if environment is not None else None
    if zf is not None and (not lows or zf <= z + 0.01):
        return min(z, zf) if lows else zf
    return z


def export_scene(scene_or_objects, out_dir: str | Path, format: str | list[str] = "mjcf", *,
                 completion: str = "auto", check: bool = True, background=None,
                 progress: bool = False, seed: int = 0, static_classes=None,
                 min_coverage: float = MIN_COVERAGE, pin_unstable: bool = True, overwrite: bool = False,
                 up: str = "auto", min_dynamic: float = MIN_DYNAMIC, check_engine: str = "mujoco",
                 preview: bool = True, **kw) -> dict:
    """Export objects to `out_dir`; returns the report dict (also written as report.json).

    scene_or_objects: psimap.scene.Scene (objects extracted with the full pipeline) or a list of
    SceneObject (background: optional static SceneObject). completion: "auto", "none" or one
    registered method by name, for every object (psimap.completion.complete). format: a name of the
    writer registry (exporters.formats.FORMATS: "mjcf", "usd", "glb"), "all" or a list. check: run
    the MuJoCo simulation check (on an MJCF written for it); a load failure raises PsimapError, a
    failed settle is reported (report["check"]["passed"]).
    static_classes: class names exported static (collider, no freejoint / rigid body); None = the
    default heavy-furniture list (exporters.physics.STATIC_CLASSES), an empty set = all dynamic.
    min_coverage: an object whose surface the views saw less of (Measurements.coverage) is exported
    static with the reason in report.json (0 = never; objects of unknown coverage, -1, never).
    pin_unstable: objects that move or fall in the settle check are exported static (reason in
    report.json, names in report["check"]["pinned"]) and the scene is checked again, up to
    PIN_ROUNDS times. A reconstructed support is never exactly flat: a box 4 cm from a table's
    rounded, fused edge rested on one point and tipped off (seed-5 demo scene). Drift, falls and
    penetration the nudges cannot clear ("wedged") are pinned; NaN and explosions still fail the
    check.
    overwrite: write into an `out_dir` psimap did not write (psimap.io_utils rules: an earlier export
    there is replaced; with overwrite, other files are kept and only same-named ones replaced).
    up: the capture's gravity-up direction ("auto": estimated, psimap.geometry.gravity; "+z", "-y",
    ... or "x,y,z"): a scene is turned so that it points along +z before anything is extracted, and
    the rotation is in report["gravity"]. Objects passed as a list are taken as Z-up already.
    min_dynamic: report["outcome"] fails when fewer than this share of the things the map found
    (those not static by class) come out dynamic: a scene in which nothing can move is no success.
    check_engine: "mujoco", "newton" or "all". The MuJoCo check always runs with `check` (its nudges
    and pins place the objects); "newton" / "all" also settle the written scene.usda in Newton
    (psimap.sim.newton_check; one written for it when the formats have no USD) into
    report["check_newton"].
    preview: write preview.png (MuJoCo's offscreen renderer: the scene before and after the settle,
    objects tinted by role; exporters.preview) and report.html (exporters.html_report); with no
    offscreen OpenGL the export still succeeds, without preview.png (report["preview"] says why).

    Roles are decided on copies of the objects (the ones passed in keep theirs). The order:
    objects -> roles -> meshes/ and collision/ (as reconstructed) -> settle check (pins, nudges) ->
    the nudges applied to the export scene once -> every writer, in registry order.
    """
    from psimap.completion.methods import Choices
    from psimap.exporters.formats import FORMATS, ExportScene, format_names, load
    from psimap.exporters.objects import SceneObject, extract_scene
    from psimap.io_utils import atomic_dir, check_output_dir

    fmts = format_names(format)
    if completion not in Choices():
        raise PsimapError(f"unknown completion {completion!r} (choose from {', '.join(Choices())})")
    if not 0.0 <= float(min_dynamic) <= 1.0:
        raise PsimapError(f"--min-dynamic must lie in 0..1, got {min_dynamic}")
    check_output_dir(out_dir, "export", overwrite=overwrite)       # before the work, not after it
    from psimap.sim.export_check import engines_of

    with_newton = check and "newton" in engines_of(check_engine)
    if with_newton:         # a missing optional extra is an error before the work
        from psimap.sim.newton_check import require_newton

        require_newton()
    t0 = clock.now()
    scene_steps: dict = {}
    if isinstance(scene_or_objects, (list, tuple)):
        all_objs = list(scene_or_objects)
        if any(not isinstance(o, SceneObject) for o in all_objs):
            raise PsimapError("export_scene: expected a Scene or a list of SceneObject")
        environment = None
        if background is not None:
            from psimap.exporters.environment import static_environment

            environment = static_environment(background.mesh, seed=seed)
        gravity = None
    else:
        scene_or_objects, gravity = gravity_aligned(scene_or_objects, up)
        all_objs, background, environment = extract_scene(
            scene_or_objects, completion=completion, progress=progress, seed=seed, timings=scene_steps,
            static_classes=static_classes, **kw)
    objects_clock: dict = {}
    clock.add(objects_clock, "objects", t0)
    # the environment passed in the list is no object (it is `background`)
    objs = [replace(o) for o in all_objs if o.role is not Role.SKIPPED and o.reason is not Reason.ENVIRONMENT]
    assign_roles(objs, static_classes, min_coverage)
    names = [o.name for o in objs]
    if len(set(names)) != len(names):
        raise PsimapError("export_scene: object names are not unique (duplicate instance ids)")
    scene = ExportScene(tuple(objs), background, floor_height(objs, environment), environment=environment)
    timings = {**objects_clock, **scene_steps}
    for o in all_objs:      # per asset step, summed over the objects
        for k, v in o.measured.timings.items():
            timings[k] = timings.get(k, 0.0) + v
    report = {"format": sorted(fmts), "floor_z": scene.floor_z, "objects": [], "background": None,
              "gravity": None if gravity is None else gravity.to_json(),
              "environment": None if environment is None else environment.summary(),
              "skipped": [{"name": o.name, "instance_id": int(o.instance_id), "class": o.label, "reason": o.why}
                          for o in all_objs if o.role is Role.SKIPPED]}
    with atomic_dir(out_dir, "export", overwrite=overwrite) as tmp, ExitStack() as on_exit:
        files = _write_meshes(scene, tmp)
        from psimap.exporters.report import object_entry, write_report

        t = clock.now()
        settled = {} if check else None
        if check:
            report["check"] = settle_check(scene, tmp / ".check", pin_unstable=pin_unstable, timings=timings,
                                           settled=settled, keep=preview)
            scene = scene.nudged(report["check"]["nudges"])
        if preview:     # drawn in a child process while the writers write
            pending, t_preview = _start_preview(scene, tmp, settled), time.perf_counter()
            on_exit.callback(pending.cancel)    # a writer that fails stops the child before tmp goes
        # after the check: it may have pinned objects static
        report["objects"] = [object_entry(o, files[o.name]) for o in scene.objects]
        report["outcome"] = export_outcome(all_objs, scene.objects, min_dynamic, static_classes)
        if background is not None:
            report["background"] = object_entry(background, files.get(background.name, {}))
        for name in fmts:
            fmt = FORMATS[name]
            with clock.step(timings, name):
                main_file = load(fmt.writer)(scene, tmp)
                if fmt.validator:
                    found = report[f"{name}_validation"] = load(fmt.validator)(main_file)
                    if found["errors"]:
                        raise PsimapError(f"{fmt.title} validation failed: {found['errors'][0]}")
        clock.add(timings, "writers", t)
        if with_newton:
            report["check_newton"] = newton_settle_check(scene, tmp, "usd" in fmts, timings)
        thumbs = {}
        if preview:
            from psimap.exporters.preview import finish_preview

            t_wait = time.perf_counter()
            report["preview"], thumbs = finish_preview(pending, scene, report.get("check"), tmp)
            timings["preview_wait_s"] = time.perf_counter() - t_wait     # what the preview adds
            timings["preview_s"] = time.perf_counter() - t_preview       # the child's draw, overlapped
            shutil.rmtree(tmp / ".preview")
        clock.add(timings, "total", t0)
        write_report(tmp / "report.json", report)
        if preview:     # from report.json as written: the page shows its figures, never others
            from psimap.exporters.html_report import write_html

            write_html(tmp / "report.html", json.loads((tmp / "report.json").read_text()), thumbs)
        (tmp / "timings.json").write_text(json.dumps({k: round(v, 4) for k, v in timings.items()},
                                                     indent=2, sort_keys=True) + "\n")
    report["timings"] = timings
    return report


def export_outcome(found, exported, min_dynamic: float = MIN_DYNAMIC, static_classes=None) -> dict:
    """What came of the things the map found (`found`: every extracted object, skipped ones too;
    `exported`: the export's objects after the settle check): how many are dynamic, and why the
    others are not. Things of a static class (furniture, the user's --static-classes; skipped ones
    too) are not asked to move. passed: at least `min_dynamic` of the others are dynamic (True when
    there are none)."""
    from psimap.exporters.physics import is_static_class

    by_name = {o.name: o for o in exported}
    counts = {"things": 0, "dynamic": 0, "static_class": 0, "pinned": 0, "little_evidence": 0, "skipped": 0}
    why = {}
    for o in found:
        if o.reason is Reason.ENVIRONMENT:
            continue
        counts["things"] += 1
        o = by_name.get(o.name, o)
        if o.role is Role.DYNAMIC:
            counts["dynamic"] += 1
        elif o.reason is Reason.STATIC_CLASS or is_static_class(o.label, static_classes):
            counts["static_class"] += 1
        elif o.reason is Reason.UNSTABLE:
            counts["pinned"] += 1
            why[o.name] = o.why
        elif o.reason is Reason.LITTLE_EVIDENCE:
            counts["little_evidence"] += 1
            why[o.name] = o.why
        else:
            counts["skipped"] += 1
            why[o.name] = o.why
    movable = counts["things"] - counts["static_class"]
    share = counts["dynamic"] / movable if movable else 1.0
    passed = movable == 0 or share >= min_dynamic
    line = (f"{counts['dynamic']} of {movable} thing(s) dynamic" + "".join(
        f", {counts[k]} {w}" for k, w in (("pinned", "pinned static (unstable)"),
                                          ("little_evidence", "static (too little evidence)"),
                                          ("skipped", "skipped"), ("static_class", "static furniture")) if counts[k]))
    return {**counts, "movable": movable, "dynamic_share": share, "min_dynamic": float(min_dynamic),
            "passed": bool(passed), "summary": line, "not_dynamic": why}


def gravity_aligned(scene, up: str = "auto"):
    """(scene turned so that its gravity-up is +z, psimap.geometry.gravity.UpEstimate). An estimate
    that is +z already (snapped within a degree) leaves the scene as it is."""
    from psimap.geometry.gravity import resolve_up

    est = resolve_up(up, *scene.up_evidence())
    if np.array_equal(est.rotation, np.eye(3)):
        return scene, est
    return scene.rotated(est.rotation), est


def settle_check(scene, work_dir: Path, *, pin_unstable: bool = True, timings: dict | None = None,
                 settled: dict | None = None, keep: bool = False) -> dict:
    """The MuJoCo check (psimap.sim.check.check_mjcf) of `scene` (ExportScene), on an MJCF written
    to `work_dir` for it and removed after. Returns the check's report with "pinned" {name:
    reason}: with pin_unstable, dynamic objects that moved, fell or stay wedged in a penetration
    are made static (Reason.UNSTABLE, on scene's objects) and the scene is checked again, up to
    PIN_ROUNDS times. The nudges it reports are those of the last round, for the scene as its
    objects' roles now stand.
    timings: receives the check's clocks (check_s, ...) and sim_seconds_per_wall_second. settled:
    receives the last round's poses after the settle (check_mjcf's `settled`); keep: leave
    work_dir/scene.xml, the MJCF of the last round (nudged, roles as they now stand), for the
    caller to remove."""
    from psimap.exporters.mjcf import write_mjcf
    from psimap.sim.check import check_mjcf

    timings = {} if timings is None else timings
    t_check = clock.now()
    res = check_mjcf(write_mjcf(scene, work_dir), settled=settled)
    pinned = {}
    for _ in range(PIN_ROUNDS if pin_unstable else 0):
        if res["penetrating"] and not res["nan"] and not res["exploded"]:
            # wedged between colliders the nudges cannot leave (a thin thing squeezed between a
            # static neighbour's hull and the floor, its own hull a few mm past its mesh): static, it
            # collides with nothing static, and the settle of the rest is asked again
            wedged = [o for o in scene.objects if o.name in res["wedged"] and o.role is Role.DYNAMIC]
            for o in wedged:
                depth, into = res["wedged"][o.name]
                pinned[o.name] = (f"wedged in the settle check: still {depth * 1000:.1f} mm inside {into} "
                                  "after the nudges")
                o.make_static(Reason.UNSTABLE, pinned[o.name])
            if wedged:
                res = check_mjcf(write_mjcf(scene, work_dir), settled=settled)
                continue
        movers = [o for o in scene.objects if o.name in res["unstable"] and o.role is Role.DYNAMIC]
        if res["passed"] or res["nan"] or res["exploded"] or res["penetrating"] or not movers:
            break
        # a thing standing on another mover may have moved only because its support did: its
        # support is pinned first and the check asked again (a box on a chair seat fell with the
        # chair, whose legs were not reconstructed, and both were pinned)
        movers = [o for o in movers if not any(stands_on_body(o, b) for b in movers if b is not o)] or movers
        for o in movers:
            if o.name in res["fell"]:
                # nothing within the support gap under it at t = 0: a piece of a wall or of furniture
                # labelled a thing (a real capture's model-free masks), or its support went unseen
                pinned[o.name] = (f"nothing under it in the settle check (fell {res['fell'][o.name] * 100:.1f} cm "
                                  "in 2 s): part of the static world, or its support was not reconstructed")
            else:
                pinned[o.name] = f"unstable in the settle check (moved {res['drift'][o.name] * 100:.1f} cm in 2 s)"
            o.make_static(Reason.UNSTABLE, pinned[o.name])
        res = check_mjcf(write_mjcf(scene, work_dir), settled=settled)
    res["pinned"] = pinned
    if not keep:
        shutil.rmtree(work_dir)
    clock.add(timings, "check", t_check)
    timings["sim_seconds_per_wall_second"] = res.pop("sim_seconds_per_wall_second")
    return res


def stands_on_body(thing, body, reach: float = 0.02) -> bool:
    """Whether `thing` (an export object) stands on `body` as reconstructed: its bottom lies above
    the body's and at most `reach` (m) over its top, its plan-view centre over the body's box."""
    lo, hi = np.asarray(thing.mesh.bounds, np.float64)
    blo, bhi = np.asarray(body.mesh.bounds, np.float64)
    c = 0.5 * (lo[:2] + hi[:2])
    return bool(blo[2] < lo[2] <= bhi[2] + reach and np.all(c >= blo[:2]) and np.all(c <= bhi[:2]))


def newton_settle_check(scene, out_dir: Path, usd_written: bool, timings: dict) -> dict:
    """The Newton check (psimap.sim.newton_check) of `scene` (ExportScene) after the MuJoCo check's
    nudges: of out_dir/scene.usda when it was written, else of one written to a work folder and
    removed after. Its speed and load time go to `timings` (report.json stays deterministic)."""
    import shutil

    from psimap.exporters.usd import write_usd
    from psimap.sim.newton_check import check_usd_newton

    t = clock.now()
    work = out_dir / ".check_newton"
    try:
        res = check_usd_newton(out_dir / "scene.usda" if usd_written else write_usd(scene, work))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    clock.add(timings, "newton_check", t)
    timings["newton_load_s"] = res.pop("load_s")
    timings["newton_sim_seconds_per_wall_second"] = res.pop("sim_seconds_per_wall_second")
    return res


def _start_preview(scene, tmp: Path, settled: dict | None):
    """Start drawing the preview of `scene` (roles final, nudged) in tmp/.preview: from the settle
    check's MJCF (tmp/.check, kept for it) with its settled poses, or, without a check, from an MJCF
    written for the picture alone."""
    from psimap.exporters.preview import start_preview

    work = tmp / ".preview"
    if settled is not None:
        (tmp / ".check").rename(work)
    else:
        from psimap.exporters.mjcf import write_mjcf

        write_mjcf(scene, work)
    return start_preview(scene, work / "scene.xml", work / "pictures.npz", settled)


def assign_roles(objs, static_classes=None, min_coverage: float = MIN_COVERAGE) -> None:
    """The role of each object (none skipped, not the environment) for this export: static for
    objects of a static class and objects seen too little to be a reliable rigid body (less than
    min_coverage of their surface observed), dynamic otherwise. Decided anew on every call (the
    same objects can be exported with other rules)."""
    from psimap.exporters.physics import is_static_class

    for o in objs:
        o.make_dynamic()
        cov = o.measured.coverage
        if is_static_class(o.label, static_classes):
            o.make_static(Reason.STATIC_CLASS, f"static furniture class: '{o.label}'")
        elif 0 <= cov < min_coverage:
            o.make_static(Reason.LITTLE_EVIDENCE, f"too little evidence for a rigid body: {cov:.0%} of its "
                                                  f"surface seen < {min_coverage:.0%}")


def _write_meshes(scene, root: Path) -> dict:
    """meshes/ (textured OBJ) and collision/ (convex parts) of every object and the background, in
    the world frame as reconstructed (report.json's bounds; the settle nudges are the scene files')."""
    from psimap.exporters.objfile import write_plain, write_textured_obj

    (root / "meshes").mkdir(parents=True, exist_ok=True)
    (root / "collision").mkdir(parents=True, exist_ok=True)
    files = {}
    for o in list(scene.objects) + ([scene.background] if scene.background is not None else []):
        write_textured_obj(np.asarray(o.visual.vertices, np.float64), o.visual.faces, o.uv, o.texture,
                           root / "meshes" / f"{o.name}.obj", o.name, vertex_rgb=o.vertex_rgb)
        entry = {"mesh": f"meshes/{o.name}.obj", "collision": []}
        if o.collision is not None:
            for k, part in enumerate(o.collision.parts):
                rel = f"collision/{o.name}_{k}.obj"
                write_plain(np.asarray(part.vertices, np.float64), part.faces, root / rel)
                entry["collision"].append(rel)
        files[o.name] = entry
    return files
