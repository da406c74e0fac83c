"""Step 6: collision geometry, the cheapest kind that fits the mesh within a tolerance.

Tried in order: primitive (sphere, box, cylinder) -> one convex hull -> convex decomposition
(CoACD) with a capped hull count. A candidate fits when the symmetric Hausdorff distance between
its surface and the mesh surface is within the tolerance. Every hull has at most 64 vertices
(MuJoCo's and PhysX's comfortable limit), reduced by quadric simplification of the hull.
Primitives matter: a ball whose collider is the convex hull of its faceted mesh rolls away on a
level floor; as a sphere primitive it stays put.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psimap.transforms import sample_surface

MAX_HULL_VERTICES = 64


@dataclass
class Collision:
    kind: str                      # "sphere" | "box" | "cylinder" | "hull" | "decomposition"
    error: float                   # metres, symmetric Hausdorff distance collider <-> mesh
    tolerance: float               # metres
    # primitives: MJCF-style size (sphere [r], box [hx, hy, hz], cylinder [r, half-height]) and
    # its pose in the world: transform [4, 4] (cylinder axis = local z)
    size: np.ndarray | None = None
    transform: np.ndarray | None = None
    parts: list = field(default_factory=list)   # convex trimesh parts (world frame); primitives too

    @property
    def is_primitive(self) -> bool:
        return self.kind in ("sphere", "box", "cylinder")

    @property
    def hull_count(self) -> int:
        return 0 if self.is_primitive else len(self.parts)


# Primitive fits whose errors differ by less than this (m) are equally good: the smaller one wins.
PRIMITIVE_ERROR_STEP = 1e-3


# a convex collider part thinner than this (m) is a sliver MuJoCo cannot take (`is_solid_part`)
MIN_PART_THICKNESS = 5e-4
# a resting cylinder collider must stand within 10 degrees of upright (collision_geometry)
UPRIGHT_COS = float(np.cos(np.radians(10.0)))


def default_tolerance(mesh, relative: float = 0.03, floor: float = 0.003) -> float:
    """3 % of the bounding-box diagonal, at least 3 mm: below what a gripper or a settle notices."""
    return max(floor, relative * float(np.linalg.norm(mesh.extents)))


# ---------------------------------------------------------------- distances
def _primitive_sdf(kind: str, size: np.ndarray, transform: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Unsigned distance of world points [P, 3] to the primitive's surface."""
    local = (pts - transform[:3, 3]) @ transform[:3, :3]
    if kind == "sphere":
        return np.abs(np.linalg.norm(local, axis=1) - size[0])
    if kind == "box":
        q = np.abs(local) - size
        outside = np.linalg.norm(np.maximum(q, 0), axis=1)
        inside = np.minimum(q.max(axis=1), 0)
        return np.abs(outside + inside)
    if kind == "cylinder":
        d = np.stack([np.linalg.norm(local[:, :2], axis=1) - size[0], np.abs(local[:, 2]) - size[1]], 1)
        outside = np.linalg.norm(np.maximum(d, 0), axis=1)
        inside = np.minimum(d.max(axis=1), 0)
        return np.abs(outside + inside)
    raise ValueError(kind)


def primitive_mesh(kind: str, size: np.ndarray, transform: np.ndarray):
    """A trimesh of the primitive (world frame) for writers that want geometry (GLB preview)."""
    import trimesh

    if kind == "sphere":
        m = trimesh.creation.icosphere(subdivisions=2, radius=float(size[0]))
    elif kind == "box":
        m = trimesh.creation.box(extents=2 * np.asarray(size, float))
    else:
        m = trimesh.creation.cylinder(radius=float(size[0]), height=2 * float(size[1]), sections=32)
    m.apply_transform(transform)
    return m


def _two_sided(mesh_pts: np.ndarray, coll_pts: np.ndarray, mesh_dist, coll_dist) -> float:
    return float(max(coll_dist(mesh_pts).max(), mesh_dist(coll_pts).max()))


# ---------------------------------------------------------------- primitive fits
def _fit_primitives(mesh) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Candidate (kind, size, transform) primitives around the mesh (float64)."""
    import trimesh

    v = np.asarray(mesh.vertices, np.float64)
    out = []
    # sphere: least-squares centre, mean radius
    try:
        center, radius, _ = trimesh.nsphere.fit_nsphere(v)
        T = np.eye(4)
        T[:3, 3] = center
        out.append(("sphere", np.array([radius]), T))
    except Exception:
        pass
    # box: minimum-volume oriented bounding box
    to_origin, extents = trimesh.bounds.oriented_bounds(mesh)
    T = np.linalg.inv(to_origin)
    out.append(("box", np.asarray(extents, float) / 2, T))
    # cylinder: each OBB axis as candidate axis, circle fitted in the cross-section
    for axis in range(3):
        R = T[:3, :3].copy()
        perm = [(axis + 1) % 3, (axis + 2) % 3, axis]
        R = R[:, perm]
        if np.linalg.det(R) < 0:
            R[:, 0] *= -1
        local = (v - T[:3, 3]) @ R
        try:
            c2, r, _ = trimesh.nsphere.fit_nsphere(local[:, :2])
        except Exception:
            continue
        zmin, zmax = local[:, 2].min(), local[:, 2].max()
        Tc = np.eye(4)
        Tc[:3, :3] = R
        Tc[:3, 3] = T[:3, 3] + R @ np.array([c2[0], c2[1], 0.5 * (zmin + zmax)])
        out.append(("cylinder", np.array([r, 0.5 * (zmax - zmin)]), Tc))
    return out


# ---------------------------------------------------------------- hulls
def limit_hull_vertices(part, max_vertices: int = MAX_HULL_VERTICES):
    """Convex hull of `part` with at most `max_vertices` vertices (quadric-simplified hull)."""
    import trimesh

    hull = part.convex_hull
    target = 2 * max_vertices - 4           # triangulated closed convex: F = 2V - 4
    while len(hull.vertices) > max_vertices:
        import fast_simplification

        v, f = fast_simplification.simplify(np.asarray(hull.vertices, np.float64),
                                            np.asarray(hull.faces, np.int32), target_count=target)
        new = trimesh.convex.convex_hull(v)
        if len(new.vertices) >= len(hull.vertices):   # no progress: keep the most extreme vertices
            idx = _farthest_points(np.asarray(hull.vertices), max_vertices)
            new = trimesh.convex.convex_hull(np.asarray(hull.vertices)[idx])
        hull = new
        target = max(8, int(target * 0.8))
    return hull


def _farthest_points(p: np.ndarray, k: int) -> np.ndarray:
    c = p.mean(axis=0)
    idx = [int(np.argmax(np.linalg.norm(p - c, axis=1)))]
    d = np.linalg.norm(p - p[idx[0]], axis=1)
    for _ in range(1, k):
        i = int(np.argmax(d))
        idx.append(i)
        d = np.minimum(d, np.linalg.norm(p - p[i], axis=1))
    return np.array(sorted(idx))


def _inside_convex(hull, pts: np.ndarray, margin: float = 1e-9) -> np.ndarray:
    """[P] bool: points inside a convex hull (all face planes' negative side, within margin)."""
    n = np.asarray(hull.face_normals, np.float64)
    o = np.asarray(hull.triangles[:, 0], np.float64)
    return ((pts @ n.T) - np.einsum("fd,fd->f", n, o) <= margin).all(axis=1)


# ---------------------------------------------------------------- neighbours' colliders
def convex_overlap(a, b) -> tuple[float, np.ndarray]:
    """(depth, axis) of two convex meshes by the separating-axis test over both face normals:
    depth <= 0 means separated; else the smallest overlap found and the unit axis along which `a`
    leaves `b` (pointing from b towards a). Edge-edge axes are left out, so depth can exceed the
    true penetration (never miss it: a zero overlap on a face axis proves separation)."""
    va, vb = np.asarray(a.vertices, np.float64), np.asarray(b.vertices, np.float64)
    axes = np.concatenate([np.asarray(a.face_normals, np.float64), np.asarray(b.face_normals, np.float64)])
    pa, pb = va @ axes.T, vb @ axes.T                         # [Va, A], [Vb, A]
    up = pb.max(0) - pa.min(0)                                # a pushed along +axis
    down = pa.max(0) - pb.min(0)                              # a pushed along -axis
    k_up, k_down = int(np.argmin(up)), int(np.argmin(down))
    if up[k_up] <= down[k_down]:
        return float(up[k_up]), axes[k_up]
    return float(down[k_down]), -axes[k_down]


STAND_BAND = 0.01       # m: a standing thing's vertices this close to its lowest are its bottom


def clip_convex(part, obstacles, clearance: float = 5e-4, max_penetration: float = 1e-3):
    """`part` (convex trimesh) cut back, one plane per obstacle it enters by more than
    max_penetration, to `clearance` outside that obstacle along the axis of least overlap (under
    it, when the obstacle is a thing standing on the part: metadata "stands"): the result stays
    convex and clears every obstacle. None when nothing of it is left."""
    for ob in obstacles:
        depth, axis = convex_overlap(part, ob)
        if depth <= max_penetration:
            continue
        if ob.metadata.get("stands") and abs(float(axis[2])) < 0.7:
            # a thing that stands on this collider (SceneObject.keep_clear): if the part holds a
            # point just under its bottom (its lowest vertices, their centre), it carries the
            # thing, and a cut beside it leaves the thing on nothing or on an edge (a chess
            # object's hulls cut back sideways dropped two things 80 cm); cut under it instead
            v = np.asarray(ob.vertices, np.float64)
            below = v[v[:, 2] <= v[:, 2].min() + STAND_BAND]
            below = np.concatenate([below, below.mean(axis=0, keepdims=True)])
            below[:, 2] = v[:, 2].min() - 2 * clearance
            if _inside_convex(part, below).any():
                axis = np.array([0.0, 0.0, -1.0])
        level = float((np.asarray(ob.vertices, np.float64) @ axis).max()) + clearance
        part = clip_halfspace(part, axis, level)
        if part is None or part.volume <= 0:
            return None
    return part


def clip_halfspace(part, normal: np.ndarray, level: float):
    """Convex `part` ∩ {x : normal·x >= level} as a convex hull (None when no volume is left): the
    kept vertices plus where the part's edges cross the plane."""
    import trimesh

    v = np.asarray(part.vertices, np.float64)
    h = v @ normal - level                                   # [V] signed height over the plane
    e = np.asarray(part.edges_unique)
    ha, hb = h[e[:, 0]], h[e[:, 1]]
    cross = (ha > 0) != (hb > 0)
    t = (ha[cross] / (ha[cross] - hb[cross]))[:, None]
    ring = v[e[cross, 0]] + t * (v[e[cross, 1]] - v[e[cross, 0]])
    pts = np.concatenate([v[h >= 0], ring])
    if len(pts) < 4 or not is_solid_part(pts):
        return None
    try:
        return trimesh.convex.convex_hull(pts)
    except Exception:        # a sliver: qhull finds no volume
        return None


def is_solid_part(points, min_thickness: float = MIN_PART_THICKNESS) -> bool:
    """Whether convex points [n, 3] span at least `min_thickness` (m) along their thinnest principal
    axis: MuJoCo refuses a mesh of coplanar vertices ("cannot compute convex hull") and the whole
    scene with it (a shelf part clipped flat at a board stopped `psimap demo`)."""
    p = np.asarray(points, np.float64)
    if len(p) < 4 or not np.isfinite(p).all():
        return False
    c = p - p.mean(axis=0)
    axis = np.linalg.svd(c, full_matrices=False)[2][-1]
    return float(np.ptp(c @ axis)) >= min_thickness


def solid_parts(parts, min_thickness: float = MIN_PART_THICKNESS) -> list:
    """The convex parts [trimesh] that are solid (`is_solid_part`); flat ones are dropped."""
    return [q for q in parts if q is not None and is_solid_part(q.vertices, min_thickness)]


def penetrates(parts, obstacles, max_penetration: float = 1e-3) -> bool:
    return any(convex_overlap(p, ob)[0] > max_penetration for p in parts for ob in obstacles)


# CoACD settings chosen for speed on a 2-core CPU (benchmarks/export.py, collider table): the
# decimated copy and the short tree search cost ~0.1-1 s per call where the library defaults
# (resolution 2000, 150 MCTS iterations, preprocessing) cost tens of seconds; the fit is measured
# afterwards against the full mesh, so a coarse call can only lose to the hull, never pass falsely.
COACD_FACES = 600
BUDGET_DIAGONAL = 0.5           # m: larger objects get proportionally more CoACD faces and time
COACD_OPTIONS = {"preprocess_mode": "off", "resolution": 300, "mcts_iterations": 12, "mcts_nodes": 8,
                 "mcts_max_depth": 2}


def _coacd(mesh, threshold: float, max_hulls: int, seed: int, max_faces: int = COACD_FACES):
    import coacd
    import trimesh

    src = mesh
    if len(src.faces) > max_faces:      # CoACD's cost grows with faces; the fit tolerance is coarser
        from psimap.exporters.decimate import simplify_to_count

        src = simplify_to_count(mesh, max_faces)
    try:
        coacd.set_log_level("error")
    except Exception:
        pass
    parts = coacd.run_coacd(coacd.Mesh(np.asarray(src.vertices, np.float64), np.asarray(src.faces, np.int64)),
                            threshold=threshold, max_convex_hull=max_hulls, seed=seed,
                            max_ch_vertex=MAX_HULL_VERTICES, **COACD_OPTIONS)
    out = [trimesh.Trimesh(np.asarray(v), np.asarray(f), process=True) for v, f in parts]
    return [p for p in out if len(p.faces) >= 4]


def collision_geometry(mesh, tolerance: float | None = None, *, max_hulls: int = 8,
                       allow_primitives: bool = True, samples: int = 4000, seed: int = 0,
                       coacd_thresholds: tuple[float, ...] = (0.3, 0.15, 0.08),
                       time_budget: float = 4.0, obstacles=(), max_penetration: float = 1e-3,
                       resting: bool = False) -> Collision:
    """The cheapest collider within `tolerance` (metres) of `mesh` (watertight trimesh, world frame).

    Cascade: primitive -> one convex hull -> CoACD, the last only when the hull misses the
    tolerance, with ever finer concavity thresholds while `time_budget` CPU seconds of the CoACD
    calls (per object up to BUDGET_DIAGONAL across, proportionally more for larger ones, up to 4x)
    last: CoACD's own CPU time, not wall time nor the whole process's, so a busy machine gets the
    colliders an idle one gets (one call took 5.1 CPU s at load 11 and 5.2 at load 6, but 7.5 s
    wall at load 11; the room exported with two busy loops beside it: the same report).
    When nothing fits, the best collider found (at most `max_hulls` hulls) is returned with its
    measured error; the report shows it.
    obstacles: convex trimesh parts of neighbours' colliders (world frame) this one must not enter
    by more than max_penetration: a primitive that would is not a candidate, hulls are cut back
    (`clip_convex`). Two colliders each within tolerance of meshes that touch can overlap by the
    sum of the tolerances, and the simulation throws them apart.
    resting: the object stands on a support (Z-up): a cylinder lying on its side is no candidate.
    It rolls about its axis unless the centre of mass lies on it, and a reconstructed apple fits
    one within tolerance (its centre of mass a few millimetres off: it rolled 10 cm and was pinned).
    """
    import time

    # furniture is what everything else rests on: a 1.6 m table decimated to the small objects' 600
    # faces for CoACD lost its top under a box by up to 4 cm (its hulls ended 0.649-0.696 m where
    # the top is 0.69-0.708 m; 0.709-0.714 m from 2400 faces, at the same CoACD time), and the box
    # fell: larger objects get proportionally more faces and time
    scale = float(np.clip(np.linalg.norm(mesh.extents) / BUDGET_DIAGONAL, 1.0, 4.0))
    time_budget *= scale
    from psimap.exporters.decimate import distance_to_surface

    tol = default_tolerance(mesh) if tolerance is None else float(tolerance)
    mesh_pts = sample_surface(mesh, samples, seed, with_vertices=True)

    def mesh_dist(p):
        return distance_to_surface(mesh, p)

    if allow_primitives:
        best = None
        for kind, size, T in _fit_primitives(mesh):
            if not np.all(np.isfinite(size)) or np.any(size <= 0):
                continue
            if resting and kind == "cylinder" and abs(float(T[2, 2])) < UPRIGHT_COS:
                continue
            pm = primitive_mesh(kind, size, T)
            err = _two_sided(mesh_pts, sample_surface(pm, samples, seed + 1, with_vertices=True), mesh_dist,
                             lambda p: _primitive_sdf(kind, size, T, p))
            vol = float(pm.volume)
            if obstacles and err <= tol and penetrates([pm], obstacles, max_penetration):
                continue
            # the primitive that follows the surface best (a reconstructed ball also fits a cylinder
            # within tolerance, one lying on its side that rolls off its support); volume breaks ties
            key = (round(err / PRIMITIVE_ERROR_STEP), vol)
            if err <= tol and (best is None or key < best[0]):
                best = (key, kind, size, T, err)
        if best is not None:
            _, kind, size, T, err = best
            return Collision(kind, err, tol, size=size, transform=T, parts=[primitive_mesh(kind, size, T)])

    def parts_error(parts):
        # collider surface = union surface: a part's samples inside another part are interior
        union = []
        for i, p in enumerate(parts):
            pts = sample_surface(p, max(200, samples // len(parts)), seed + 2 + i, with_vertices=True)
            for j, q in enumerate(parts):
                if j != i:
                    pts = pts[~_inside_convex(q, pts, 1e-5)]   # shared faces are interior
            union.append(pts)
        union_pts = np.concatenate(union)
        d = np.full(len(mesh_pts), np.inf)
        for p in parts:
            d = np.minimum(d, distance_to_surface(p, mesh_pts))
        if len(parts) > 1:          # mesh points inside the union are covered
            inside = np.zeros(len(mesh_pts), bool)
            for p in parts:
                inside |= _inside_convex(p, mesh_pts)
            d[inside] = 0.0
        coll_to_mesh = mesh_dist(union_pts).max() if len(union_pts) else 0.0
        return float(max(d.max(), coll_to_mesh))

    def clipped(parts):
        if not obstacles:
            return parts
        out = []
        for p in parts:
            for _ in range(3):      # a cut adds vertices; reducing them can move the cut a little
                p = clip_convex(p, obstacles, max_penetration=max_penetration)
                if p is None or len(p.vertices) <= MAX_HULL_VERTICES:
                    break
                p = limit_hull_vertices(p)
            if p is not None:
                out.append(p)
        return out

    hull = clipped([limit_hull_vertices(mesh)])
    if not hull:        # the neighbours' colliders cover it: keep its own hull (reported error)
        hull = [limit_hull_vertices(mesh)]
    hull = hull[0]
    err = parts_error([hull])
    if err <= tol:
        return Collision("hull", err, tol, parts=[hull])
    best = Collision("hull", err, tol, parts=[hull])
    last = spent = 0.0
    for thr in coacd_thresholds:
        # a finer threshold costs ~3-4x the previous call (measured on 10 fused objects): start
        # it only when it can end within the budget. The budget counts the CoACD calls' own CPU
        # time: the process's CPU time between them (distances, clipping) grows on a busy machine
        # with the worker threads of numpy's and Open3D's pools waiting for a core, and the same
        # checkpoint exported under load stopped earlier and got other colliders
        if time_budget <= 0 or spent + 3.0 * last > time_budget:
            break
        t_call = time.process_time()
        raw = _coacd(mesh, thr, max_hulls, seed, max_faces=int(COACD_FACES * scale))
        last = time.process_time() - t_call
        spent += last
        parts = clipped([limit_hull_vertices(p) for p in raw])
        if not parts:
            continue
        err = parts_error(parts)
        if err < best.error:
            best = Collision("decomposition" if len(parts) > 1 else "hull", err, tol, parts=parts)
        if err <= tol or len(raw) >= max_hulls:
            break       # fits, or the hull cap already binds: a finer threshold cannot add parts
    return best
