"""Procedural furniture and small objects for the synthetic benchmark scenes, built watertight.

Every builder works in the object's local frame: footprint centred on the origin, bottom at z = 0,
front facing +y (the back, -y, is what goes against a wall). Composite furniture is a manifold3d
union of boxes, so each object is one closed, oriented solid. Curved parts are tessellated from a
chordal error budget (`CHORD_TOL`), not a fixed segment count: a polygon inscribed in the true
circle never sticks out of it, so objects placed tangent to each other touch without overlapping.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# Largest distance between a tessellated curved surface and the true one, metres.
CHORD_TOL = 5e-4

THING_CLASSES = ("table", "chair", "shelf", "cabinet", "box", "bottle", "ball", "mug")
STUFF_CLASSES = ("floor", "wall", "ceiling")
FURNITURE = ("table", "chair", "shelf", "cabinet")
SMALL = ("box", "bottle", "ball", "mug")


@dataclass
class Support:
    """A horizontal rectangle objects can rest on, in the object's local frame.

    centre: (x, y); half: (half width along x, half depth along y); z: height of the surface;
    clearance: free height above it (inf when open).
    """

    centre: tuple[float, float]
    half: tuple[float, float]
    z: float
    clearance: float = math.inf


@dataclass
class Shape:
    """One procedural object in its local frame (see module doc).

    solid: manifold3d.Manifold; half: footprint half extents (x, y) of its bounding rectangle;
    height: top z; supports: surfaces other objects may rest on; round: footprint is a circle of
    radius `radius` (so its yaw does not matter for placement). A given object (`given`) keeps its
    own surface, which need not be closed; its solid is then the surface's convex hull, used only
    to keep others out of it.
    """

    kind: str
    solid: object
    half: tuple[float, float]
    height: float
    supports: list[Support] = field(default_factory=list)
    round: bool = False
    radius: float = 0.0
    surface: object = None      # a given trimesh to render instead of `solid` (then its convex hull)
    mass_kg: float | None = None  # the real mass of a given object, when known


def segments_for(radius: float, tol: float | None = None) -> int:
    """Fewest polygon sides whose chordal deviation from a circle of `radius` stays within `tol`
    (default: the module's CHORD_TOL, read at call time so a benchmark can vary it)."""
    tol = CHORD_TOL if tol is None else tol
    c = 1.0 - min(tol / max(radius, 1e-9), 1.0)
    n = math.ceil(math.pi / math.acos(c)) if c > -1 else 3
    return int(max(8, min(n, 256)) + (-max(8, min(n, 256))) % 4)  # multiple of 4: spheres need it


def sphere(radius: float, tol: float | None = None):
    """Geodesic sphere (manifold3d) centred at the origin whose faces stay within `tol` of the true
    sphere. Its faces are not a circle's chords, so the segment count is refined until the
    measured depth of the deepest face centre meets the budget (error ~ 1 / n^2)."""
    import manifold3d as m3d

    tol = CHORD_TOL if tol is None else tol
    n = segments_for(radius, tol)
    while True:
        s = m3d.Manifold.sphere(radius, n)
        mesh = s.to_mesh()
        v = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3]
        centres = v[np.asarray(mesh.tri_verts)].mean(axis=1)
        depth = radius - float(np.linalg.norm(centres, axis=1).min())
        if depth <= tol or n >= 512:
            return s
        n = min(512, max(n + 4, int(math.ceil(n * math.sqrt(depth / tol) / 4)) * 4))


def _box(sx: float, sy: float, sz: float, x: float = 0.0, y: float = 0.0, z0: float = 0.0):
    """Axis-aligned box of size (sx, sy, sz) centred at (x, y) in plan, bottom at z0."""
    import manifold3d as m3d

    return m3d.Manifold.cube([sx, sy, sz], center=True).translate([x, y, z0 + sz / 2])


def _union(parts):
    import manifold3d as m3d

    return m3d.Manifold.batch_boolean(list(parts), m3d.OpType.Add)


def _revolve(profile: list[tuple[float, float]], radius: float):
    """Solid of revolution about z of a closed (r, z) profile."""
    import manifold3d as m3d

    cs = m3d.CrossSection([np.asarray(profile, dtype=np.float64)])
    return m3d.Manifold.revolve(cs, segments_for(radius))


# ---------------------------------------------------------------------------------------- furniture
def table(rng: np.random.Generator, max_half: float = 0.8, lengths=(0.7, 1.6), depths=(0.55, 0.9)) -> Shape:
    """lengths / depths: ranges (m) of the top's two sides (the depth never exceeds the length)."""
    length = rng.uniform(lengths[0], min(lengths[1], 2 * max_half))
    depth = rng.uniform(depths[0], min(depths[1], length))
    height = rng.uniform(0.68, 0.78)
    top_t = rng.uniform(0.03, 0.05)
    leg = rng.uniform(0.04, 0.06)
    inset = rng.uniform(0.03, 0.08)
    # Legs reach 5 mm into the top so the union is one solid (no coplanar contact only).
    legs = [_box(leg, leg, height - top_t + 0.005, sx * (length / 2 - inset - leg / 2),
                 sy * (depth / 2 - inset - leg / 2)) for sx in (-1, 1) for sy in (-1, 1)]
    solid = _union([_box(length, depth, top_t, z0=height - top_t), *legs])
    return Shape("table", solid, (length / 2, depth / 2), height,
                 [Support((0.0, 0.0), (length / 2, depth / 2), height)])


def chair(rng: np.random.Generator, max_half: float = 0.4) -> Shape:
    w = rng.uniform(0.38, min(0.5, 2 * max_half))
    d = rng.uniform(0.38, 0.48)
    seat_h = rng.uniform(0.42, 0.48)
    seat_t = 0.04
    leg = rng.uniform(0.03, 0.04)
    back_h = rng.uniform(0.35, 0.5)
    back_t = 0.035
    legs = [_box(leg, leg, seat_h - seat_t + 0.005, sx * (w / 2 - leg / 2), sy * (d / 2 - leg / 2))
            for sx in (-1, 1) for sy in (-1, 1)]
    seat = _box(w, d, seat_t, z0=seat_h - seat_t)
    back = _box(w, back_t, back_h + 0.005, 0.0, -d / 2 + back_t / 2, seat_h - 0.005)
    solid = _union([seat, back, *legs])
    # The seat in front of the backrest is a support.
    return Shape("chair", solid, (w / 2, d / 2), seat_h + back_h,
                 [Support((0.0, back_t / 2), (w / 2, d / 2 - back_t / 2), seat_h, back_h)])


def shelf(rng: np.random.Generator, max_half: float = 0.6) -> Shape:
    w = rng.uniform(0.6, min(1.2, 2 * max_half))
    d = rng.uniform(0.28, 0.4)
    h = rng.uniform(1.1, 1.9)
    side_t, board_t, back_t = 0.02, 0.02, 0.012
    n_boards = int(np.clip(round(h / rng.uniform(0.3, 0.42)), 3, 6))
    parts = [_box(side_t, d, h, sx * (w / 2 - side_t / 2)) for sx in (-1, 1)]
    parts.append(_box(w - 2 * side_t + 0.01, back_t, h, 0.0, -d / 2 + back_t / 2))
    inner_w = w - 2 * side_t + 0.01  # 5 mm into each side panel
    zs = np.linspace(0.0, h - board_t, n_boards + 1)
    supports = []
    for i, z in enumerate(zs):
        parts.append(_box(inner_w, d - back_t + 0.005, board_t, 0.0, back_t / 2 - 0.0025, z))
        top = z + board_t
        clear = (zs[i + 1] - top) if i + 1 < len(zs) else math.inf
        supports.append(Support((0.0, back_t / 2), ((w - 2 * side_t) / 2, (d - back_t) / 2), top, clear))
    return Shape("shelf", _union(parts), (w / 2, d / 2), h, supports)


def cabinet(rng: np.random.Generator, max_half: float = 0.5) -> Shape:
    w = rng.uniform(0.45, min(1.0, 2 * max_half))
    d = rng.uniform(0.38, 0.52)
    h = rng.uniform(0.6, 1.0)
    plinth = rng.uniform(0.05, 0.1)
    handle_d = 0.025
    body_d = d - handle_d
    parts = [_box(w - 0.04, body_d - 0.04, plinth + 0.005, 0.0, -handle_d / 2),
             _box(w, body_d, h - plinth, 0.0, -handle_d / 2, plinth)]
    # One door: handle off-centre; two doors: a handle either side of the middle gap.
    handle_xs = [w / 4] if w < 0.6 else [-0.06, 0.06]
    for hx in handle_xs:
        # Handles reach 5 mm into the door.
        parts.append(_box(0.02, handle_d + 0.005, 0.12, hx, d / 2 - handle_d / 2 - 0.0025,
                          plinth + (h - plinth) * 0.55))
    return Shape("cabinet", _union(parts), (w / 2, d / 2), h,
                 [Support((0.0, -handle_d / 2), (w / 2, body_d / 2), h)])


# ------------------------------------------------------------------------------------ small objects
def box(rng: np.random.Generator, max_height: float = math.inf, sides=(0.06, 0.26)) -> Shape:
    """sides: range (m) of the two horizontal sides; the height lies in 5-25 cm."""
    sx, sy = rng.uniform(sides[0], sides[1], size=2)
    sz = min(rng.uniform(0.05, 0.25), max_height)
    return Shape("box", _box(sx, sy, sz), (sx / 2, sy / 2), sz, [Support((0.0, 0.0), (sx / 2, sy / 2), sz)])


def bottle(rng: np.random.Generator, max_height: float = math.inf) -> Shape:
    r = rng.uniform(0.028, 0.05)
    body = rng.uniform(0.1, 0.2)
    shoulder = rng.uniform(0.02, 0.05)
    rn = rng.uniform(0.011, 0.018)
    neck = rng.uniform(0.025, 0.06)
    total = body + shoulder + neck
    if total > max_height:
        s = max_height / total
        body, shoulder, neck = body * s, shoulder * s, neck * s
        total = max_height
    prof = [(0.0, 0.0), (r, 0.0), (r, body), (rn, body + shoulder), (rn, total), (0.0, total)]
    return Shape("bottle", _revolve(prof, r), (r, r), total, round=True, radius=r)


def ball(rng: np.random.Generator, max_height: float = math.inf, radii=(0.04, 0.12)) -> Shape:
    """radii: range (m) of the radius."""
    r = min(rng.uniform(radii[0], radii[1]), max_height / 2)
    s = sphere(r)
    # The geodesic sphere has a vertex at each pole: its bottom is exactly at z = 0 after this.
    return Shape("ball", s.translate([0, 0, r]), (r, r), 2 * r, round=True, radius=r)


def mug(rng: np.random.Generator, max_height: float = math.inf) -> Shape:
    import manifold3d as m3d

    r = rng.uniform(0.035, 0.05)
    h = min(rng.uniform(0.08, 0.12), max_height)
    wall, bottom = 0.006, 0.008
    tube = rng.uniform(0.006, 0.009)
    ring = min(rng.uniform(0.025, 0.035), h / 2 - tube - 0.005)
    outer = m3d.Manifold.cylinder(h, r, circular_segments=segments_for(r))
    # Two tessellations stack on the torus (tube circle, ring revolution): half the budget each.
    half_tol = CHORD_TOL / 2
    handle = m3d.Manifold.revolve(
        m3d.CrossSection.circle(tube, segments_for(tube, half_tol)).translate([ring, 0]),
        segments_for(ring + tube, half_tol))
    handle = handle.rotate([90, 0, 0]).translate([r, 0, h / 2])
    cavity = m3d.Manifold.cylinder(h, r - wall, circular_segments=segments_for(r)).translate([0, 0, bottom])
    solid = (outer + handle) - cavity
    reach = r + ring + tube
    return Shape("mug", solid, (reach, reach), h, round=True, radius=reach)


def solid_mug():
    """A fixed mug as a watertight trimesh without its cavity (radius 4 cm, 10 cm tall, a torus
    handle on +x): the shape the completion tests and benchmark complete, where the generator's
    `mug` varies with the scene's rng."""
    import manifold3d as m3d

    profile = [(0, 0), (0.04, 0), (0.04, 0.1), (0.035, 0.1), (0.035, 0.006), (0, 0.006)]
    body = m3d.Manifold.revolve(m3d.CrossSection([profile]), 64)
    handle = m3d.Manifold.revolve(m3d.CrossSection.circle(0.006, 12).translate([0.03, 0]), 48)
    return to_trimesh(body + handle.rotate([90, 0, 0]).translate([0.045, 0, 0.05]))


def given(name: str, mesh, mass_kg: float | None = None) -> Shape:
    """A given object (e.g. a scanned YCB model) as a Shape of class `name`: its surface (trimesh, metres,
    +z up) with duplicate vertices merged, moved so that its footprint's bounding rectangle is centred
    on the origin and its lowest point is at z = 0; its solid is the convex hull (always closed, so
    placement and the overlap check work on scans with holes too)."""
    import manifold3d as m3d
    import trimesh

    surface = trimesh.Trimesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64),
                              process=True)   # texture seams duplicate vertices: merged by position
    lo, hi = surface.bounds
    surface.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    hull = surface.convex_hull
    solid = m3d.Manifold(m3d.Mesh(vert_properties=np.asarray(hull.vertices, np.float32),
                                  tri_verts=np.asarray(hull.faces, np.uint32)))
    half = (hi[:2] - lo[:2]) / 2
    return Shape(name, solid, (float(half[0]), float(half[1])), float(hi[2] - lo[2]), surface=surface,
                 mass_kg=mass_kg)


FURNITURE_BUILDERS = {"table": table, "chair": chair, "shelf": shelf, "cabinet": cabinet}
SMALL_BUILDERS = {"box": box, "bottle": bottle, "ball": ball, "mug": mug}


# ------------------------------------------------------------------------------------ conversions
def place(solid, yaw: float, xyz) -> object:
    """The solid rotated by `yaw` (radians, about z) then translated to `xyz`."""
    return solid.rotate([0.0, 0.0, math.degrees(yaw)]).translate([float(v) for v in xyz])


def to_trimesh(solid):
    """manifold3d.Manifold -> watertight trimesh.Trimesh (float64 vertices)."""
    import trimesh

    mesh = solid.to_mesh()
    verts = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3]
    faces = np.asarray(mesh.tri_verts, dtype=np.int64)
    return trimesh.Trimesh(verts, faces, process=False)


def room_parts(half_x: float, half_y: float, height: float, ceiling: bool, thickness: float = 0.1):
    """Floor slab (top at z = 0), four wall slabs (inner faces at |x| = half_x, |y| = half_y) and
    an optional ceiling slab (bottom at z = height), as (class name, trimesh) pairs."""
    import trimesh

    def slab(lo, hi):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        m = trimesh.creation.box(extents=hi - lo)
        m.apply_translation((lo + hi) / 2)
        return m

    t = thickness
    ox, oy = half_x + t, half_y + t
    parts = [("floor", slab((-ox, -oy, -t), (ox, oy, 0.0))),
             ("wall", slab((-ox, -oy, 0.0), (-half_x, oy, height))),
             ("wall", slab((half_x, -oy, 0.0), (ox, oy, height))),
             ("wall", slab((-half_x, -oy, 0.0), (half_x, -half_y, height))),
             ("wall", slab((-half_x, half_y, 0.0), (half_x, oy, height)))]
    if ceiling:
        parts.append(("ceiling", slab((-ox, -oy, height), (ox, oy, height + t))))
    return parts
