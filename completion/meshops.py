"""Mesh and voxel helpers shared by the completion methods.

Exact booleans go through manifold3d (watertight inputs), distances and inside tests through
Open3D's RaycastingScene, and voxel occupancy becomes a closed surface through VTK's contouring
(pyvista). Heavy imports stay inside the functions.
"""
from __future__ import annotations

import numpy as np

from psimap import transforms


def as_trimesh(vertices: np.ndarray, faces: np.ndarray):
    import trimesh

    return trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64),
                           process=True)


def is_solid(mesh) -> bool:
    """A closed, consistently wound mesh with positive volume (what a boolean can use)."""
    return mesh is not None and len(mesh.faces) >= 4 and bool(mesh.is_watertight) \
        and bool(mesh.is_winding_consistent) and float(mesh.volume) > 0


def faces_closed(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Whether every edge of the faces that are triangles (no repeated index, which manifold3d
    ignores) has exactly one face on each side: each directed edge once, its reverse once (closed,
    consistently wound). Vertices are not merged by position: manifold3d does not merge them either."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    tri = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    if len(tri) < 4 or int(f.max()) >= len(vertices):
        return False
    n = np.int64(len(vertices))
    a, b = tri.reshape(-1), tri[:, [1, 2, 0]].reshape(-1)
    fwd = np.sort(a * n + b)
    if np.any(fwd[1:] == fwd[:-1]):             # an edge walked twice one way: non-manifold or mis-wound
        return False
    if not np.all(np.isin(b * n + a, fwd)):     # an edge with no face on its other side: open
        return False
    return True


def is_closed(mesh) -> bool:
    """`faces_closed` holds for the trimesh `mesh` (what manifold3d needs). trimesh's watertight
    and consistently wound flags (cached on the mesh, and most meshes here have been asked already)
    imply it; only a mesh they reject (a repeated-index face, or truly open) is checked in full."""
    if mesh is None or len(mesh.faces) < 4:
        return False
    if bool(mesh.is_watertight) and bool(mesh.is_winding_consistent):
        return int(np.max(mesh.faces)) < len(mesh.vertices)
    return faces_closed(mesh.vertices, mesh.faces)


def to_manifold(mesh):
    """trimesh -> manifold3d.Manifold; an empty Manifold when the mesh is not closed (`is_closed`).
    manifold3d reads every edge's paired half-edge and does not check that one exists: an edge with
    one face made it read outside its arrays, a segfault or not as memory lay (the room export
    crashed in `Impl::IsManifold` on a convex collider part whose trimesh hull was left open).
    Kept on the mesh (cached_on; a Manifold is immutable): a room export converted 454 meshes, 153
    of them again."""
    return cached_on(mesh, "psimap.manifold", lambda: _build_manifold(mesh))


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Volume (m3) a closed mesh (vertices [V, 3], faces [F, 3]) encloses, negative when its faces
    wind inward: the sum of its triangles' triple products / 6, taken from a point near the mesh
    (as exporters.physics' integrals: small float64 cancellation far from the origin). Where only
    the sign or the volume is asked: trimesh's `volume` computes all the mass properties (0.84 s
    of a room export's 297 conversions to manifold3d)."""
    v = np.asarray(vertices, np.float64)
    if len(v) == 0 or len(faces) == 0:
        return 0.0
    t = (v - v.mean(axis=0))[np.asarray(faces)]
    return float(np.einsum("ij,ij->", t[:, 0], np.cross(t[:, 1], t[:, 2]))) / 6.0


def _build_manifold(mesh):
    import manifold3d

    if not is_closed(mesh):
        return manifold3d.Manifold()
    v = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
    f = np.ascontiguousarray(mesh.faces, dtype=np.uint32)
    if signed_volume(mesh.vertices, mesh.faces) < 0:     # inside-out input: flip so the boolean sees the right solid
        f = np.ascontiguousarray(f[:, ::-1])
    return manifold3d.Manifold(manifold3d.Mesh(vert_properties=v, tri_verts=f))


def closed_convex_hull(points: np.ndarray):
    """The convex hull of points [P, 3] as a closed trimesh (qhull's facets, wound outward; None for
    fewer than 4 points or a flat set). trimesh.convex.convex_hull merges and drops qhull's sliver
    facets and can leave the hull open (a 38-point collider part: 71 faces, 3 edges with one face)."""
    import trimesh
    from scipy.spatial import ConvexHull, QhullError

    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 4:
        return None
    try:
        hull = ConvexHull(pts)
    except QhullError:
        return None
    faces = hull.simplices.copy()
    centre = pts[hull.vertices].mean(0)
    normal = np.cross(pts[faces[:, 1]] - pts[faces[:, 0]], pts[faces[:, 2]] - pts[faces[:, 0]])
    inward = (normal * (pts[faces[:, 0]] - centre)).sum(1) < 0
    faces[inward] = faces[inward][:, ::-1]
    used, faces = np.unique(faces, return_inverse=True)
    return trimesh.Trimesh(pts[used], faces.reshape(-1, 3), process=False)


def convex_hull(points: np.ndarray):
    """trimesh's convex hull of points [P, 3], rebuilt from qhull's facets (`closed_convex_hull`)
    where trimesh left it open; None for a degenerate (flat) set. For hulls a boolean takes."""
    import trimesh

    try:
        hull = trimesh.convex.convex_hull(points)
    except Exception:
        hull = None
    return hull if is_closed(hull) else closed_convex_hull(points)


def from_manifold(man):
    m = man.to_mesh()
    return as_trimesh(np.asarray(m.vert_properties)[:, :3], np.asarray(m.tri_verts))


def cached_on(mesh, key, build):
    """build() once per content of `mesh`: kept in the mesh's own trimesh cache, which trimesh
    empties when its vertices or faces change (an edited mesh is never served a stale value). An
    export completes each object against the same background and neighbours: their ray-casting
    index and solids were built again for every object (room, 12 completions: 3.8 s of BVH builds
    for 13 rays each)."""
    cache = getattr(mesh, "_cache", None)
    if cache is None:
        return build()
    held = cache[key]
    if held is None:
        held = (build(),)           # a tuple: build() may return None
        cache[key] = held
    return held[0]


def raycasting_scene(mesh):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)))
    return scene


def distance_to_surface(points: np.ndarray, mesh, scene=None) -> np.ndarray:
    """Unsigned distance of points [P, 3] to the surface of `mesh` (scene: its raycasting_scene,
    when the caller has built it). Returns [P] float64."""
    import open3d as o3d

    if len(points) == 0:
        return np.zeros(0)
    scene = raycasting_scene(mesh) if scene is None else scene
    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy() \
        .astype(np.float64)


def closest_points(points: np.ndarray, mesh, scene=None) -> np.ndarray:
    """The closest point [P, 3] on the surface of `mesh` to each of points [P, 3] (float32 precision;
    open3d's BVH: trimesh.proximity.closest_point took ~0.3 s for a few hundred points on a 20k-face
    mesh, most of a real capture's outlier attachment). scene: as distance_to_surface's."""
    import open3d as o3d

    if len(points) == 0:
        return np.zeros((0, 3))
    scene = raycasting_scene(mesh) if scene is None else scene
    found = scene.compute_closest_points(o3d.core.Tensor(np.asarray(points, dtype=np.float32)))
    return found["points"].numpy().astype(np.float64)


def inside(points: np.ndarray, mesh, scene=None) -> np.ndarray:
    """Which points [P, 3] lie inside the closed `mesh` (ray parity, 3 rays; scene: as
    distance_to_surface's). Returns [P] bool."""
    import open3d as o3d

    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    scene = raycasting_scene(mesh) if scene is None else scene
    occ = scene.compute_occupancy(o3d.core.Tensor(np.asarray(points, dtype=np.float32)), nsamples=3)
    return occ.numpy().astype(bool)


# The grids that test a candidate cell by cell (free-space carving, handle sealing, the free-space
# share of `constraints.check`) and the support closing's grid hold at most this many cells: the
# pitch grows past the voxel for large objects only (~0.65 m cube at a 1 cm voxel, ~0.38 m at 5.7
# mm). At the voxel, a 1.5 m fragment of a real capture (7-Scenes chess, 5.7 mm) asked 1.6 M cells
# of each of its six candidates (22 s for the object, 11 s now), and the 9 objects no method could
# close took 116 s of the capture's 218 s of completion (docs/export-speed.md). The support
# closings of its furniture (up to 2 M cells at half the tolerance) were 176k-325k-face contours
# that the carving and each neighbour's boolean then paid for: capped, completion 58.8 -> 50.8 s.
CUT_CELLS = 300_000


def capped_pitch(lo: np.ndarray, hi: np.ndarray, pitch: float, max_cells: int) -> float:
    """`pitch`, grown so a grid over [lo, hi] holds about `max_cells` cells when it would hold more."""
    ext = np.maximum(np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64), pitch)
    return max(pitch, float(np.cbrt(np.prod(ext) / max_cells)))


def grid_points(lo: np.ndarray, hi: np.ndarray, pitch: float, max_cells: int = 2_000_000):
    """Cell centres of a regular grid covering [lo, hi] (pitch grown if it would exceed max_cells).

    Returns (centres [X*Y*Z, 3], shape (X, Y, Z), origin [3] of cell (0,0,0) centre, pitch used).
    """
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    ext = np.maximum(hi - lo, pitch)
    pitch = capped_pitch(lo, hi, pitch, max_cells)
    shape = tuple(int(n) for n in np.maximum(np.ceil(ext / pitch).astype(int), 1))
    origin = lo + 0.5 * pitch
    axes = [origin[i] + pitch * np.arange(shape[i]) for i in range(3)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return g, shape, origin, pitch


def occupancy_to_mesh(occ: np.ndarray, origin: np.ndarray, pitch: float):
    """Closed surface around the True cells of occ [X, Y, Z] (cell centres at origin + pitch * idx).

    The grid is padded by one empty cell so the contour always closes; the 0.5 iso-level of the
    lightly smoothed indicator puts the surface half a cell outside the occupied centres, i.e. on
    the cell faces. Returns a trimesh or None when nothing is occupied.
    """
    import pyvista as pv
    from scipy import ndimage

    if not occ.any():
        return None
    field = np.pad(occ.astype(np.float32), 2)
    field = ndimage.gaussian_filter(field, 0.6)
    img = pv.ImageData(dimensions=field.shape, spacing=(pitch,) * 3,
                       origin=tuple(np.asarray(origin, dtype=np.float64) - 2 * pitch))
    img.point_data["occ"] = field.ravel(order="F")
    surf = img.contour([0.5], scalars="occ").triangulate().clean()
    if surf.n_cells == 0:
        return None
    faces = np.asarray(surf.faces).reshape(-1, 4)[:, 1:]
    mesh = as_trimesh(np.asarray(surf.points), faces)
    # the sign alone (trimesh's `volume` computes every mass property: ~20 ms a cutter of a real
    # capture's completion, 200 of them)
    if signed_volume(mesh.vertices, mesh.faces) < 0:
        mesh.invert()
    return mesh


def solids_near(meshes, box, pitch: float, max_cells: int = 2_000_000) -> list:
    """Closed solids for `meshes` where they come within `box` (lo [3], hi [3]) — what a boolean
    confined to the box needs: each watertight mesh itself, and the open scans' surface bands
    (surface samples within the box and two cells around it, voxelised at `pitch`, dilated by a
    cell, each scan's cavities filled; about 3 cells thick) as one solid on one grid.

    The work is bounded by the box, not the scans: a real capture's 2 m table, solidified whole at
    the pitch of a 5 cm object beside it, was a 968k-face solid that each completion candidate
    subtracted, and each of ~20 neighbours was its own contour, manifold and boolean. The grid
    grows its pitch beyond `pitch` only past `max_cells` cells. Returns [] when none comes near.
    """
    import trimesh
    from scipy import ndimage

    margin = 2 * pitch
    blo, bhi = np.asarray(box[0], dtype=np.float64) - margin, np.asarray(box[1], dtype=np.float64) + margin
    solids, bands = [], []
    for mesh in meshes:
        if mesh is None or not len(mesh.faces):
            continue
        if is_solid(mesh):
            solids.append(mesh)
            continue
        tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
        keep = (tri.max(1) >= blo).all(1) & (tri.min(1) <= bhi).all(1)
        if not keep.any():
            continue
        pts = sample_surface(trimesh.Trimesh(mesh.vertices, np.asarray(mesh.faces)[keep], process=False), pitch)
        pts = pts[((pts >= blo) & (pts <= bhi)).all(1)]
        if len(pts):
            bands.append(pts)
    if not bands:
        return solids
    every = np.concatenate(bands)
    lo, hi = every.min(0) - margin, every.max(0) + margin
    pitch = capped_pitch(lo, hi, pitch, max_cells)
    shape = np.maximum(np.ceil((hi - lo) / pitch).astype(int), 1)
    occ = np.zeros(shape, dtype=bool)
    for pts in bands:
        # each scan's cavities on its own, as when each was solidified apart (two scans side by
        # side enclose nothing of theirs), on the grid cells around it
        idx = np.clip(((pts - lo) / pitch).astype(int), 0, shape - 1)
        a, b = np.maximum(idx.min(0) - 1, 0), np.minimum(idx.max(0) + 2, shape)
        own = np.zeros(b - a, dtype=bool)
        own[tuple((idx - a).T)] = True
        # one cell of dilation: a one-cell sheet would thin out under the contour's smoothing
        own = ndimage.binary_fill_holes(ndimage.binary_dilation(own))
        occ[a[0]:b[0], a[1]:b[1], a[2]:b[2]] |= own
    band = occupancy_to_mesh(occ, lo + 0.5 * pitch, pitch)
    return solids + ([band] if band is not None else [])


def significant_pieces(mesh, share: float = 0.02) -> int:
    """How many connected pieces of a closed mesh hold at least `share` of its volume (crumbs a
    boolean leaves count for nothing)."""
    if int(mesh.body_count) <= 1:
        return int(mesh.body_count)
    # a flat crumb encloses nothing: trimesh's centre of mass for it divides 0 by 0 (a warning the
    # user would read on every export), its volume is 0 all the same
    with np.errstate(invalid="ignore", divide="ignore"):
        vols = np.array([abs(float(p.volume)) for p in mesh.split(only_watertight=False)])
    total = float(vols.sum())
    return int(np.count_nonzero(vols >= share * total)) if total > 0 else len(vols)


def genus(mesh) -> int:
    """Handles of a closed mesh, summed over its pieces (a sphere 0, a mug 1)."""
    return int(mesh.body_count) - int(mesh.euler_number) // 2


def seal_handles(mesh, pitch: float):
    """`mesh` re-meshed from its inside at `pitch` (coarser past CUT_CELLS cells) with tunnels and
    pockets up to two cells wide closed (morphological closing, cavities filled): Poisson surfaces
    carry sub-voxel handles."""
    from scipy import ndimage

    centres, shape, origin, pitch = grid_points(mesh.bounds[0] - 2 * pitch, mesh.bounds[1] + 2 * pitch, pitch,
                                                max_cells=CUT_CELLS)
    occ = inside(centres, mesh).reshape(shape)
    occ = ndimage.binary_fill_holes(occ | ndimage.binary_closing(occ, np.ones((3, 3, 3), bool)))
    return occupancy_to_mesh(occ, origin, pitch)


def sample_surface(mesh, spacing: float, max_points: int = 200_000, seed: int = 0) -> np.ndarray:
    """Area-uniform surface samples about `spacing` apart (count from area / spacing²). [P, 3]."""
    if mesh is None or len(mesh.faces) == 0:
        return np.zeros((0, 3))
    area = float(mesh.area)
    if not area > 0:
        return np.asarray(mesh.vertices, dtype=np.float64)
    n = int(np.clip(2.0 * area / spacing ** 2, 200, max_points))
    return transforms.sample_surface(mesh, n, seed)


def volume_of_intersection(a, b) -> float:
    """Volume (m³) of a ∩ b for two closed meshes (0 when either is not a solid)."""
    if a is None or b is None or len(a.faces) == 0 or len(b.faces) == 0:
        return 0.0
    (alo, ahi), (blo, bhi) = a.bounds, b.bounds
    if (ahi < blo).any() or (bhi < alo).any():     # apart: no conversion nor boolean to find 0
        return 0.0
    if not (is_solid(a) and is_solid(b)):
        return 0.0
    inter = to_manifold(a) ^ to_manifold(b)
    return float(inter.volume())
