"""Per-object assets: `SceneObject` and the asset steps 2-7 applied to one mesh.

`build_object(mesh, label, instance_id, ...)`: repair -> completion hook -> decimation to an error
budget -> UV + texture -> collision geometry -> mass properties. An object that cannot be made
sound (flat, sliver, no volume, cannot be closed) comes back with role Role.SKIPPED, its Reason and
`why`, and never reaches a writer. `extract_objects(scene)` does this for every instance of a
checkpoint.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field, replace

import numpy as np

from psimap.exporters import clock
from psimap.exporters.roles import Reason, Role


# Hull cap of static furniture's colliders (dynamic objects: finish_object's max_hulls, 8). What
# rests on a support feels its collider's error, and static parts cost the simulation little (they
# never collide with each other): on the demo scene a cap of 32 took the shelf's collider from
# 155.5 to 77.6 mm (RESULTS.md, "hull cap of static furniture colliders").
STATIC_MAX_HULLS = 32


@dataclass
class Measurements:
    """What the asset steps did to one object and how well: report.json's per-object numbers."""

    faces_before: int = 0
    faces_after: int = 0
    decimation_error: float = 0.0           # metres (symmetric Hausdorff)
    decimation_mean_error: float = 0.0
    decimation_budget: float = 0.0
    face_budget: int = 0                    # most faces the visual mesh may have (decimate.visual_face_budget)
    coverage: float = -1.0                  # share of its surface the views saw (observed_coverage; -1: unknown)
    watertight: bool = False
    completed: bool = False
    completion_method: str = "none"
    repair_steps: list = field(default_factory=list)
    timings: dict = field(default_factory=dict, repr=False)   # wall / user / system seconds per asset step (clock)


@dataclass
class SceneObject:
    """One exported object. mesh: trimesh.Trimesh in metres, world frame (textured when baked).

    Inputs (what the checkpoint says): instance_id, label, semantic_id, surfel_count. Role: one of
    Role with the Reason code and `why` in words (Role.DYNAMIC needs no reason). Asset: the solid,
    its texture, collider and mass. Measurements: `measured`.
    """

    instance_id: int
    label: str
    mesh: object
    semantic_id: int = 0
    surfel_count: int = -1                  # surfels of the checkpoint behind it (-1: not from one)
    role: Role = Role.DYNAMIC
    reason: Reason | None = None
    why: str = ""                           # the reason in words, as report.json writes it
    collision: object | None = None         # psimap.exporters.collision.Collision
    physics: object | None = None           # psimap.exporters.physics.Physics
    visual_mesh: object | None = None       # seam-split copy of mesh that uv / vertex_rgb index
    uv: np.ndarray | None = None            # [V, 2] per visual_mesh vertex
    texture: np.ndarray | None = None       # uint8 [S, S, 3]
    vertex_rgb: np.ndarray | None = None    # [V, 3] float fallback colours (per visual vertex)
    texture_source: str = "none"            # "views" | "mesh" | "vertex" | "none"
    texture_coverage: float = 0.0           # fraction of texels some view saw
    solid_pitch: float = 0.0                # voxel (m) of the solid it was closed as (0: not voxelised)
    solid_kind: str = ""                    # how (exporters.solidify): "enclosed" | "carved" | "shell" | ""
    detail: float = 0.0                     # finest detail (m) its own surfels resolve: the voxel it was fused at (0: unknown)
    support_z: float | None = None          # height of the plane it rests on (None: not resting)
    # objects whose observed surface its solid yielded to (exporters.consistency): its collider
    # must not enter them either
    keep_clear: list = field(default_factory=list)
    # objects its carved solid yielded to (exporters.consistency): cleared by its collider too,
    # unless it is furniture with tops (kept_clear)
    yielded_to: list = field(default_factory=list)
    measured: Measurements = field(default_factory=Measurements)
    source: object | None = field(default=None, repr=False)   # input mesh until finish_object

    def skip(self, reason: Reason, why: str) -> None:
        """Leave the object out of the export (it never reaches a writer)."""
        self.role, self.reason, self.why = Role.SKIPPED, reason, why

    def make_static(self, reason: Reason, why: str) -> None:
        """Export the object as a collider welded to the world."""
        self.role, self.reason, self.why = Role.STATIC, reason, why

    def make_dynamic(self) -> None:
        self.role, self.reason, self.why = Role.DYNAMIC, None, ""

    @property
    def name(self) -> str:
        safe = re.sub(r"[^A-Za-z0-9]+", "_", self.label).strip("_") or "object"
        if safe[0].isdigit():
            safe = "c" + safe
        return f"{safe}_{int(self.instance_id)}"

    @property
    def visual(self):
        """The mesh the writers draw: the UV'd, seam-split mesh when textured, else `mesh`."""
        return self.mesh if self.visual_mesh is None else self.visual_mesh

    @property
    def mass(self) -> float:
        return 0.0 if self.physics is None else float(self.physics.mass)

    @property
    def friction(self) -> float:
        return 0.7 if self.physics is None else float(self.physics.friction)


def build_object(mesh, label: str, instance_id: int, *, semantic_id: int = 0, views=None,
                 source_textured=None, completion: str = "auto", context=None,
                 decimation_budget: float | None = None, collision_tolerance: float | None = None,
                 max_hulls: int = 8, densities: dict | None = None, texel: float = 0.001,
                 resolution: float | None = None, seed: int = 0) -> SceneObject:
    """Asset steps 2-7 for one dynamic object: `prepare_solid` then `finish_object`.

    mesh: trimesh.Trimesh (metres, world frame). views: list of texture.View to bake from;
    source_textured: a textured trimesh to transfer colour from (scans); else vertex colours of
    `mesh` (if any). completion and context: as prepare_solid's.
    resolution: size (m) of the finest detail the source resolves (TSDF voxel): decimation budget
    and collision tolerance are never asked to be finer than it.
    """
    obj = prepare_solid(mesh, label, instance_id, semantic_id=semantic_id, completion=completion,
                        context=context, resolution=resolution)
    return finish_object(obj, views=views, source_textured=source_textured,
                         decimation_budget=decimation_budget, collision_tolerance=collision_tolerance,
                         max_hulls=max_hulls, densities=densities, texel=texel, resolution=resolution, seed=seed)


def prepare_solid(mesh, label: str, instance_id: int, *, semantic_id: int = 0, completion: str = "auto",
                  context=None, support_z: float | None = None, surfel_points=None, carve_views=None,
                  resolution: float | None = None, open_under: float | None = None) -> SceneObject:
    """Steps 2-3: clean, complete and close `mesh` into a sound watertight solid (obj.mesh), or an
    object with role Role.SKIPPED. The solid can still be edited (overlaps, support) before
    `finish_object`.

    completion: "auto" (psimap.completion's tiers), "none" (skipped) or the name of one registered
    method (psimap.completion.complete says what running one method means); context: the
    psimap.completion.CompletionContext of the object (its label and method are set here).
    With `resolution` (the source's voxel) an open scan is closed as the voxel solid it encloses
    (exporters.solidify), carved by `carve_views` (texture.View) around `surfel_points` [P, 3], down
    to the support plane at height `support_z`, on which the solid is then made to rest; below a
    furniture top at height `open_under` only what its observed sides enclose is solid.
    """
    from psimap.exporters.repair import repair_mesh

    obj = SceneObject(int(instance_id), str(label), mesh, semantic_id=int(semantic_id))
    obj.source = mesh
    obj.measured.faces_before = int(len(getattr(mesh, "faces", [])))
    # clean first (floaters, degenerate faces), let completion close a partial scan, then require
    # a sound watertight solid
    t0 = clock.now()
    pre = repair_mesh(mesh, need_volume=False)
    if not pre.ok:
        obj.skip(Reason.REPAIR, f"repair: {pre.reason}")
        return obj
    m = pre.mesh
    # furniture with a top is carved and opened under it (exporters.solidify): completion tiers are
    # for what a movable thing hides, and extruding a table's top down to the floor made a block
    if completion != "none" and open_under is None:
        from psimap.completion import CompletionContext, complete

        with clock.step(obj.measured.timings, "completion"):
            res = complete(m, replace(context or CompletionContext(), label=label, method=completion))
        obj.measured.completed, obj.measured.completion_method = bool(res.completed), str(res.method)
        if res.completed and res.mesh is not None:
            m = res.mesh
    support = support_z
    # a fused (open) scan is closed as the voxel solid it encloses, at the source's resolution
    solid_kw = {}
    if resolution:
        from psimap.exporters.solidify import solid_pitch

        solid_kw = {"pitch": solid_pitch(m, resolution), "support_z": support, "points": surfel_points,
                    "views": carve_views, "open_under": open_under}
    rep = repair_mesh(m, need_volume=True, **solid_kw)
    obj.measured.repair_steps = pre.steps + rep.steps
    if not rep.ok and obj.measured.completed:         # a bad completion must not lose the object
        obj.measured.repair_steps.append(f"completion discarded: {rep.reason}")
        obj.measured.completed = False
        rep = repair_mesh(pre.mesh, need_volume=True, **solid_kw)
        obj.measured.repair_steps += rep.steps
    if not rep.ok:
        obj.skip(Reason.REPAIR, f"repair: {rep.reason}")
        return obj
    m = rep.mesh
    if "solidify" in getattr(m, "metadata", {}):
        # a voxel solid is known to one voxel: decimation need not keep its staircase finer
        obj.solid_pitch = float(solid_kw["pitch"])
        obj.solid_kind = str(m.metadata["solidify"])
    if support is not None:
        obj.support_z = float(support)
        cut = cut_at_support(m, float(support))
        if cut is not m:
            obj.measured.repair_steps.append(f"cut flat at its support ({float(support):.3f} m)")
            m = cut
        m, grew = rest_on_support(m, float(support))
        if grew:
            obj.measured.repair_steps.append("extended down to its support")
    obj.mesh = m
    clock.add(obj.measured.timings, "repair", t0)
    for suffix in clock.SUFFIXES:       # repair = everything here but the completion
        obj.measured.timings["repair" + suffix] -= obj.measured.timings.get("completion" + suffix, 0.0)
    return obj


def finish_object(obj: SceneObject, *, views=None, source_textured=None, decimation_budget: float | None = None,
                  collision_tolerance: float | None = None, max_hulls: int = 8, densities: dict | None = None,
                  texel: float = 0.001, resolution: float | None = None, seed: int = 0,
                  obstacles=()) -> SceneObject:
    """Steps 4-7 on a prepared solid: decimation to an error budget, mass properties, collider,
    UV + texture. Skipped objects come back unchanged. obstacles: convex collider parts of
    neighbours that the collider must not enter."""
    from psimap.exporters.collision import collision_geometry, default_tolerance, solid_parts
    from psimap.exporters.decimate import decimate_to_budget, decimate_to_count, default_budget, visual_face_budget
    from psimap.exporters.physics import mass_properties

    if obj.role is Role.SKIPPED:
        obj.source = None
        return obj
    m, label, mesh = obj.mesh, obj.label, obj.source
    vertex_rgb = _vertex_rgb(mesh)
    obj.source = None
    if decimation_budget is None:
        # the visual mesh keeps what the map resolves at this object: half its own surfels' voxel
        # (a scene's finest voxel belongs to its smallest, most finely mapped thing), no finer
        # than the voxel solid it was closed as, and 0.5 % of its size
        decimation_budget = max(default_budget(m), 0.5 * resolution if resolution else 0.0, 0.5 * obj.detail,
                                obj.solid_pitch)
    if collision_tolerance is None:
        collision_tolerance = max(default_tolerance(m), 1.5 * resolution if resolution else 0.0)
    t0 = clock.now()
    # the error budget may ask for more faces than an object this size needs (a voxel solid's
    # staircase, a closing that refined the surface): the face budget wins, its error is kept
    cap = obj.measured.face_budget = visual_face_budget(m, decimation_budget, obj.measured.faces_before)
    dec = decimate_to_budget(m, decimation_budget, max_faces=cap, seed=seed)
    if len(dec.mesh.faces) > cap:
        # no closed mesh at the cap itself: twice and four times as many are tried
        dec = decimate_to_count(m, cap, dec, seed=seed)
    clock.add(obj.measured.timings, "decimation", t0)
    m = dec.mesh
    obj.measured.faces_after = int(len(m.faces))
    obj.measured.decimation_error, obj.measured.decimation_mean_error = dec.hausdorff, dec.mean_error
    obj.measured.decimation_budget = dec.budget
    obj.measured.watertight = bool(m.is_watertight)
    if not obj.measured.watertight:
        obj.skip(Reason.DECIMATION, "decimation: result not watertight")
        return obj
    try:
        obj.physics = mass_properties(m, label, densities=densities)
    except Exception as e:  # PsimapError: no volume
        obj.skip(Reason.PHYSICS, f"physics: {e}")
        return obj
    t0 = clock.now()
    obj.collision = collision_geometry(m, collision_tolerance, max_hulls=max_hulls, seed=seed,
                                       obstacles=obstacles, resting=obj.support_z is not None)
    if obj.support_z is not None and not obj.collision.is_primitive:
        obj.collision.parts = solid_parts(with_flat_base(obj.collision.parts, obj.support_z)) or obj.collision.parts
    clock.add(obj.measured.timings, "collision", t0)
    if obj.collision.kind == "sphere":
        # a sphere collider means the object is a ball: its COM is the centre (a reconstruction's
        # sub-millimetre COM offset would otherwise roll a ball that rests in the scan)
        obj.physics.com = np.asarray(obj.collision.transform, np.float64)[:3, 3].copy()
    if views:
        texel = max(texel, view_texel(m, views))
        if len(views) > MAX_BAKE_VIEWS:
            # views spread along the trajectory; more only average the same texels again
            views = [views[i] for i in np.unique(np.linspace(0, len(views) - 1, MAX_BAKE_VIEWS).round().astype(int))]
    with clock.step(obj.measured.timings, "texture"):
        _texture(obj, m, views, source_textured, vertex_rgb, mesh, texel)
    return obj


def view_texel(mesh, views) -> float:
    """Texel size (m) the views can fill: half the finest pixel footprint (depth / focal length)
    at the object's centre over `views`; finer texels only interpolate (a 1 mm atlas baked from
    160x120 views at 1.5 m cost 5 s per object and held no more detail than a 5 mm one)."""
    c = np.asarray(mesh.bounds, np.float64).mean(axis=0)
    best = np.inf
    for v in views:
        w2c = np.linalg.inv(v.c2w)
        z = float(w2c[2, :3] @ c + w2c[2, 3])
        if z > 1e-3:
            best = min(best, z / float(max(v.K[0, 0], v.K[1, 1])))
    return 0.5 * best if np.isfinite(best) else 0.0


def with_flat_base(parts, z: float, *, touch: float = 0.01, band: float = 0.01) -> list:
    """Convex collider parts whose bottom reaches the support plane z (within `touch`), each with
    its vertices less than `band` above its own bottom copied straight down onto the plane (a gap
    of a few millimetres closes with it): a hull simplified
    to a tolerance tilts a bottle's small base by millimetres, and a tall object standing on one
    edge of it tips over. The footprint does not grow (a wider base would reach into the neighbour
    the collider was clipped against). Parts not at the base are kept as they are."""
    import trimesh

    out = []
    for p in parts:
        v = np.asarray(p.vertices, np.float64)
        low = v[v[:, 2] <= v[:, 2].min() + band]
        if v[:, 2].min() > z + touch or len(low) < 3:
            out.append(p)
            continue
        try:
            out.append(trimesh.convex.convex_hull(np.vstack([v, np.column_stack([low[:, :2], np.full(len(low), z)])])))
        except Exception:           # a degenerate base: keep the part
            out.append(p)
    return out


def cut_at_support(mesh, z: float, tol: float = 1e-3, min_keep: float = 0.5):
    """A watertight solid cut flat at the support plane z: what the fusion let sink into the table
    it stands on goes, and the cut is its flat bottom (manifold3d). The same mesh when nothing lies
    more than `tol` below z, or when the cut would keep less than `min_keep` of the volume (then
    the support is not under it)."""
    import manifold3d

    from psimap.completion.meshops import to_manifold

    lo, hi = np.asarray(mesh.bounds, np.float64)
    if lo[2] >= z - tol or hi[2] <= z:
        return mesh
    pad = 1.0 + float(np.ptp(np.asarray(mesh.vertices)[:, :2], axis=0).max())
    box = manifold3d.Manifold.cube([2 * pad + (hi[0] - lo[0]), 2 * pad + (hi[1] - lo[1]), hi[2] - z + 1.0])
    box = box.translate([lo[0] - pad, lo[1] - pad, z])
    a = to_manifold(mesh)
    out = a ^ box
    if float(out.volume()) < min_keep * float(a.volume()):
        return mesh
    import trimesh

    mm = out.to_mesh()
    res = trimesh.Trimesh(np.asarray(mm.vert_properties, np.float64)[:, :3], np.asarray(mm.tri_verts), process=False)
    return res if res.is_watertight and res.volume > 0 else mesh


def rest_on_support(mesh, z: float, band: float = 0.15, max_gap: float = 0.05):
    """(mesh, grown) — a watertight object that rests on the plane height z stands on a base under
    its centre of mass.

    The underside of a resting object is never seen: the fused mesh ends in a rounded or ragged
    bottom that touches the support at a point off to one side, and the object rolls. When the base
    (the part within 1 mm of z) does not hold the centre of mass above it, the lowest `band` of the
    height is extruded straight down to z and joined to the object (manifold3d), as the real object
    does rest there. Objects more than `max_gap` above z are not resting and stay as they are.
    """
    import trimesh

    from psimap.completion.meshops import convex_hull, is_closed
    from psimap.exporters.physics import centre_of_volume

    v = np.asarray(mesh.vertices, np.float64)
    lo, hi = float(v[:, 2].min()), float(v[:, 2].max())
    if lo - z > max_gap or hi - z <= 0:
        return mesh, False
    # a flat fused piece has no volume: trimesh's centre of mass is 0 / 0 there (a RuntimeWarning on
    # the console of a 7-Scenes export), centre_of_volume the vertices' mean
    com = centre_of_volume(mesh)
    base = v[v[:, 2] < z + 1e-3, :2]
    if len(base) >= 3:
        try:
            if _in_hull_2d(base, com[:2]) and np.ptp(base, axis=0).min() > 0.2 * np.ptp(
                    v[:, :2], axis=0).min():
                return mesh, False
        except Exception:       # collinear base points: no area, extend
            pass
    # the band grows until its footprint holds the centre of mass (a tilted, ragged bottom puts
    # its lowest points all on one side)
    for frac in (band, 2 * band, 3 * band):
        ring = v[v[:, 2] <= lo + frac * (hi - lo)]
        try:
            if len(ring) >= 3 and _in_hull_2d(ring[:, :2], com[:2]):
                break
        except Exception:
            continue
    if len(ring) < 3:
        return mesh, False
    foot_pts = np.concatenate([ring, np.column_stack([ring[:, :2], np.full(len(ring), z)])])
    foot = convex_hull(foot_pts)        # closed: trimesh's union hands both to manifold3d unchecked
    if foot is None or not is_closed(mesh):
        return mesh, False
    try:
        out = trimesh.boolean.union([mesh, foot], engine="manifold")
    except Exception:
        return mesh, False
    if not out.is_watertight or out.volume <= 0:
        return mesh, False
    return out, True


def _in_hull_2d(points: np.ndarray, p: np.ndarray) -> bool:
    """Whether p [2] lies in the convex hull of points [n, 2] (False for a degenerate hull).
    (The hull of the unique points: a Delaunay triangulation of every vertex of an extruded
    footprint repeats each 2D point many times.)"""
    from scipy.spatial import ConvexHull

    pts = np.unique(np.round(points, 6), axis=0)
    if len(pts) < 3:
        return False
    try:
        hull = ConvexHull(pts)
    except Exception:       # collinear: no area
        return False
    return bool((hull.equations[:, :2] @ p + hull.equations[:, 2] <= 1e-9).all())


def build_background(mesh, *, views=None, label: str = "background", decimation_budget: float | None = None,
                     texel: float = 0.01, seed: int = 0) -> SceneObject:
    """Static background (floor, walls, ...): cleaned and decimated, textured, no mass."""
    from psimap.exporters.decimate import decimate_to_budget
    from psimap.exporters.repair import repair_mesh

    obj = SceneObject(0, label, mesh, role=Role.STATIC, reason=Reason.ENVIRONMENT,
                      why="static environment: floor, walls and unlabelled surfaces")
    obj.measured.faces_before = int(len(getattr(mesh, "faces", [])))
    vertex_rgb = _vertex_rgb(mesh)
    rep = repair_mesh(mesh, need_volume=False)
    if not rep.ok:
        obj.skip(Reason.REPAIR, f"repair: {rep.reason}")
        return obj
    budget = decimation_budget if decimation_budget is not None else 0.01
    dec = decimate_to_budget(rep.mesh, budget, quantile=BACKGROUND_ERROR_QUANTILE, seed=seed)
    m = dec.mesh
    obj.measured.faces_after, obj.measured.decimation_error = int(len(m.faces)), dec.hausdorff
    obj.measured.decimation_mean_error, obj.measured.decimation_budget = dec.mean_error, dec.budget
    obj.measured.watertight = bool(m.is_watertight)
    if len(m.faces) > MAX_ATLAS_FACES:
        # a room-sized mesh: xatlas took 201 s on a 137 k-face room (the demo scene), the colour per
        # vertex from the views 2.4 s, and the background is context, not an asset
        from psimap.exporters import texture as T

        obj.mesh = m
        obj.vertex_rgb = T.vertex_colors_from_views(np.asarray(m.vertices, np.float64), views) if views else None
        obj.texture_source = "vertex" if obj.vertex_rgb is not None else "none"
        return obj
    _texture(obj, m, views, None, vertex_rgb, mesh, texel)
    return obj


# The visual background's error budget holds for this quantile of the surface sample distances,
# not their maximum: it is context, not an asset (its colliders come from the undecimated mesh), and
# a few samples on a thin edge held a 644k-face room at 347k faces (2 cm off at up to 321k); at
# 0.999 one sample in 1000 may lie beyond the budget
BACKGROUND_ERROR_QUANTILE = 0.999
MAX_ATLAS_FACES = 20_000      # above this many faces a mesh is coloured per vertex, not UV-unwrapped
MAX_BAKE_VIEWS = 16           # views a texture is baked from (spread over those that see the object)


def _vertex_rgb(mesh):
    try:
        vis = mesh.visual
        if vis.kind in ("vertex", "face"):
            return np.asarray(vis.to_color().vertex_colors if vis.kind != "vertex" else vis.vertex_colors,
                              np.float64)[:, :3] / 255.0
    except Exception:
        pass
    return None


def _texture(obj: SceneObject, m, views, source_textured, vertex_rgb, original, texel: float) -> None:
    """UV-unwrap `m` and bake a texture into obj (mesh replaced by the seam-split, UV'd mesh)."""
    import trimesh

    from psimap.exporters import texture as T

    fallback = None
    if vertex_rgb is not None and len(vertex_rgb) == len(original.vertices):
        # colours of the decimated vertices from the nearest original vertex
        from scipy.spatial import cKDTree

        _, idx = cKDTree(np.asarray(original.vertices)).query(np.asarray(m.vertices))
        fallback = vertex_rgb[idx]
    if views:
        fallback = T.vertex_colors_from_views(np.asarray(m.vertices, np.float64), views) if fallback is None \
            else fallback
    try:
        v, f, uv, vmap = T.unwrap(m)
    except Exception:   # xatlas fails on some degenerate charts: colour per vertex instead
        obj.mesh = m
        obj.vertex_rgb = fallback
        obj.texture_source = "vertex" if fallback is not None else "none"
        return
    size = T.texture_size(m, texel)
    fb = None if fallback is None else fallback[vmap]
    if views:
        img, cov = T.bake_from_views(v, f, uv, views, size, fallback_vertex_rgb=fb)
        obj.texture, obj.texture_source, obj.texture_coverage = img, "views", cov
    elif source_textured is not None:
        obj.texture, obj.texture_source, obj.texture_coverage = T.bake_from_mesh(v, f, uv, source_textured, size), \
            "mesh", 1.0
    elif fb is not None:
        rows, cols, fid, bary = T.rasterize_uv(f, uv, size)
        colors = np.einsum("pk,pkd->pd", bary, fb[f[fid]])
        obj.texture, obj.texture_source = T.texel_image(rows, cols, colors, size), "vertex"
    obj.mesh = m
    obj.visual_mesh = trimesh.Trimesh(v, f, process=False)
    obj.uv = uv if obj.texture is not None else None
    obj.vertex_rgb = fb


def extract_objects(scene, *, completion: str = "auto", include_skipped: bool = False,
                    progress: bool = False, **kw) -> list[SceneObject]:
    """One SceneObject per thing instance of a trained scene (psimap.scene.Scene).

    Meshes come from TSDF fusion of the rendered depth masked by the rendered instance id (step 1),
    then go through the asset steps. Skipped objects (Role.SKIPPED) only when include_skipped.
    """
    objs, _, _ = extract_scene(scene, completion=completion, progress=progress, **kw)
    return [o for o in objs if include_skipped or o.role is not Role.SKIPPED]


def extract_scene(scene, *, completion: str = "auto", progress: bool = False, seed: int = 0,
                  timings: dict | None = None, static_classes=None,
                  **kw) -> tuple[list[SceneObject], SceneObject | None, object | None]:
    """(objects incl. skipped ones, background or None, static environment or None) of a trained
    scene (world Z-up: exporters.pipeline.gravity_aligned turns a capture first). timings: a dict that
    receives the seconds of the scene-level steps (instance meshes, consistency, background).
    static_classes: classes exported static (None = physics.STATIC_CLASSES); their colliders may
    use up to STATIC_MAX_HULLS parts.

    Every instance is first made a solid (`prepare_solid`), the solids are made consistent as one
    scene (exporters.consistency: floor cut, overlaps removed, room-sized labels left to the
    background), then finished (`finish_object`: decimation, mass, collider, texture).
    """
    from psimap.threads import single_threaded

    with single_threaded():     # many small renders: spinning thread pools cost more than they give
        return _extract_scene(scene, completion=completion, progress=progress, seed=seed, timings=timings,
                              static_classes=static_classes, **kw)


def _extract_scene(scene, *, completion: str, progress: bool, seed: int, timings: dict | None,
                   static_classes=None, **kw):
    import trimesh
    from tqdm import tqdm

    from psimap.completion import CompletionContext
    from psimap.exporters.consistency import (cut_by_colliders, cut_by_environment, make_consistent,
                                              neighbour_collider_parts)
    from psimap.exporters.environment import (add_support_slabs, add_unseen_supports, flatten_solid, flatten_under,
                                              furniture_tops, static_environment, tops_under_things)
    from psimap.exporters.collision import solid_parts
    from psimap.exporters.instance_meshes import instance_meshes
    from psimap.exporters.physics import is_static_class
    from psimap.exporters.solidify import disc_points

    timings = {} if timings is None else timings
    with clock.step(timings, "instance_meshes"):
        inst = instance_meshes(scene, progress=progress)
    sf = {k: scene.surfels[k].detach().cpu().numpy() for k in ("means", "quats", "scales", "opacities")}
    iid = scene.instance_ids().cpu().numpy()
    t0 = clock.now()
    # the static world first: what the things stand on decides where their bottoms are
    env = static_environment(inst.background, voxel=inst.voxel_size, exclude_points=sf["means"][iid > 0], seed=seed)
    floor_z = env.floor_z if env.floor_observed else None
    tops = {item.instance_id: furniture_tops(item.mesh, voxel=inst.voxel_size) for item in inst.things
            if is_static_class(item.label, static_classes) and item.mesh is not None and len(item.mesh.faces)}
    # levels too little seen from above to be found (a shelf board seen edge-on) where things stand
    movable = [t.mesh for t in inst.things if t.instance_id not in tops and t.mesh is not None and len(t.mesh.faces)]
    for item in inst.things:
        if item.instance_id in tops:
            tops[item.instance_id] += tops_under_things(item.mesh, env.supports + tops[item.instance_id], movable)
    # supports no camera saw (a black counter top), under things standing on nothing observed
    unseen, rests_on = things_on_unseen_supports(inst, env.supports + [s for ts in tops.values() for s in ts],
                                                 set(tops), env.floor_z)
    add_unseen_supports(env, unseen)
    clock.add(timings, "environment", t0)
    objs, views_of, surfels_of = [], {}, {}
    for item in tqdm(inst.things, desc="object solids", disable=not progress, leave=False):
        if item.mesh is None or len(item.mesh.faces) == 0:
            objs.append(SceneObject(item.instance_id, item.label, item.mesh, semantic_id=item.semantic_id))
            objs[-1].skip(Reason.NO_SURFACE, "no surface fused for this instance"
                          + (f": {item.why_empty}" if item.why_empty else ""))
            continue
        views = views_of[item.instance_id] = inst.views_for(item.instance_id)
        members = item.members if item.members is not None else iid == item.instance_id
        support = resting_height(item, env.supports + [s for i, ts in tops.items() if i != item.instance_id
                                                        for s in ts])
        context = CompletionContext(
            background=inst.background, voxel_size=inst.voxel_size,
            support_planes=[] if support is None else [((0.0, 0.0, 1.0), support)],
            neighbours=[t.mesh for t in inst.things if t is not item and t.mesh is not None and len(t.mesh.faces)],
            cameras=[(v.K, v.c2w, v.depth.shape[1], v.depth.shape[0]) for v in views],
            depths=[v.depth for v in views], images=[v.rgb for v in views])
        surfel_points = disc_points(*(sf[k][members] for k in ("means", "quats", "scales", "opacities")))
        objs.append(prepare_solid(item.mesh, item.label, item.instance_id, semantic_id=item.semantic_id,
                                  completion=completion, context=context, support_z=support,
                                  surfel_points=surfel_points, carve_views=inst.views, resolution=inst.voxel_size,
                                  open_under=max((t.height for t in tops.get(item.instance_id, [])), default=None)))
        objs[-1].surfel_count = int(np.count_nonzero(members))
        if item.instance_id in rests_on:
            u = rests_on[item.instance_id]
            u.name = objs[-1].name
            objs[-1].measured.repair_steps.append(
                f"stands on a support no camera saw (a slab inferred at {u.support.height:.3f} m, "
                f"{u.support.area * 1e4:.0f} cm2: nothing observed under it, {u.free_share:.0%} of the views of "
                "the space around its bottom saw it empty)")
        objs[-1].detail = float(getattr(item.mesh, "voxel_size", 0.0) or 0.0)
        surfels_of[item.instance_id] = surfel_points
        if item.dropped_surfels:
            objs[-1].measured.repair_steps.insert(0, f"{item.dropped_surfels} surfels of this label away "
                                                     "from its main body left out")
    t0 = clock.now()
    for o in objs:
        if o.role is not Role.SKIPPED and tops.get(o.instance_id):
            o.mesh, steps = flatten_solid(o.mesh, tops[o.instance_id])
            o.measured.repair_steps += steps
            standing = [t for t in objs if t is not o and t.role is not Role.SKIPPED and t.mesh is not None
                        and not tops.get(t.instance_id)]
            clear_tops(o, tops[o.instance_id], standing)
    make_consistent(objs, floor_z)
    clock.add(timings, "consistency", t0)
    for o in objs:
        if o.role is not Role.SKIPPED and o.instance_id in surfels_of:
            o.measured.coverage = observed_coverage(o.mesh, surfels_of[o.instance_id], tol=1.5 * inst.voxel_size)
    # biggest first: each smaller solid is cut by the colliders already made around it
    finished = []
    order = sorted((o for o in objs if o.role is not Role.SKIPPED),
                   key=lambda o: (-float(o.mesh.volume), o.instance_id))
    for o in tqdm(order, desc="object assets", disable=not progress, leave=False):
        with clock.step(timings, "consistency"):
            cut_by_environment(o, env.colliders)
            cut_by_colliders(o, finished)
        hulls = {"max_hulls": STATIC_MAX_HULLS} if is_static_class(o.label, static_classes) else {}
        world = [c.mesh for c in env.colliders if c.mesh.bounds[1][2] > o.mesh.bounds[0][2] - 0.05
                 and np.all(c.mesh.bounds[0] < o.mesh.bounds[1] + 0.05) and np.all(c.mesh.bounds[1] > o.mesh.bounds[0] - 0.05)]
        hulls_kept_clear = [standing_hull(t.mesh) for t in kept_clear(o, bool(tops.get(o.instance_id)))
                            if t.role is not Role.SKIPPED and t.mesh is not None]
        obstacles = neighbour_collider_parts(o, finished) + world + [h for h in hulls_kept_clear if h is not None]
        finish_object(o, views=views_of.get(o.instance_id), resolution=inst.voxel_size, seed=seed,
                      obstacles=obstacles, **{**kw, **hulls})
        if tops.get(o.instance_id) and o.collision is not None and not o.collision.is_primitive:
            # static furniture: a flat slab is its top, its fused hulls are cut flat under it
            o.collision.parts = solid_parts(flatten_under(o.collision.parts, tops[o.instance_id])) or o.collision.parts
        finished.append(o)
    background = inst.background
    # labels too big to be objects stay in the scene as static background (what they covered is
    # still there to see)
    room_sized = [t.mesh for t, o in zip(inst.things, objs) if o.reason is Reason.ROOM_SIZED and t.mesh is not None]
    if room_sized:
        background = trimesh.util.concatenate([m for m in [background, *room_sized] if m is not None])
        with clock.step(timings, "environment"):
            env = static_environment(background, voxel=inst.voxel_size, exclude_points=sf["means"][iid > 0],
                                     seed=seed)
        add_unseen_supports(env, unseen)
    for o in objs:
        if o.role is not Role.SKIPPED and tops.get(o.instance_id):
            add_support_slabs(env, tops[o.instance_id], o.name)
    bg = None
    with clock.step(timings, "background"):
        if background is not None and len(background.faces):
            bg = build_background(background, views=inst.views, seed=seed)
            if bg.role is Role.SKIPPED:
                bg = None
    return objs, bg, env


def kept_clear(obj: SceneObject, has_tops: bool) -> list:
    """The objects obj's collider keeps clear of: its keep_clear (things seen inside its solid,
    things on its tops) and, unless it is furniture with tops (`has_tops`), the objects its carved
    solid yielded to (yielded_to): clear_tops already clears what stands on a top, and cut back
    around the things beside it, a chess counter's hulls left two of them sliding 2 cm."""
    return obj.keep_clear + ([] if has_tops else obj.yielded_to)      # disjoint: consistency adds to one


def standing_hull(mesh):
    """The closed convex hull of a thing's solid (trimesh) as an obstacle a support's collider keeps
    clear of, marked as standing on it (metadata "stands": collision.clip_convex cuts the part that
    carries it under it, not beside it), or None."""
    from psimap.completion.meshops import closed_convex_hull

    hull = closed_convex_hull(np.asarray(mesh.vertices))
    if hull is not None:
        hull.metadata["stands"] = True
    return hull


def things_on_unseen_supports(inst, known, static_ids, floor_z: float | None) -> tuple[list, dict]:
    """([exporters.environment.UnseenSupport], the same by instance id) of the movable things of
    `inst` (instance_meshes: not in static_ids, the static furniture) that stand on a support no
    camera saw (environment.unseen_supports: nothing observed under them, the space there not seen
    empty by the rendered views' depth). known: the supports found so far."""
    from psimap.completion.freespace import cameras_seeing, check_cameras, free_votes
    from psimap.exporters.environment import unseen_supports

    items = [t for t in inst.things if t.instance_id not in static_ids and t.mesh is not None and len(t.mesh.faces)]
    if not items or not inst.views:
        return [], {}
    cams = check_cameras([(v.K, v.c2w, v.depth.shape[1], v.depth.shape[0]) for v in inst.views],
                         [v.depth for v in inst.views])
    tol = max(0.01, 1.5 * inst.voxel_size)

    def votes(q):
        return free_votes(q, cameras_seeing(cams, q.min(axis=0), q.max(axis=0)), tol)

    index = {id(t): i for i, t in enumerate(items)}         # static furniture: -2, its own owner
    parts = [(inst.background, -1)] + [(t.mesh, index.get(id(t), -2)) for t in inst.things]
    parts = [(m, k) for m, k in parts if m is not None and len(m.faces)]
    surfaces = (np.concatenate([np.asarray(m.triangles_center, np.float64) for m, _ in parts]),
                np.concatenate([np.asarray(m.area_faces, np.float64) for m, _ in parts]),
                np.concatenate([np.asarray(m.face_normals, np.float64) for m, _ in parts]),
                np.concatenate([np.full(len(m.faces), k) for m, k in parts]))
    unseen = unseen_supports([t.mesh for t in items], known, surfaces, votes, floor_z=floor_z)
    return unseen, {items[u.thing].instance_id: u for u in unseen}


def clear_tops(furniture: SceneObject, tops, standing: list) -> None:
    """The space over each of a static furniture's `tops` (exporters.environment Supports) where
    one of `standing` (SceneObjects, not furniture) stands is that thing's: cut out of the
    furniture's solid (environment.clear_above_top), and its collider keeps clear of the thing
    (`keep_clear`): a shelf's hulls spanned the compartment a bottle stood in (9 cm off the
    shelf's solid) and cut half of the bottle away, which then fell off its board."""
    from psimap.exporters.environment import clear_above_top, stands_on

    for top in tops:
        furniture.mesh, steps = clear_above_top(furniture.mesh, top, [t.mesh for t in standing])
        furniture.measured.repair_steps += steps
        furniture.keep_clear += [t for t in standing if stands_on(t.mesh, top) and t not in furniture.keep_clear]


def observed_coverage(mesh, surfel_points: np.ndarray, *, tol: float, samples: int = 3000, seed: int = 0) -> float:
    """Share of a solid's surface (trimesh) the views saw: area samples within `tol` of an observed
    surfel disc (surfel_points [n, 3], exporters.solidify.disc_points), its bottom left out (the
    side an object rests on is never seen; the support decides it). How well an object is known,
    whatever number of surfels happens to represent it."""
    from scipy.spatial import cKDTree

    from psimap.transforms import sample_surface

    if len(surfel_points) == 0 or mesh is None or len(mesh.faces) == 0:
        return 0.0
    pts = sample_surface(mesh, samples, seed)
    lo = float(np.asarray(mesh.bounds)[0, 2])
    pts = pts[pts[:, 2] > lo + tol]
    if len(pts) == 0:
        return 0.0
    d, _ = cKDTree(np.asarray(surfel_points, np.float64)).query(pts, distance_upper_bound=tol)
    return float(np.isfinite(d).mean())


def resting_height(item, supports, max_gap: float = 0.05) -> float | None:
    """Height of the support a fused thing (instance_meshes item) rests on: the highest support
    (exporters.environment) under its plan-view centre within `max_gap` of its fused bottom (which
    sinks into or hovers over what it stands on by a centimetre or two), else of the surfels'
    support level; else that level as it is. Snapped to the support's own plane, object and
    collider meet flat. (The surfels' level alone found the floor under a bottle on a cabinet, and
    a lower shelf board under a bottle on the board above it.)"""
    from psimap.exporters.environment import support_under

    lo, hi = np.asarray(item.mesh.bounds, np.float64)
    centre = 0.5 * (lo[:2] + hi[:2])
    for bottom in (float(lo[2]), item.support_z):
        if bottom is not None:
            s = support_under(supports, centre, bottom, max_gap=max_gap)
            if s is not None:
                return s.height
    return item.support_z


def object_from_scan(path, label: str, instance_id: int, *, place_on_floor: bool = True,
                     offset=(0.0, 0.0, 0.0), **kw) -> SceneObject:
    """A SceneObject from a scanned, textured mesh file (OBJ/PLY/GLB; e.g. a YCB `textured.obj`).

    The colour is transferred from the scan's own texture onto the new UV atlas. place_on_floor
    moves the scan so its lowest point is at z = 0, then by `offset` (metres). Other keyword
    arguments go to build_object (completion defaults to "none": a scan is complete).
    """
    import trimesh

    from psimap import PsimapError

    try:
        src = trimesh.load(str(path), force="mesh", process=False)
    except Exception as e:
        raise PsimapError(f"cannot read mesh {path}: {e}") from None
    if not isinstance(src, trimesh.Trimesh) or len(src.faces) == 0:
        raise PsimapError(f"{path}: no triangles")
    shift = np.asarray(offset, np.float64).copy()
    if place_on_floor:
        shift[2] -= float(src.bounds[0, 2])
    src.apply_translation(shift)
    kw.setdefault("completion", "none")
    return build_object(src, label, instance_id, source_textured=src, **kw)
