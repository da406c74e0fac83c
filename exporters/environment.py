"""The static world: collision geometry for everything that does not move (issue #16 §1).

A robot and the objects it handles touch far more than the floor: table and counter tops, shelves,
walls, static furniture, and surfaces nobody labelled. From the fused background surface (stuff
classes and unlabelled pixels, world Z-up) this module builds colliders that follow the observed
surface, the same set for every writer:

- supports: up-facing surfaces grouped by height, split into connected pieces in plan view; each
  piece becomes a convex slab (its footprint's convex hull, extruded `thickness` down from the
  fitted height). A piece whose footprint is far from convex (an L-shaped counter) is split along
  its principal axis until each part fills its hull. What is occluded on a support (where objects
  stand) is filled: a table top continues under the mug on it.
- walls: vertical surfaces grouped by direction and offset, split into pieces in their own plane,
  each a slab `thickness` deep behind the observed side; a wall with a door opening is split around
  it rather than closed.
- clutter: whatever surface is left (unlabelled boxes, a sofa's front, table legs), in connected
  pieces, each the convex hull of its points and their copy `thickness` behind the surface,
  bisected until the hull stays within the error budget of the surface it stands for.
- the floor: the lowest support that is a real share of the supported area (not merely the lowest
  point: a desk capture's carpet is 73 cm below the desk); when no floor was seen, a safety plane
  under everything, marked unobserved.

Every collider is a convex mesh in world coordinates (the writers emit them as convex mesh geoms /
convexHull colliders). The reported error is measured, not assumed: surface points of the background
sampled by area, each one's distance to the nearest collider surface.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# A face is horizontal (support) / vertical (wall) within this angle: fused TSDF surfaces of a flat
# table top scatter a few degrees.
PLANE_DEGREES = 12.0
# Smallest support worth a collider (m^2): a 10 x 10 cm stool top or shelf board end.
MIN_SUPPORT_AREA = 0.01
# Smallest wall piece (m^2) and clutter piece (m^2) worth a collider.
MIN_WALL_AREA = 0.05
MIN_CLUTTER_AREA = 0.002
# Slab depth below a support top / behind a wall (m): thick enough that a falling object cannot
# tunnel through in one 2 ms step at 3 m/s (6 mm), thin enough not to reach what is below.
THICKNESS = 0.04
# A convex slab may not close an open gap of this radius (m): a 20 cm wide door or corner a thing
# could pass through.
GAP_RADIUS = 0.1
# The floor is the lowest support holding at least this share of the supported area.
FLOOR_SHARE = 0.2
# Nothing but noise lies below a floor: at most this share of the surface, further than
# FLOOR_CLEARANCE (m) below it.
MAX_AREA_BELOW_FLOOR = 0.02
FLOOR_CLEARANCE = 0.1
MAX_SPLIT_DEPTH = 4
MAX_CLUTTER_PARTS = 64


@dataclass
class StaticCollider:
    """One convex collider of the static world. mesh: trimesh.Trimesh, convex, world frame, metres.
    role: "support" | "ceiling" | "wall" | "slope" | "clutter"; height: top of a support (m), else None."""

    name: str
    role: str
    mesh: object
    height: float | None = None
    area: float = 0.0                   # observed surface area it stands for (m^2)


@dataclass
class Support:
    """A flat surface things can rest on: top height (m) and plan-view footprint polygon [k, 2]."""

    height: float
    polygon: np.ndarray
    area: float

    def contains(self, xy, margin: float = 0.0) -> bool:
        """Whether the plan-view point xy [2] lies in the footprint grown by `margin` (m)."""
        from matplotlib.path import Path as MplPath

        if len(self.polygon) < 3:
            return False
        return bool(MplPath(self.polygon).contains_point(np.asarray(xy, np.float64), radius=2 * margin)
                    or MplPath(self.polygon[::-1]).contains_point(np.asarray(xy, np.float64), radius=2 * margin))


def support_under(supports, xy, z_bottom: float, *, max_gap: float = 0.05, margin: float = 0.03):
    """The highest of `supports` whose footprint (grown by `margin`) holds the plan-view point xy and
    whose top lies within `max_gap` of z_bottom (below, or above it: a fused bottom sinks into what
    it stands on), or None."""
    best = None
    for s in supports:
        if abs(s.height - z_bottom) <= max_gap and s.contains(xy, margin):
            if best is None or s.height > best.height:
                best = s
    return best


@dataclass
class StaticEnvironment:
    """The static world of an export: its colliders, the floor, the supports, and how well the
    colliders follow the observed surface (error_m: 95th percentile distance of the background's
    surface points to the nearest collider surface; coverage: share of that surface within budget_m)."""

    floor_z: float | None
    floor_observed: bool
    colliders: list = field(default_factory=list)
    supports: list = field(default_factory=list)
    error_m: float = 0.0
    mean_error_m: float = 0.0
    coverage: float = 1.0
    budget_m: float = 0.0
    unseen: list = field(default_factory=list)      # [UnseenSupport] among supports (add_unseen_supports)

    def support_under(self, xy, z_bottom: float, *, max_gap: float = 0.05, margin: float = 0.03):
        """`support_under(self.supports, ...)`."""
        return support_under(self.supports, xy, z_bottom, max_gap=max_gap, margin=margin)

    def summary(self) -> dict:
        roles = {}
        for c in self.colliders:
            roles[c.role] = roles.get(c.role, 0) + 1
        return {"floor_z": self.floor_z, "floor_observed": self.floor_observed, "colliders": roles,
                "supports": [{"height": s.height, "area_m2": s.area} for s in self.supports],
                "error_m": self.error_m, "mean_error_m": self.mean_error_m, "coverage": self.coverage,
                "budget_m": self.budget_m,
                "unseen_supports": [{"height": u.support.height, "area_m2": u.support.area,
                                     "free_share": u.free_share, "thing": u.name} for u in self.unseen]}


# ---- footprints --------------------------------------------------------------------------------
def _hull_2d(points: np.ndarray) -> np.ndarray:
    """Convex hull polygon [k, 2] (counter-clockwise) of plan-view points, [] when degenerate."""
    from scipy.spatial import ConvexHull, QhullError

    pts = np.asarray(points, np.float64)
    if len(pts) < 3:
        return np.zeros((0, 2))
    try:
        h = ConvexHull(pts)
    except (QhullError, ValueError):
        return np.zeros((0, 2))
    return pts[h.vertices]


def _polygon_area(poly: np.ndarray) -> float:
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def split_footprint(points: np.ndarray, areas: np.ndarray, *, cell: float, min_area: float,
                    depth: int = 0, measured=None) -> list[tuple[np.ndarray, float]]:
    """Convex plan-view pieces covering a connected surface piece, as (hull polygon [k, 2], observed
    area). One piece, its convex hull, unless the hull spans an open gap something could pass
    through (a door in a wall, the inside corner of an L-shaped counter: an unobserved region of
    radius >= GAP_RADIUS reaching the piece's outline; holes enclosed by observed surface are
    occlusions and count as surface); then it is cut along a principal axis at the gap's edge and
    each side handled alike. points [n, 2] (face centres), areas [n] (the area each stands for).
    measured: `_measure_piece(points, cell)` when the caller has it (a parent measured each side of
    its cut), not measured again."""
    poly = _hull_2d(points) if measured is None else measured[0]
    observed = float(areas.sum())
    if _polygon_area(poly) <= 0 or observed < min_area:
        return []
    radius, gap = _largest_gap(points, poly, cell) if measured is None else measured[1:]
    if radius < GAP_RADIUS or depth >= MAX_SPLIT_DEPTH:
        return [(poly, observed)]
    c = points.mean(axis=0)
    axes = np.linalg.eigh(np.cov((points - c).T))[1].T
    best = None
    for ax in axes:
        t_pts, t_gap = points @ ax, gap @ ax
        for before_gap, cut in ((True, t_gap.min() - 0.5 * cell), (False, t_gap.max() + 0.5 * cell)):
            side = t_pts < cut
            if side.all() or not side.any():
                continue
            # the cut whose worse side has the smallest gap wins, the first of equals: once one
            # side's gap is no smaller than the best so far this cut cannot win, and the other side
            # is not measured. The side holding the gap is measured first (it most often has the
            # larger gap); a gap is >= 0: after a cut leaving none nothing is measured.
            if best is not None and best[0] <= 0.0:
                break
            worst, parts = 0.0, {}
            for below in ((False, True) if before_gap else (True, False)):
                s = side if below else ~side
                sub = points[s]
                parts[below] = (s, sub, _measure_piece(sub, cell))
                worst = max(worst, parts[below][2][1])
                if best is not None and worst >= best[0]:
                    break
            if best is None or worst < best[0]:
                best = (worst, parts)
    if best is None:
        return [(poly, observed)]
    out = []
    for s, sub, m in (best[1][True], best[1][False]):      # below the cut, then above it
        # each side's hull and gap as measured for the cut (the same points: the same result)
        out += split_footprint(sub, areas[s], cell=cell, min_area=min_area, depth=depth + 1, measured=m)
    return out


def _measure_piece(points: np.ndarray, cell: float):
    """(hull polygon [k, 2], gap radius m, gap cell centres [g, 2]) of plan-view points [n, 2]:
    `_hull_2d` and `_largest_gap`; under 3 points no hull and no gap."""
    if len(points) < 3:
        return np.zeros((0, 2)), 0.0, np.zeros((0, 2))
    poly = _hull_2d(points)
    return (poly, *_largest_gap(points, poly, cell))


def _column_extreme(a: np.ndarray, reduce=np.min) -> np.ndarray:
    """reduce(a, axis=0) of a [n, k] with small k (np.min or np.max), a column at a time: numpy's
    reduction across rows of a short last axis is ~40x slower (an extreme does not depend on the
    order it is taken in)."""
    return np.array([reduce(a[:, j]) for j in range(a.shape[1])], dtype=a.dtype)


def _occupancy(points: np.ndarray, cell: float):
    """(grid [I, J] bool, origin [2]): cells of size `cell` holding a point, with pinholes closed and
    enclosed holes filled (what observed surface surrounds on every side was occluded, not absent)."""
    from scipy import ndimage

    origin = _column_extreme(points) - cell
    ij = np.floor((points - origin) / cell).astype(int)
    grid = np.zeros(tuple(_column_extreme(ij, np.max) + 2), bool)
    grid[ij[:, 0], ij[:, 1]] = True
    grid |= ndimage.binary_closing(grid, iterations=1)
    return ndimage.binary_fill_holes(grid), origin


def _largest_gap(points: np.ndarray, poly: np.ndarray, cell: float) -> tuple[float, np.ndarray]:
    """(radius in m, cell centres [k, 2]) of the widest unobserved region inside the hull `poly`."""
    from matplotlib.path import Path as MplPath
    from scipy import ndimage

    if len(poly) < 3:
        return 0.0, np.zeros((0, 2))
    grid, origin = _occupancy(points, cell)
    ii, jj = np.meshgrid(np.arange(grid.shape[0]), np.arange(grid.shape[1]), indexing="ij")
    centres = origin + (np.stack([ii, jj], -1) + 0.5) * cell
    # only an unobserved cell can be gap, and a cell inside one orientation's test needs no other
    # (each point's test is its own: the same answers as testing every cell with both)
    free = ~grid
    cand = centres[free]
    inside = MplPath(poly).contains_points(cand, radius=-cell)
    rest = ~inside
    inside[rest] = MplPath(poly[::-1]).contains_points(cand[rest], radius=-cell)
    gap = np.zeros(grid.shape, bool)
    gap[free] = inside
    if not gap.any():
        return 0.0, np.zeros((0, 2))
    dist = ndimage.distance_transform_edt(np.pad(gap, 1)) [1:-1, 1:-1]
    lab, _ = ndimage.label(gap)
    k = lab[np.unravel_index(int(dist.argmax()), dist.shape)]
    return float(dist.max()) * cell, centres[lab == k]


def _components_2d(points: np.ndarray, cell: float) -> np.ndarray:
    """Connected-component label per plan-view point (8-connected on a grid of `cell`, one cell of
    slack so TSDF pinholes do not split a table top)."""
    from scipy import ndimage

    ij = np.floor((points - _column_extreme(points)) / cell).astype(int)
    grid = np.zeros(tuple(_column_extreme(ij, np.max) + 1), bool)
    grid[ij[:, 0], ij[:, 1]] = True
    grid = ndimage.binary_dilation(grid, iterations=1)
    lab, _ = ndimage.label(grid, structure=np.ones((3, 3), bool))
    return lab[ij[:, 0], ij[:, 1]]


def _prism(poly: np.ndarray, z_lo: float, z_hi: float):
    """Convex slab: plan polygon [k, 2] extruded from z_lo to z_hi (trimesh)."""
    import trimesh

    k = len(poly)
    pts = np.vstack([np.column_stack([poly, np.full(k, z_lo)]), np.column_stack([poly, np.full(k, z_hi)])])
    return trimesh.convex.convex_hull(pts)


# ---- levels ------------------------------------------------------------------------------------
def _levels(values: np.ndarray, weights: np.ndarray, tol: float, min_weight: float) -> list[np.ndarray]:
    """Greedy peaks of a weighted 1-D distribution: index sets of values within `tol` of each peak,
    heaviest first, while a peak holds at least `min_weight`."""
    left = np.ones(len(values), bool)
    out = []
    while left.any():
        v, w = values[left], weights[left]
        bins = max(1, int(np.ceil((v.max() - v.min()) / tol)) + 1)
        hist, edges = np.histogram(v, bins=bins, range=(v.min() - tol / 2, v.min() - tol / 2 + bins * tol),
                                   weights=w)
        k = int(hist.argmax())
        centre = 0.5 * (edges[k] + edges[k + 1])
        for _ in range(3):      # settle on the weighted mean of the window
            sel = np.abs(v - centre) <= tol
            centre = float(np.average(v[sel], weights=w[sel])) if w[sel].sum() > 0 else centre
        sel = left & (np.abs(values - centre) <= tol)
        if weights[sel].sum() < min_weight:
            break
        out.append(np.flatnonzero(sel))
        left &= ~sel
    return out


def _direction_levels(dirs: np.ndarray, weights: np.ndarray, degrees: float, min_weight: float) -> list[np.ndarray]:
    """Greedy peaks of weighted directions dirs [n, 2] (plan view) or [n, 3] (no seams): index
    sets within `degrees` of each peak direction, heaviest first, while a peak holds `min_weight`."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True).clip(1e-12)
    if d.shape[1] == 2:
        probes = np.stack([np.cos(a := np.radians(np.arange(0.0, 360.0, 2.5))), np.sin(a)], 1)
    else:                   # a Fibonacci sphere: probes ~4 degrees apart
        k = np.arange(2500) + 0.5
        z, phi = 1 - 2 * k / 2500, np.pi * (1 + 5 ** 0.5) * k
        probes = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], 1)
    cos_tol = np.cos(np.radians(degrees))
    left = np.ones(len(d), bool)
    out = []
    while left.any():
        mass = _window_mass(d[left] @ probes.T, cos_tol, weights[left])
        peak = probes[int(mass.argmax())]
        for _ in range(3):      # settle on the weighted mean direction of the window
            sel = left & (d @ peak >= cos_tol)
            if not sel.any():
                break
            m = _weighted_column_sum(d[sel], weights[sel])
            peak = m / max(np.linalg.norm(m), 1e-12)
        sel = left & (d @ peak >= cos_tol)
        if weights[sel].sum() < min_weight:
            break
        out.append(np.flatnonzero(sel))
        left &= ~sel
    return out


def _window_mass(dots: np.ndarray, cos_tol: float, weights: np.ndarray) -> np.ndarray:
    """Weight [P] in each probe's window: dots [n, P] (directions . probes), weights [n] (finite).
    The same floats as ((dots >= cos_tol) * weights[:, None]).sum(0), which adds the rows in order:
    per probe its window's weights in row order, summed in order (cumsum; a plain sum pairs them),
    without the [n, P] float product (a wall set's 300k faces x 144 probes: 0.35 GB per peak)."""
    within = np.empty(dots.shape[::-1], bool)
    np.greater_equal(dots, cos_tol, out=within.T)      # [P, n]: a probe's window is one row
    out = np.zeros(len(within))
    for p, row in enumerate(within):
        w = weights[row]
        if len(w):
            out[p] = np.cumsum(w)[-1] + 0.0     # numpy's sum starts at 0.0: never -0.0
    return out


def _weighted_column_sum(a: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(a * weights[:, None]).sum(0) of a [n, k] with small k, the same floats (rows added in order,
    `_window_mass`), a column at a time: numpy's reduction across rows of a short last axis is slow."""
    out = np.zeros(a.shape[1])
    if len(a):
        for j in range(a.shape[1]):
            out[j] = np.cumsum(a[:, j] * weights)[-1] + 0.0
    return out


# ---- the three kinds -----------------------------------------------------------------------------
def _face_centres(triangles: np.ndarray) -> np.ndarray:
    """Centres [F, 3] of triangles [F, 3, 3]: triangles.mean(axis=1) to the bit, ~4x faster (numpy
    adds the corners in order from 0.0, and + 0.0 turns the one difference, -0.0, into 0.0)."""
    return (triangles[:, 0] + triangles[:, 1] + triangles[:, 2]) / 3 + 0.0


def _face_points(triangles: np.ndarray, areas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(points [4F, 3], weights [4F]): each face's corners and centre, a quarter of its area each:
    a footprint's hull reaches the surface's real edge, not the last face centre."""
    pts = np.concatenate([triangles.reshape(-1, 3), _face_centres(triangles)])
    return pts, np.concatenate([np.repeat(areas / 4, 3), areas / 4])


def _plane_pieces(triangles, areas, faces, project, *, cell: float, min_area: float, used: np.ndarray):
    """(convex polygon, observed area) of each connected piece of the coplanar `faces`, in the 2D
    coordinates project(points [n, 3]) -> [n, 2] of their plane (split_footprint); the faces of
    every piece kept are marked in `used`."""
    comp = _components_2d(project(_face_centres(triangles[faces])), cell)
    for c in np.unique(comp):
        g = faces[comp == c]
        if areas[g].sum() < min_area:
            continue
        used[g] = True
        pts, wts = _face_points(triangles[g], areas[g])
        yield from split_footprint(project(pts), wts, cell=cell, min_area=min_area)


def find_supports(triangles, normals, areas, *, tol: float, cell: float, min_area: float = MIN_SUPPORT_AREA,
                  facing: float = 1.0):
    """(supports, face mask) of up-facing surfaces: [Support] heaviest level first, and which faces
    they took. triangles [F, 3, 3], normals [F, 3], areas [F] of the background's faces. facing -1:
    the down-facing ones instead (ceilings, undersides of shelves)."""
    centres = _face_centres(triangles)
    up = facing * normals[:, 2] >= np.cos(np.radians(PLANE_DEGREES))
    idx = np.flatnonzero(up)
    supports, used = [], np.zeros(len(centres), bool)
    if len(idx) == 0:
        return supports, used
    for level in _levels(centres[idx, 2], areas[idx], tol, min_area):
        f = idx[level]
        z = float(np.average(centres[f, 2], weights=areas[f]))
        for poly, area in _plane_pieces(triangles, areas, f, lambda p: p[:, :2], cell=cell, min_area=min_area,
                                        used=used):
            supports.append(Support(z, poly, area))
    return supports, used


def find_walls(triangles, normals, areas, *, tol: float, cell: float, min_area: float = MIN_WALL_AREA,
               skip=None):
    """(walls, face mask) of the vertical surfaces: `find_planes` of the faces within PLANE_DEGREES
    of vertical."""
    sel = np.abs(normals[:, 2]) <= np.sin(np.radians(PLANE_DEGREES))
    return find_planes(triangles, normals, areas, tol=tol, cell=cell, min_area=min_area,
                       select=sel if skip is None else sel & ~skip, vertical=True)


def find_planes(triangles, normals, areas, *, tol: float, cell: float, min_area: float = MIN_WALL_AREA,
                select=None, vertical: bool = False):
    """(planes, face mask): [(normal [3], offset, polygon [k, 2] in the plane's (u, v), u [3], v [3])]
    for the faces `select`, grouped by direction (within PLANE_DEGREES) and offset (within tol),
    split into connected pieces in their plane. vertical: the directions are taken horizontal
    (walls; v is then +z). Otherwise any direction (a ramp, a slanted lid)."""
    centres = _face_centres(triangles)
    idx = np.flatnonzero(np.ones(len(centres), bool) if select is None else select)
    planes, used = [], np.zeros(len(centres), bool)
    if len(idx) == 0:
        return planes, used
    dirs = normals[idx, :2] if vertical else normals[idx]
    for d_level in _direction_levels(dirs, areas[idx], PLANE_DEGREES, min_area):
        f = idx[d_level]
        n = np.average(normals[f], axis=0, weights=areas[f])
        if vertical:
            n[2] = 0.0
        n /= max(np.linalg.norm(n), 1e-12)
        u = np.cross([0.0, 0.0, 1.0], n)
        u = u / np.linalg.norm(u) if np.linalg.norm(u) > 1e-6 else np.array([1.0, 0.0, 0.0])
        v = np.cross(n, u)
        off = centres[f] @ n
        for o_level in _levels(off, areas[f], tol, min_area):
            g = f[o_level]
            d = float(np.average(off[o_level], weights=areas[g]))
            for poly, _ in _plane_pieces(triangles, areas, g, lambda p: np.column_stack([p @ u, p @ v]),
                                         cell=cell, min_area=min_area, used=used):
                planes.append((n.copy(), d, poly, u, v))
    return planes, used


def _plane_slab(n, d, poly, u, v, thickness):
    """A plane piece as a convex slab from its observed plane d back to d - thickness along -n."""
    import trimesh

    front = np.array([p[0] * u + p[1] * v + d * n for p in poly])
    return trimesh.convex.convex_hull(np.vstack([front, front - thickness * n]))


def clutter_colliders(mesh, faces: np.ndarray, *, budget: float, thickness: float,
                      min_area: float = MIN_CLUTTER_AREA, max_parts: int = MAX_CLUTTER_PARTS) -> list:
    """Convex pieces for the background faces `faces` (indices) that no support or wall explains:
    per connected piece (largest first), the hull of its points and their copy `thickness` behind
    the surface, bisected along its principal axis while the surface lies more than `budget` inside
    the hull (95th percentile)."""
    import trimesh
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if len(faces) == 0:
        return []
    keep = np.zeros(len(mesh.faces), bool)
    keep[faces] = True
    adj = np.asarray(mesh.face_adjacency)
    adj = adj[keep[adj[:, 0]] & keep[adj[:, 1]]]
    n = len(mesh.faces)
    graph = coo_matrix((np.ones(len(adj)), (adj[:, 0], adj[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    tri = np.asarray(mesh.triangles, np.float64)
    fn = np.asarray(mesh.face_normals, np.float64)
    fa = np.asarray(mesh.area_faces, np.float64)
    labels, inverse = np.unique(label[faces], return_inverse=True)
    comp_area = np.bincount(inverse, weights=fa[faces])
    out = []

    def add(points, normal, depth):
        # an open patch (a surface seen from one side) is given depth behind it; a piece that is
        # already thick (a ramp seen on top and sides) is its own hull: depth added there would be
        # error, and the budget would tile it into steps
        along = points @ normal
        extra = max(0.0, thickness - float(along.max() - along.min()))
        hull = trimesh.convex.convex_hull(np.vstack([points, points - extra * normal]) if extra > 0 else points)
        probe = points if len(points) <= 4000 else points[np.linspace(0, len(points) - 1, 4000).astype(int)]
        err = _distance_to_convex(hull, probe)
        if float(np.percentile(err, 95)) <= budget or depth >= MAX_SPLIT_DEPTH or len(points) < 16:
            out.append(hull)
            return
        c = points.mean(axis=0)
        axis = np.linalg.eigh(np.cov((points - c).T))[1][:, -1]
        side = (points - c) @ axis > 0
        for s in (side, ~side):
            if s.sum() >= 4 and len(out) < max_parts:
                add(points[s], normal, depth + 1)

    for k in np.argsort(-comp_area):
        if comp_area[k] < min_area or len(out) >= max_parts:
            break
        f = faces[inverse == k]
        nrm = (fn[f] * fa[f, None]).sum(0)
        nrm = nrm / np.linalg.norm(nrm) if np.linalg.norm(nrm) > 1e-9 else np.array([0.0, 0.0, 1.0])
        add(np.concatenate([tri[f].reshape(-1, 3), _face_centres(tri[f])]), nrm, 0)
    return out[:max_parts]


def _distance_to_colliders(points: np.ndarray, colliders, floor_z: float | None, reach: float = 0.1) -> np.ndarray:
    """Distance [n] of each point to the nearest collider surface or the floor plane (points farther
    than `reach` from every collider's box count as far)."""
    d = np.full(len(points), np.inf) if floor_z is None else np.abs(points[:, 2] - floor_z)
    for c in colliders:
        lo, hi = np.asarray(c.mesh.bounds)
        near = np.all((points > lo - reach) & (points < hi + reach), axis=1)
        if near.any():
            d[near] = np.minimum(d[near], _distance_to_convex(c.mesh, points[near]))
    return d


def _distance_to_convex(hull, points: np.ndarray) -> np.ndarray:
    """Distance [n] of points to a convex mesh's surface: exact inside; outside, the distance to the
    farthest face plane in front of the point (a lower bound, exact over a face)."""
    n = np.asarray(hull.face_normals, np.float64)
    d = np.einsum("ij,ij->i", n, np.asarray(hull.triangles, np.float64)[:, 0])
    signed = points @ n.T - d[None, :]          # > 0 in front of a face
    outside = signed.max(axis=1)
    return np.where(outside > 0, outside, -outside)


def _scatter(mask_of_ok: np.ndarray, ok: np.ndarray) -> np.ndarray:
    out = np.zeros(len(ok), bool)
    out[np.flatnonzero(ok)[mask_of_ok]] = True
    return out


# ---- the environment -------------------------------------------------------------------------------
def static_environment(background, *, voxel: float = 0.01, budget: float | None = None,
                       thickness: float = THICKNESS, exclude_points=None, seed: int = 0) -> StaticEnvironment:
    """Colliders of the static world from the fused background surface (trimesh, world Z-up, face
    normals towards the observed side). voxel: the fusion's voxel (m); budget: collider error budget
    (m), default 2 voxels but not under 1.5 cm. exclude_points [n, 3]: where the objects are (their
    surfel centres): background surface within the budget of them is a mask's bleeding onto the
    background, never clutter (a clutter hull there would start inside the object)."""
    budget = max(0.015, 2.0 * voxel) if budget is None else float(budget)
    if background is None or len(getattr(background, "faces", [])) == 0:
        return StaticEnvironment(None, False, budget_m=budget)
    T = np.asarray(background.triangles, np.float64)
    C = _face_centres(T)
    N = np.asarray(background.face_normals, np.float64)
    A = np.asarray(background.area_faces, np.float64)
    ok = np.isfinite(C).all(1) & np.isfinite(N).all(1) & (A > 0)
    tol = max(0.01, 1.5 * voxel)
    # plan-view grid: fine enough for a 20 cm gap, never finer than the mesh's own edges (a cell
    # with no face centre in it would read as a hole)
    cell = max(0.02, 2.0 * voxel, float(np.median(background.edges_unique_length)))
    supports, s_used = find_supports(T[ok], N[ok], A[ok], tol=tol, cell=cell)
    ceilings, c_used = find_supports(T[ok], N[ok], A[ok], tol=tol, cell=cell, facing=-1.0)
    walls, w_used = find_walls(T[ok], N[ok], A[ok], tol=tol, cell=cell, skip=s_used | c_used)
    s_used, w_used = _scatter(s_used | c_used, ok), _scatter(w_used, ok)

    # floor: the lowest support holding a real share of the supported area, with (almost) nothing
    # observed below it; a desk seen without the floor has walls or legs going on down
    floor_z, observed = None, False
    if supports:
        # by level, not by piece: a floor is seen in pieces around the furniture standing on it
        levels = {}
        for s in supports:
            key = min(levels, key=lambda h: abs(h - s.height), default=None)
            key = key if key is not None and abs(key - s.height) <= tol else s.height
            levels[key] = levels.get(key, 0.0) + s.area
        total = sum(levels.values())
        for h in sorted(h for h, a in levels.items() if a >= FLOOR_SHARE * total):
            below = float(A[ok & (C[:, 2] < h - FLOOR_CLEARANCE)].sum())
            if below <= MAX_AREA_BELOW_FLOOR * float(A[ok].sum()):
                floor_z, observed = float(h), True
            break
    if floor_z is None:
        # no floor seen (a close-up of a table): a safety plane under everything, not a surface
        floor_z = float(T[ok][:, :, 2].min()) - FLOOR_CLEARANCE

    colliders = []
    for k, s in enumerate(sorted(supports, key=lambda s: (s.height, -s.area))):
        if observed and abs(s.height - floor_z) <= tol:
            continue                    # the floor plane is the floor's collider
        colliders.append(StaticCollider(f"support_{k}", "support", _prism(s.polygon, s.height - thickness, s.height),
                                        s.height, s.area))
    for k, c in enumerate(sorted(ceilings, key=lambda s: (s.height, -s.area))):
        colliders.append(StaticCollider(f"ceiling_{k}", "ceiling", _prism(c.polygon, c.height, c.height + thickness),
                                        None, c.area))
    for k, (n, d, poly, u, v) in enumerate(walls):
        colliders.append(StaticCollider(f"wall_{k}", "wall", _plane_slab(n, d, poly, u, v, thickness), None,
                                        _polygon_area(poly)))

    def unexplained(faces):
        # a fused surface rounds every corner where two planes meet, and a noisy floor's faces tilt
        # by tens of degrees: what lies within the budget of a collider already made is explained
        return faces[_distance_to_colliders(C[faces], colliders, floor_z if observed else None) > budget]

    rest = unexplained(np.flatnonzero(ok & ~s_used & ~w_used & (C[:, 2] > floor_z + 0.5 * tol)))
    # planes of any other slant (a ramp, a lid) among what is left
    select = np.zeros(len(C), bool)
    select[rest] = True
    slopes, p_used = find_planes(T[ok], N[ok], A[ok], tol=tol, cell=cell, select=select[ok])
    for k, (n, d, poly, u, v) in enumerate(slopes):
        colliders.append(StaticCollider(f"slope_{k}", "slope", _plane_slab(n, d, poly, u, v, thickness), None,
                                        _polygon_area(poly)))
    rest = unexplained(rest[~_scatter(p_used, ok)[rest]])
    if exclude_points is not None and len(exclude_points) and len(rest):
        from scipy.spatial import cKDTree

        near, _ = cKDTree(np.asarray(exclude_points, np.float64)).query(C[rest], distance_upper_bound=budget)
        rest = rest[~np.isfinite(near)]
    for k, hull in enumerate(clutter_colliders(background, rest, budget=budget, thickness=thickness)):
        colliders.append(StaticCollider(f"clutter_{k}", "clutter", hull, None, float(hull.area)))
    env = StaticEnvironment(floor_z, observed, colliders, supports, budget_m=budget)
    measure_error(env, background, seed=seed)
    return env


# levels of one furniture top closer than this (m) are one top (`one_level_per_top`)
TOP_MERGE = 0.03


def furniture_tops(mesh, *, voxel: float = 0.01, min_area: float = MIN_SUPPORT_AREA) -> list:
    """[Support] of a static furniture object's fused surface (a thing labelled table, shelf,
    cabinet): its up-facing levels, the same way as the background's."""
    if mesh is None or len(getattr(mesh, "faces", [])) == 0:
        return []
    T = np.asarray(mesh.triangles, np.float64)
    tol = max(0.01, 1.5 * voxel)
    cell = max(0.02, 2.0 * voxel, float(np.median(mesh.edges_unique_length)))
    supports, _ = find_supports(T, np.asarray(mesh.face_normals, np.float64), np.asarray(mesh.area_faces, np.float64),
                                tol=tol, cell=cell, min_area=min_area)
    return one_level_per_top(supports, merge=max(TOP_MERGE, 3 * voxel))


def tops_under_things(mesh, known, things, *, band: float = 0.03, min_area: float = MIN_CLUTTER_AREA,
                      merge: float = TOP_MERGE, clearance: float = 0.05) -> list:
    """[Support] levels of a static furniture object's fused surface (watertight or not, world
    frame) that `furniture_tops` missed but where `things` (trimesh meshes of the other things) stand.

    A shelf board seen edge-on from the front fuses to little up-facing surface (the generated
    room's board under three bottles: 0.005 m², against 0.08-0.10 m² for the boards seen from
    above, and MIN_SUPPORT_AREA is 0.01), so it got no slab, the furniture's coarse decomposition
    stood in for it (a hull 2 cm above the board, sloped 6 degrees) and a bottle lifted onto it
    tipped and was pinned. The things on the board say where it is: a thing whose bottom lies
    over the furniture's plan-view box, above its foot (`clearance`), on none of the `known`
    supports, and with at least `min_area` of the furniture's up-facing surface in the `band`
    below its bottom, marks a level there: its height is that surface's (area-weighted), its
    footprint the plan-view hull of that surface and the bottoms of the things that marked it.
    Things within `merge` of each other in height mark one level."""
    if mesh is None or len(getattr(mesh, "faces", [])) == 0 or not things:
        return []
    lo, hi = np.asarray(mesh.bounds, np.float64)
    T = np.asarray(mesh.triangles, np.float64)
    up = np.asarray(mesh.face_normals, np.float64)[:, 2] >= np.cos(np.radians(PLANE_DEGREES))
    centres, areas = _face_centres(T)[up], np.asarray(mesh.area_faces, np.float64)[up]
    boxes = [np.asarray(t.bounds, np.float64) if len(t.vertices) else None for t in things]
    marks = []                                  # (bottom z, bottom points [k, 2]) of things on a missed level
    for i, t in enumerate(things):
        v = np.asarray(t.vertices, np.float64)
        if len(v) == 0:
            continue
        z = float(v[:, 2].min())
        base = v[v[:, 2] <= z + 0.01, :2]
        c = base.mean(axis=0)
        if not (lo[2] + clearance < z < hi[2] + band and np.all(c >= lo[:2]) and np.all(c <= hi[:2])):
            continue
        if support_under(known, c, z) is not None:
            continue
        # standing on another thing (a box on a book): that thing is its support, not a board
        if any(b is not None and j != i and z - band <= b[1, 2] <= z + 0.01 and np.all(c >= b[0, :2])
               and np.all(c <= b[1, :2]) for j, b in enumerate(boxes)):
            continue
        near = (centres[:, 2] >= z - band) & (centres[:, 2] <= z + 0.01)
        if areas[near].sum() >= min_area:
            marks.append((z, base))
    levels = []
    for z, base in sorted(marks, key=lambda m: m[0]):
        if levels and z - levels[-1][0][-1] <= merge:
            levels[-1][0].append(z)
            levels[-1][1].append(base)
        else:
            levels.append(([z], [base]))
    out = []
    for zs, bases in levels:
        near = (centres[:, 2] >= min(zs) - band) & (centres[:, 2] <= max(zs) + 0.01)
        height = float(np.average(centres[near, 2], weights=areas[near]))
        poly = _hull_2d(np.concatenate([centres[near, :2], *bases]))
        if len(poly) >= 3:
            out.append(Support(height, poly, float(areas[near].sum())))
    return out


def one_level_per_top(supports, *, merge: float = 0.03) -> list:
    """`supports` without the levels a fused top's waviness adds: a smaller level within `merge` (m)
    of a larger one, lying on its footprint, is the same top. (A table fused 1.3 cm higher over one
    patch got a second slab there, and the 25 cm ball standing on the patch was pushed out of it,
    moved 1.6 cm and was pinned.)"""
    kept = []
    for s in sorted(supports, key=lambda s: -s.area):
        if len(s.polygon) and any(abs(s.height - k.height) <= merge and _within_box(s.polygon, k.polygon, merge)
                                  for k in kept):
            continue
        kept.append(s)
    return kept


def _within_box(inner, outer, margin: float) -> bool:
    """Whether the centre of plan-view polygon `inner` [k, 2] lies in the bounding box of `outer`
    grown by `margin` (the larger level's outline excludes the patch that rose above it: its
    notch, not a test of containment, is where the patch lies)."""
    c = np.asarray(inner, np.float64).mean(axis=0)
    o = np.asarray(outer, np.float64)
    return bool(np.all(c >= o.min(axis=0) - margin) and np.all(c <= o.max(axis=0) + margin))


def add_support_slabs(env: StaticEnvironment, supports, owner: str, thickness: float = THICKNESS) -> None:
    """Add `supports` (of static furniture `owner`) to env: things may rest on them, and each gets a
    flat slab collider (its furniture's own collider is flattened under it: `flatten_under`)."""
    for k, s in enumerate(sorted(supports, key=lambda s: (s.height, -s.area))):
        env.supports.append(s)
        env.colliders.append(StaticCollider(f"{owner}_top_{k}", "support",
                                            _prism(s.polygon, s.height - thickness, s.height), s.height, s.area))


# ---- supports no camera saw ---------------------------------------------------------------------
# A black or glossy counter top returns no depth to a structured-light or time-of-flight camera, and
# a table top seen edge-on (a robot's camera at table height) fuses to no up-facing surface: the
# things on it are found, nothing is under them, and the settle check pinned them (7-Scenes chess:
# 8 of 13 pinned things stood on its black counter, 65-92 cm above the floor). A thing is taken to
# stand on such a support when no support is known under it, no observed surface lies within
# UNSEEN_BAND below its bottom over its footprint, and the space under and around its bottom was
# not seen empty by the cameras (at most UNSEEN_MAX_FREE of their views of it): a thing hanging on
# a wall or a fragment floating in the room has its surroundings seen empty and stays the settle
# check's to pin.
UNSEEN_BAND = 0.05
UNSEEN_MAX_FREE = 0.2
UNSEEN_PROBES = (0.02, 0.05)        # m below the bottom: inside the slab a support would be
UNSEEN_NEIGHBOUR = 0.5              # m: things this close (plan view) at one level mark one surface
UNSEEN_MIN_THINGS = 2


@dataclass
class UnseenSupport:
    """A support inferred under a thing (`thing`: its index in the list asked about) whose bottom
    no camera saw standing on anything: `support` (height = its bottom), `free_share` the share of
    the cameras' views of its probe points that saw them empty; `name`: the thing's object name."""

    support: Support
    thing: int
    free_share: float
    name: str = ""


def _grow_polygon(poly: np.ndarray, by: float) -> np.ndarray:
    """Convex plan polygon [k, 2] grown by `by` (m): the hull of its corners moved 16 ways."""
    a = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
    ring = by * np.stack([np.cos(a), np.sin(a)], 1)
    return _hull_2d((np.asarray(poly, np.float64)[:, None, :] + ring[None]).reshape(-1, 2))


def _in_polygon(poly: np.ndarray, xy: np.ndarray) -> np.ndarray:
    from matplotlib.path import Path as MplPath

    if len(poly) < 3 or len(xy) == 0:
        return np.zeros(len(xy), bool)
    return MplPath(poly).contains_points(np.asarray(xy, np.float64))


def _plan_grid(poly: np.ndarray, max_points: int = 400) -> np.ndarray:
    """Plan points [n, 2] on a regular grid inside convex polygon [k, 2] (at most ~max_points)."""
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    step = max(float(np.sqrt(_polygon_area(poly) / max_points)), 0.003)
    xs, ys = np.arange(lo[0] + step / 2, hi[0], step), np.arange(lo[1] + step / 2, hi[1], step)
    g = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    g = g[_in_polygon(poly, g)]
    return g if len(g) else poly.mean(axis=0, keepdims=True)


def unseen_supports(things, known, surfaces, free_votes, *, floor_z: float | None = None, band: float = UNSEEN_BAND,
                    max_free: float = UNSEEN_MAX_FREE, merge: float = UNSEEN_BAND, neighbour: float = UNSEEN_NEIGHBOUR,
                    min_things: int = UNSEEN_MIN_THINGS, thickness: float = THICKNESS, why: dict | None = None) -> list:
    """[UnseenSupport] under `things` (trimesh meshes of the movable things, world Z-up; None or
    empty ones are passed over) that stand on a support no camera saw.

    known: [Support] of the static world (background levels, furniture tops); floor_z: the floor
    (a thing within `band` above it stands on it); surfaces: (centres [F, 3], areas [F], normals
    [F, 3], owner [F]) of every observed surface, owner = the index of the thing it belongs to or
    -1; free_votes(points [Q, 3]) -> (free [Q], valid [Q]): how many cameras saw each point empty
    and how many had a depth at its pixel (completion.freespace.free_votes).

    A thing's support is unseen when none of `known` lies under its plan-view centre within 5 cm of
    its bottom, the up-facing observed surface (not its own) within `band` below its bottom over
    its footprint grown by a quarter of its size is less than a quarter of the footprint's area,
    and at most `max_free` of the views of the probe points (that grown footprint, UNSEEN_PROBES
    below its bottom) saw them empty. Its slab (`thickness` deep) is the plan hull of the probes
    most views did not see empty; none is made when observed surface of anything else lies inside
    it (a chair's slats under a piece of its back rail labelled a thing), nor unless `min_things`
    such things stand within `merge` of one height, each within `neighbour` (plan view, between
    bounding boxes) of another: one thing over unseen space may be a fragment of furniture
    (7-Scenes chess: two pieces of chairs behind the table, 1.1 m apart; the things on its black
    counter stand in rows).
    why: receives {thing index: the reason it got no slab} for the things passed over."""
    why = {} if why is None else why
    centres, areas, normals, owner = surfaces
    centres = np.asarray(centres, np.float64).reshape(-1, 3)
    areas, owner = np.asarray(areas, np.float64), np.asarray(owner)
    up = np.asarray(normals, np.float64).reshape(-1, 3)[:, 2] >= np.cos(np.radians(45.0))
    found = []                                  # (bottom z, slab polygon, thing index, free share)
    for i, t in enumerate(things):
        if t is None or len(getattr(t, "vertices", [])) < 4:
            continue
        v = np.asarray(t.vertices, np.float64)
        z0 = float(v[:, 2].min())
        if floor_z is not None and z0 <= floor_z + band:
            why[i] = "on the floor"
            continue
        plan = _hull_2d(v[:, :2])
        area = _polygon_area(plan)
        if area <= 0:
            continue
        centre = v[v[:, 2] <= z0 + 0.01, :2].mean(axis=0)
        if support_under(known, centre, z0) is not None:
            why[i] = "on a known support"
            continue
        grown = _grow_polygon(plan, max(0.02, 0.25 * np.sqrt(area)))
        below = up & (owner != i) & (centres[:, 2] >= z0 - band) & (centres[:, 2] <= z0 + 0.01)
        below[below] = _in_polygon(grown, centres[below, :2])
        if areas[below].sum() >= 0.25 * area:
            why[i] = f"observed surface under it ({areas[below].sum() / area:.0%} of its footprint)"
            continue
        xy = _plan_grid(grown)
        probes = np.concatenate([np.column_stack([xy, np.full(len(xy), z0 - d)]) for d in UNSEEN_PROBES])
        free, valid = (np.asarray(a, np.float64) for a in free_votes(probes))
        share = float(free.sum() / max(valid.sum(), 1.0))
        if share > max_free:
            why[i] = f"the space under it seen empty ({share:.0%} of its views)"
            continue
        poly = _hull_2d(xy[(2 * free <= valid)[:len(xy)]])
        if len(poly) < 3 or not _in_polygon(poly, centre[None])[0]:
            why[i] = "the unseen space does not reach under its centre"
            continue
        inside = (owner != i) & (centres[:, 2] > z0 - thickness) & (centres[:, 2] < z0 - 0.01)
        inside[inside] = _in_polygon(poly, centres[inside, :2])
        if areas[inside].sum() > 0.05 * _polygon_area(poly):
            why[i] = "observed surface inside the slab"
            continue
        found.append((z0, poly, i, share))
    if not found:
        return []
    # one thing over unseen space may be a fragment of furniture labelled a thing (a chair's back
    # rail behind a table); things standing at one level near each other mark a surface
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(found)
    pairs = np.array([(k, j) for k in range(n) for j in range(k + 1, n)
                      if abs(found[k][0] - found[j][0]) <= merge and _box_gap(found[k][1], found[j][1]) <= neighbour],
                     np.int64).reshape(-1, 2)
    _, label = connected_components(coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)),
                                    directed=False)
    sizes = np.bincount(label)
    out = []
    for k, (z0, poly, i, share) in enumerate(found):
        if sizes[label[k]] < min_things:
            why[i] = f"no other thing stands at its level within {neighbour:.1f} m"
            continue
        out.append(UnseenSupport(Support(z0, poly, _polygon_area(poly)), i, share))
    return out


def _box_gap(a: np.ndarray, b: np.ndarray) -> float:
    """Plan-view distance (m) between the bounding boxes of polygons a [k, 2] and b [m, 2]."""
    gap = np.maximum(0.0, np.maximum(a.min(axis=0) - b.max(axis=0), b.min(axis=0) - a.max(axis=0)))
    return float(np.linalg.norm(gap))


def add_unseen_supports(env: StaticEnvironment, unseen, thickness: float = THICKNESS) -> None:
    """Add `unseen` ([UnseenSupport]) to env: a support things rest on, and a slab collider
    `unseen_support_<k>` under each (the same set for every writer)."""
    for k, u in enumerate(unseen):
        s = u.support
        env.supports.append(s)
        env.unseen.append(u)
        env.colliders.append(StaticCollider(f"unseen_support_{k}", "support",
                                            _prism(s.polygon, s.height - thickness, s.height), s.height, s.area))


def flatten_solid(mesh, supports, *, bump: float = 0.05):
    """(mesh, steps): a static furniture solid (watertight trimesh) with what rises less than `bump`
    above each of its supports, inside the support's footprint, cut away: a fused table top is
    wavy by a centimetre, and a bottle cut free of the table's bumps would stand on them and tip.
    Steps name each cut; a cut that would take more than a tenth of the solid is not made."""
    steps = []
    for s in supports:
        if len(s.polygon) < 3:
            continue
        mesh, removed = _cut_away(mesh, _prism(s.polygon, s.height, s.height + bump), max_share=0.1)
        if removed:
            steps.append(f"top flattened at {s.height:.3f} m ({removed * 1e6:.0f} cm3)")
    return mesh, steps


def stands_on(thing, top, margin: float = 0.01, reach: float = 0.05) -> bool:
    """Whether `thing` (trimesh) stands on the furniture `top` (Support): its bottom at most `reach`
    above the top (or below it: a fused bottom sinks in), its top above it, and its plan-view
    centre on the top (a box on the floor under a table does not stand on the table)."""
    v = np.asarray(thing.vertices, np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    return bool(lo[2] <= top.height + reach and hi[2] > top.height
                and top.contains(0.5 * (lo[:2] + hi[:2]), margin))


def clear_above_top(mesh, top, things, *, margin: float = 0.01, tol: float = 0.01):
    """(mesh, steps): a static furniture solid with the space over its `top` (Support) where each
    of `things` (watertight trimeshes resting on that top) stands cut away, up to the thing's
    height: that space is the thing's. Carving keeps what the things on a table hide from every
    view, and the table's label bleeds onto their bottoms; the table then rose 6 cm above its top
    under them and every thing was cut by its collider. A cut that leaves the solid unsound, or
    takes more than half of it, is not made."""
    from scipy.spatial import ConvexHull, QhullError

    steps = []
    for t in things:
        if not stands_on(t, top, margin):
            continue
        v = np.asarray(t.vertices, np.float64)
        hi = v.max(axis=0)
        xy = v[:, :2]
        try:
            ring = xy[ConvexHull(xy).vertices]
        except QhullError:
            continue
        d = ring - ring.mean(axis=0)
        ring = ring + margin * d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
        mesh, removed = _cut_away(mesh, _prism(ring, top.height + tol, hi[2] + margin), max_share=0.5)
        if removed:
            steps.append(f"cleared over its top under a thing ({removed * 1e6:.0f} cm3)")
    return mesh, steps


def _cut_away(mesh, tool, *, max_share: float):
    """(mesh, removed m3): watertight `mesh` minus convex `tool`, or (mesh, 0.0) unchanged when the
    cut removes nothing, more than `max_share` of the solid, or leaves it unsound."""
    import manifold3d  # noqa: F401  (to_manifold's engine)
    import trimesh

    from psimap.completion.meshops import to_manifold

    a = to_manifold(mesh)
    cut = a - to_manifold(tool)
    removed = float(a.volume() - cut.volume())
    if removed <= 1e-9 or removed > max_share * float(a.volume()):
        return mesh, 0.0
    m = cut.to_mesh()
    out = trimesh.Trimesh(np.asarray(m.vert_properties, np.float64)[:, :3], np.asarray(m.tri_verts), process=False)
    # the cut's own volume, not trimesh's (its mass properties: ~0.1 s a call on a 90k-face solid,
    # 1.4 s of a room's export); manifold3d's meshes are closed and outward, as the test asks
    if not (out.is_watertight and cut.volume() > 0):
        return mesh, 0.0
    return out, removed


def flatten_under(parts, supports, *, bump: float = 0.05, margin: float = 0.02) -> list:
    """Convex collider parts [trimesh] of a static furniture object with every part that bulges
    less than `bump` above one of its supports (inside the footprint grown by `margin`) cut flat at
    the support's height: the support's slab is the flat top things rest on, and a fused table top
    is rounded and wavy by centimetres. Parts that rise well above (a shelf's sides) are kept."""
    from psimap.exporters.collision import clip_halfspace

    out = []
    for p in parts:
        lo, hi = np.asarray(p.bounds)
        centre = np.asarray(p.vertices, np.float64).mean(axis=0)[:2]
        for s in supports:
            if lo[2] < s.height < hi[2] <= s.height + bump and s.contains(centre, margin):
                p = clip_halfspace(p, np.array([0.0, 0.0, -1.0]), -s.height)
                if p is None:
                    break
        if p is not None:
            out.append(p)
    return out


def measure_error(env: StaticEnvironment, background, *, samples: int = 20000, seed: int = 0) -> None:
    """Fill env.error_m / mean_error_m / coverage: distances of area-sampled background surface
    points to the nearest collider surface (the floor plane included)."""
    import trimesh

    if background is None or len(background.faces) == 0:
        return
    pts, _ = trimesh.sample.sample_surface(background, samples, seed=seed)
    d = np.minimum(_distance_to_colliders(pts, env.colliders, env.floor_z), 10.0)
    env.error_m = float(np.percentile(d, 95))
    env.mean_error_m = float(d.mean())
    env.coverage = float(np.mean(d <= env.budget_m))
