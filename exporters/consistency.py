"""Step 3b: make the prepared object solids consistent with each other as one scene.

A trained panoptic map is imperfect: an instance can swallow part of its neighbour (a bottle
merged into the table it stands on), fused solids of touching objects overlap by the TSDF's
blur, a solid can reach below the floor, and a label can spread over the room. Simulated as they
are, overlapping solids start 10 cm deep in each other and the solver throws them apart. Here,
before decimation and colliders:
- the floor: everything below the background's floor plane is cut off (manifold3d);
- overlaps: where two solids intersect, the larger one keeps the shared volume and it is cut out of
  the smaller one (a small object is what stands on or leans against the big one); an object left
  with under `min_keep` of its volume was inside the other and is skipped. Except a carved solid
  (exporters.solidify: everything no view saw through, an upper bound) yields to one built from its
  own observed surface: a table carved around the box standing on it holds the box's lower half;
  cut from the box instead, the box hovers over the table's collider and falls. And a solid that
  would swallow a smaller object whose own observed surface lies deep inside it (a shelf closed
  as a voxel solid fills the compartment a mug stands in) yields too: a camera saw that surface,
  so the fill is wrong there. It gives up the shared space (or, the object wholly inside, stays
  whole: the difference would be a cavity) and its collider is built to clear the object
  (`SceneObject.keep_clear`; a carved solid that yielded clears the object too, `yielded_to`:
  finished first, its hulls would span the notch again; static furniture keeps its collider clear
  of every thing standing on one of its tops, `exporters.objects.clear_tops`);
- room-sized instances: an "object" wider than `max_extent` is not an object a robot moves (a
  merged label of many things, or furniture fused with the room) and is skipped with the reason.
Then, while the objects are finished biggest first, each solid is cut by the colliders of the
bigger ones already finished (`cut_by_colliders`): convex hulls span hollows their meshes leave.
Every change is recorded in the object's repair steps and so in report.json.
"""
from __future__ import annotations

import numpy as np

from psimap.completion.meshops import closed_convex_hull, is_closed, signed_volume, to_manifold
from psimap.exporters.roles import Reason, Role

# an object this much wider than the largest thing class a robot moves (a table: ~2 m) is not one
MAX_EXTENT = 2.5
MIN_KEEP = 0.25                 # volume fraction an object must keep after an overlap cut
MIN_OVERLAP = 1e-7              # m^3 (0.1 cm^3): intersections smaller than this are rounding
# another object's observed surface this deep inside a solid (and two of its voxels) says the
# solid's fill is wrong there (holds_observed_surface)
OBSERVED_DEPTH = 0.01


def floor_from_background(background) -> float | None:
    """Height (world z) of the largest up-facing horizontal surface of the background mesh (the
    floor of a room), or None when it has none."""
    if background is None or len(background.faces) == 0:
        return None
    up = np.asarray(background.face_normals)[:, 2] > 0.9
    if not up.any():
        return None
    zc = np.asarray(background.triangles_center)[up, 2]
    area = np.asarray(background.area_faces)[up]
    bins = max(8, int((zc.max() - zc.min()) / 0.01) + 1)
    hist, edges = np.histogram(zc, bins=bins, weights=area)
    k = int(hist.argmax())
    sel = (zc >= edges[k]) & (zc <= edges[k + 1])
    return float(np.average(zc[sel], weights=area[sel]))


def _to_trimesh(man):
    import trimesh

    m = man.to_mesh()
    # manifold's output is already indexed: re-merging vertices by distance could pinch it
    out = trimesh.Trimesh(np.asarray(m.vert_properties, np.float64)[:, :3], np.asarray(m.tri_verts),
                          process=False)
    if len(out.faces):
        parts = out.split(only_watertight=True)
        if len(parts) > 1:      # a cut can leave crumbs: the object is its largest piece
            out = largest_piece(parts)
    return out


def largest_piece(parts):
    """The part of largest volume of watertight trimesh parts. The volume alone (signed_volume):
    trimesh's `volume` computes every mass property, and a flat crumb's centre of mass divides by
    its zero volume (a RuntimeWarning on the console of a 7-Scenes export)."""
    return max(parts, key=lambda p: signed_volume(p.vertices, p.faces))


def make_consistent(objects, floor_z: float | None = None, *, max_extent: float = MAX_EXTENT,
                    min_keep: float = MIN_KEEP) -> None:
    """Edit prepared SceneObjects (obj.mesh = watertight solid) in place: cut at the floor, remove
    overlaps, skip room-sized and swallowed ones. Objects already skipped are left alone."""
    import manifold3d

    live = [o for o in objects if o.role is not Role.SKIPPED]
    for o in live:
        ext = np.asarray(o.mesh.extents, np.float64)
        if float(ext[:2].max()) > max_extent:
            o.skip(Reason.ROOM_SIZED, f"spans {ext[:2].max():.1f} m (> {max_extent:.1f} m): a merged or "
                                      "room-sized label, not an object; left to the static background")
    live = [o for o in live if o.role is not Role.SKIPPED]
    if floor_z is not None:
        for o in live:
            depth = float(floor_z - o.mesh.bounds[0, 2])
            if depth <= 1e-3:
                continue
            lo, hi = np.asarray(o.mesh.bounds, np.float64)
            span = hi - lo
            keep = manifold3d.Manifold.cube(list(span + 0.2), False).translate(
                [float(lo[0] - 0.1), float(lo[1] - 0.1), float(floor_z)])
            cut = _to_trimesh(to_manifold(o.mesh) ^ keep)
            _apply_cut(o, cut, min_keep, f"cut at the floor ({depth * 1000:.0f} mm below it)",
                       "below the floor")
    live = [o for o in live if o.role is not Role.SKIPPED]
    # big first: each solid keeps what it shares with every smaller one
    live.sort(key=lambda o: (-float(o.mesh.volume), o.instance_id))
    for i, big in enumerate(live):
        if big.role is Role.SKIPPED:
            continue
        for small in live[i + 1:]:
            if small.role is Role.SKIPPED or not _boxes_overlap(big.mesh.bounds, small.mesh.bounds):
                continue
            a, b = to_manifold(big.mesh), to_manifold(small.mesh)
            shared = float((a ^ b).volume())
            if shared < MIN_OVERLAP:
                continue
            keeper, loser, ka, kb = big, small, a, b
            if big.solid_kind == "carved" and small.solid_kind != "carved":
                keeper, loser, ka, kb = small, big, b, a
            cut = _to_trimesh(kb - ka)
            if keeper is big and not _keeps_enough(small, cut, min_keep) and holds_observed_surface(big, small):
                # big's solid fills space where small's own surface was seen (a shelf closed as a
                # voxel solid around the mug on its board): the fill is wrong there, big yields,
                # and its collider must clear small too (exporters.objects)
                yielded = _to_trimesh(a - b)
                if _keeps_enough(big, yielded, min_keep):
                    big.keep_clear.append(small)
                    if float(big.mesh.volume) - float(yielded.volume) < MIN_OVERLAP:
                        # small wholly inside: the difference is a cavity, which the solid's largest
                        # piece (_to_trimesh) leaves out; the solid stays whole, the collider clears
                        big.measured.repair_steps.append(
                            f"holds {small.name} inside ({shared * 1e6:.1f} cm3): its collider keeps clear of it")
                        continue
                    keeper, loser, ka, kb, cut = small, big, b, a, yielded
            _apply_cut(loser, cut, min_keep,
                       f"overlap with {keeper.name} removed ({shared * 1e6:.1f} cm3)", f"inside {keeper.name}")
            if keeper is small and loser.role is not Role.SKIPPED and small not in big.keep_clear:
                # big gave up the space, and it is finished (its collider made) before small: its
                # convex hulls would span the notch again and swallow small (a carved chess-scene
                # object left two observed ones 0-1 % of their volume)
                big.yielded_to.append(small)
            if big.role is Role.SKIPPED:
                break


def holds_observed_surface(solid_obj, other, share: float = 0.5, depth: float = OBSERVED_DEPTH) -> bool:
    """Whether more than `share` of `other`'s observed surface (the vertices of its source scan)
    lies inside solid_obj's solid deeper than `depth` and two of its voxels: a camera saw that
    surface, so the solid cannot fill that space. A label fragment on the solid's own surface lies
    within a voxel of it; False when `other` has no source scan."""
    from psimap.completion.meshops import distance_to_surface, inside, raycasting_scene

    src = other.source
    pts = np.asarray(getattr(src, "vertices", np.zeros((0, 3))), np.float64)
    if len(pts) == 0 or solid_obj.mesh is None or len(solid_obj.mesh.faces) == 0:
        return False
    if len(pts) > 4000:         # a fixed subsample: a share needs no more
        pts = pts[np.linspace(0, len(pts) - 1, 4000).astype(np.int64)]
    scene = raycasting_scene(solid_obj.mesh)
    deep = inside(pts, solid_obj.mesh, scene)
    if not deep.any():
        return False
    deep &= distance_to_surface(pts, solid_obj.mesh, scene) > max(depth, 2.0 * solid_obj.solid_pitch)
    return bool(deep.mean() > share)


def _keeps_enough(obj, cut, min_keep: float) -> bool:
    return bool(len(cut.faces) and cut.is_watertight and cut.volume >= min_keep * float(obj.mesh.volume))


def _apply_cut(obj, cut, min_keep: float, step: str, swallowed: str) -> None:
    before = float(obj.mesh.volume)
    if not _keeps_enough(obj, cut, min_keep):
        kept = 0.0 if len(cut.faces) == 0 else float(cut.volume) / before
        obj.skip(Reason.SWALLOWED, f"{swallowed}: {kept * 100:.0f} % of its volume left after the cut")
        return
    obj.mesh = cut
    obj.measured.repair_steps.append(step)


def _boxes_overlap(b1, b2, pad: float = 0.0) -> bool:
    b1, b2 = np.asarray(b1), np.asarray(b2)
    return bool(np.all(b1[0] - pad <= b2[1]) and np.all(b2[0] - pad <= b1[1]))


def cut_by_colliders(obj, finished) -> None:
    """Cut the prepared solid `obj` by the colliders of the already finished (bigger) objects
    whose boxes it overlaps: the simulation sees convex hulls, and a hull spans the hollows of its
    mesh (a cabinet's hull covers the dent a box on it left), so a solid that clears the other's
    mesh can still start centimetres inside its collider."""
    if obj.role is Role.SKIPPED:
        return
    for other in finished:
        if (other.role is Role.SKIPPED or other.collision is None
                or not _boxes_overlap(other.mesh.bounds, obj.mesh.bounds, pad=0.01)):
            continue
        _cut_by_parts(obj, other.collision.parts, f"the collider of {other.name}")
        if obj.role is Role.SKIPPED:
            return


def cut_by_environment(obj, colliders) -> None:
    """Cut the prepared solid `obj` by the static world's colliders (exporters.environment) it
    overlaps: a thing's underside and back are never seen, and a solid carved from the views' free
    space reaches into the unlabelled ramp or the wall it stands against; the world keeps its volume."""
    if obj.role is Role.SKIPPED:
        return
    near = [c for c in colliders if _boxes_overlap(c.mesh.bounds, obj.mesh.bounds, pad=0.005)]
    for c in near:
        _cut_by_parts(obj, [c.mesh], f"the static world ({c.name})")
        if obj.role is Role.SKIPPED:
            return


def _cut_by_parts(obj, parts, what: str) -> None:
    """obj's solid minus the union of convex `parts` (when they share more than MIN_OVERLAP), the
    cut recorded in its repair steps; skipped when less than MIN_KEEP of it is left."""
    import manifold3d

    # the parts are convex: one left open by its hull is closed again rather than skipped
    hulls = [to_manifold(p if is_closed(p) else closed_convex_hull(p.vertices)) for p in parts if len(p.faces) >= 4]
    hulls = [h for h in hulls if not h.is_empty()]
    if not hulls:
        return
    union = manifold3d.Manifold.batch_boolean(hulls, manifold3d.OpType.Add) if len(hulls) > 1 else hulls[0]
    a = to_manifold(obj.mesh)
    shared = float((a ^ union).volume())
    if shared < MIN_OVERLAP:
        return
    _apply_cut(obj, _to_trimesh(a - union), MIN_KEEP, f"cut by {what} ({shared * 1e6:.1f} cm3)", f"inside {what}")


def neighbour_collider_parts(obj, finished, pad: float = 0.05) -> list:
    """Convex collider parts of the finished objects whose boxes come within `pad` of obj's: what
    obj's own collider must not enter (collision.collision_geometry's obstacles)."""
    if obj.role is Role.SKIPPED:
        return []
    return [p for other in finished
            if other.role is not Role.SKIPPED and other.collision is not None
            and _boxes_overlap(other.mesh.bounds, obj.mesh.bounds, pad=pad)
            for p in other.collision.parts if len(p.faces) >= 4]
