"""Synthetic benchmark scenes with exact ground truth: `generate(out_dir, seed)` / `psimap generate`.

A room (floor, four walls, optional ceiling) holds 5-15 objects: watertight composite furniture
(tables, chairs, shelves, cabinets; `synthetic_shapes`) and small objects (boxes, bottles, balls,
mugs) resting on furniture or the floor, some touching each other. Shelves and cabinets stand with
their backs against a wall, so those backs (and every underside) are never seen, as in a real scan.
Frames are ray cast with Open3D's `RaycastingScene` in one batch over all frames; colour is
Lambertian shading of smooth procedural textures computed from the world position. Sensor and
pseudo-label noise come from `synthetic_noise`. Everything is written with
`psimap.data.scene_format.write_scene`; the same seed gives byte-identical files.

The tabletop layout (`layout="tabletop"`) puts one table in a room, walls 1.5-3 m from it, and 4-8
things on its top, none hidden behind another for most of the way round; a hand-held orbit films it.
Given meshes (`extra_objects`, e.g. scanned YCB models with their real masses) join them as things of
new classes.

Pixel convention: pixel (u, v) (column, row; integers) is the ray through K^-1 [u, v, 1], i.e. pixel
centres sit at integer coordinates (OpenCV), and `cx = (W - 1) / 2`.
"""
from __future__ import annotations

import math
import numbers
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from psimap import PsimapError
from psimap.camera import look_at
from psimap.data import synthetic_noise as N
from psimap.data import synthetic_shapes as S

# Class table: fixed across seeds so metrics of different scenes are comparable. Id 0 = void.
CLASS_NAMES = list(S.STUFF_CLASSES) + list(S.THING_CLASSES)
CLASS_ID = {name: i + 1 for i, name in enumerate(CLASS_NAMES)}
HFOV_DEG = 65.0              # horizontal field of view of the synthetic RGB-D camera
WALL_BAND = 0.55             # wall furniture is at most this deep
ORBIT_MARGIN = 1.05          # camera orbit keeps this distance from the walls (on its axes)
INNER_CLEAR = 0.45           # free-standing objects stay this far inside the orbit
FURNITURE_GAP = 0.12         # free floor between pieces of furniture
RAYS_PER_BATCH = 2_000_000   # camera rays cast at once (~150 MB of temporaries)
LAYOUTS = ("room", "tabletop")


def classes(extra_things=()):
    """The class table as a list of `ClassInfo` (ids from 1): the fixed table, then a thing class for
    each name of `extra_things` not in it (ids follow in order of first appearance)."""
    from psimap.data.frames import ClassInfo

    return [ClassInfo(i, n, n not in S.STUFF_CLASSES) for n, i in class_ids(extra_things).items()]


def class_ids(extra_things=()) -> dict[str, int]:
    """Class name -> id: CLASS_ID, then the new names of `extra_things` appended."""
    ids = dict(CLASS_ID)
    for name in extra_things:
        ids.setdefault(name, len(ids) + 1)
    return ids


# ------------------------------------------------------------------------------------------ layout
@dataclass
class Placed:
    """An object placed in the world: instance id, its shape, yaw (rad), position of its local origin,
    the instance id of what it rests on (0 = floor) and its footprint rectangle (centre, half, yaw)."""

    instance_id: int
    shape: S.Shape
    yaw: float
    xyz: np.ndarray
    support: int
    solid: object = None

    @property
    def rect(self):
        return (self.xyz[:2], np.asarray(self.shape.half), self.yaw)


@dataclass
class Layout:
    half_x: float
    half_y: float
    height: float
    ceiling: bool
    objects: list[Placed] = field(default_factory=list)
    kind: str = "room"           # "room", or "tabletop": objects[0] is the table, the others on it

    @property
    def orbit(self) -> tuple[float, float]:
        return self.half_x - ORBIT_MARGIN, self.half_y - ORBIT_MARGIN

    @property
    def inner(self) -> tuple[float, float]:
        ax, ay = self.orbit
        return ax - INNER_CLEAR, ay - INNER_CLEAR


def _rot2(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


def _corners(rect) -> np.ndarray:
    """[4, 2] corners of an oriented rectangle (centre [2], half [2], yaw)."""
    c, h, yaw = rect
    local = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * h
    return local @ _rot2(yaw).T + c


def rects_overlap(a, b, gap: float = 0.0) -> bool:
    """Separating-axis test of two oriented rectangles, each grown by gap / 2."""
    ca, cb = _corners(a), _corners(b)
    for yaw in (a[2], b[2]):
        R = _rot2(yaw)
        for axis in R.T:
            pa, pb = ca @ axis, cb @ axis
            if pa.max() + gap / 2 <= pb.min() - gap / 2 or pb.max() + gap / 2 <= pa.min() - gap / 2:
                return False
    return True


def _in_ellipse(points: np.ndarray, ax: float, ay: float) -> np.ndarray:
    return (points[:, 0] / ax) ** 2 + (points[:, 1] / ay) ** 2 <= 1.0


def _world_supports(p: Placed):
    """(rect, z, clearance) of each support surface of a placed object, in the world."""
    out = []
    R = _rot2(p.yaw)
    for s in p.shape.supports:
        c = R @ np.asarray(s.centre) + p.xyz[:2]
        out.append(((c, np.asarray(s.half), p.yaw), p.xyz[2] + s.z, s.clearance))
    return out


def _place_furniture(kind: str, lay: Layout, rng: np.random.Generator, iid: int) -> Placed | None:
    ax_in, ay_in = lay.inner
    builder = S.FURNITURE_BUILDERS[kind]
    against_wall = kind in ("shelf", "cabinet")
    tables = [o for o in lay.objects if o.shape.kind == "table"]
    for attempt in range(60):
        if against_wall:
            side = int(rng.integers(4))  # 0: +x wall, 1: -x, 2: +y, 3: -y
            along = lay.half_y if side < 2 else lay.half_x
            shape = builder(rng, max_half=min(0.6, along - 0.3))
            hx, hy = shape.half
            if 2 * hy > WALL_BAND:  # would reach into the camera orbit's clearance
                continue
            t = rng.uniform(-along + hx, along - hx)
            # Yaw turns the local front (+y) towards the room; the back touches the wall exactly.
            yaw_deg, xy = [(90.0, (lay.half_x - hy, t)), (-90.0, (-lay.half_x + hy, t)),
                           (180.0, (t, lay.half_y - hy)), (0.0, (t, -lay.half_y + hy))][side]
            xy = np.array(xy)
            yaw = math.radians(yaw_deg)
        else:
            shape = builder(rng, max_half=0.9 * min(ax_in, ay_in))
            if kind == "chair" and tables and attempt < 30:
                # A chair at a table, facing it.
                tab = tables[int(rng.integers(len(tables)))]
                k = int(rng.integers(4))
                d_local = np.array([[1, 0], [-1, 0], [0, 1], [0, -1]][k], float)
                reach = tab.shape.half[0 if k < 2 else 1] + shape.half[1] + 0.12
                d_world = _rot2(tab.yaw) @ d_local
                xy = tab.xyz[:2] + d_world * reach
                yaw = math.atan2(d_world[0], -d_world[1])  # local +y (front) -> -d_world
            else:
                xy = rng.uniform([-ax_in, -ay_in], [ax_in, ay_in])
                yaw = rng.uniform(0, 2 * math.pi)
        rect = (xy, np.asarray(shape.half), yaw)
        if not against_wall and not np.all(_in_ellipse(_corners(rect), ax_in, ay_in)):
            continue
        if against_wall and np.any(np.abs(_corners(rect)) > [lay.half_x + 1e-9, lay.half_y + 1e-9]):
            continue
        if any(rects_overlap(rect, o.rect, FURNITURE_GAP) for o in lay.objects):
            continue
        return Placed(iid, shape, yaw, np.array([xy[0], xy[1], 0.0]), 0)
    return None


def _place_small(kind: str, lay: Layout, rng: np.random.Generator, iid: int) -> Placed | None:
    furniture_supports = [(o, s) for o in lay.objects if o.shape.kind in S.FURNITURE
                          for s in _world_supports(o)]
    boxes = [p for p in lay.objects if p.shape.kind == "box"]
    for attempt in range(40):
        touching = None
        if boxes and kind != "mug" and rng.random() < 0.45:
            # Touch an existing box, on whatever it stands on.
            touching = boxes[int(rng.integers(len(boxes)))]
            sup_id, z = touching.support, float(touching.xyz[2])
            sup_rect, clear = None, math.inf
            for o, (rect_, z_, clear_) in furniture_supports:
                if o.instance_id == sup_id and abs(z_ - z) < 1e-9:
                    sup_rect, clear = rect_, clear_
        elif not furniture_supports or rng.random() < 0.25:
            sup_id, sup_rect, z, clear = 0, None, 0.0, math.inf
        else:
            o, (sup_rect, z, clear) = furniture_supports[int(rng.integers(len(furniture_supports)))]
            sup_id = o.instance_id
        on_floor = sup_id == 0
        if clear < 0.08:
            continue
        shape = S.SMALL_BUILDERS[kind](rng, max_height=clear - 0.02)
        if shape.height > clear - 0.015:
            continue
        # Objects on the same surface (a shelf has several, told apart by height).
        neighbours = [p for p in lay.objects if p.support == sup_id and p.shape.kind in S.SMALL
                      and abs(p.xyz[2] - z) < 1e-9]
        xy = None
        yaw = 0.0 if shape.round else rng.uniform(0, 2 * math.pi)
        if touching is not None:
            # Flush against one of the box's side faces.
            b = touching
            k = int(rng.integers(4))
            axis, sign = k // 2, (1 if k % 2 else -1)
            lat = 1 - axis
            if shape.round:
                if kind == "ball" and b.shape.height < shape.radius:
                    continue
                reach = b.shape.half[axis] + shape.radius
                lat_off = rng.uniform(-0.8, 0.8) * b.shape.half[lat]
            else:
                yaw = b.yaw
                reach = b.shape.half[axis] + shape.half[axis]
                lim = b.shape.half[lat] + shape.half[lat]
                lat_off = rng.uniform(-0.5, 0.5) * lim
            off = np.zeros(2)
            off[axis], off[lat] = sign * reach, lat_off
            xy = b.xyz[:2] + _rot2(b.yaw) @ off
        elif on_floor:
            xy = rng.uniform([-lay.half_x, -lay.half_y], [lay.half_x, lay.half_y])
        else:
            c, h, syaw = sup_rect
            # Uniform over the support, then kept only if the whole footprint lies on it.
            xy = c + _rot2(syaw) @ (rng.uniform(-1, 1, 2) * h)
        rect = (np.asarray(xy), np.asarray(shape.half), yaw)
        if on_floor:
            if not _floor_spot_ok(lay, rect):
                continue
            others = [p for p in lay.objects if p.support == 0]
        else:
            local = (_corners(rect) - sup_rect[0]) @ _rot2(sup_rect[2])
            if np.any(np.abs(local) > sup_rect[1] + 1e-9):
                continue
            others = neighbours
        gap = 0.01
        if any(rects_overlap(rect, p.rect, gap) for p in others if p is not touching):
            continue
        return Placed(iid, shape, yaw, np.array([xy[0], xy[1], z]), sup_id)
    return None


def _floor_spot_ok(lay: Layout, rect) -> bool:
    """Inside the room and either well inside the camera orbit or well outside it."""
    ax, ay = lay.orbit
    ax_in, ay_in = lay.inner
    c = _corners(rect)
    if not np.all(np.abs(c) <= [lay.half_x, lay.half_y]):
        return False
    return bool(np.all(_in_ellipse(c, ax_in, ay_in)) or not np.any(_in_ellipse(c, ax + 0.4, ay + 0.4)))


def make_layout(rng: np.random.Generator, n_objects: int | None = None, ceiling: bool | None = None) -> Layout:
    """Random room and object placement. n_objects: total things (None = random in 5..15)."""
    hx, hy = rng.uniform(2.2, 3.4, size=2)
    lay = Layout(float(hx), float(hy), float(rng.uniform(2.5, 3.0)),
                 bool(rng.random() < 0.5) if ceiling is None else bool(ceiling))
    n = int(rng.integers(5, 16)) if not n_objects else int(n_objects)
    if n < 1:
        raise PsimapError(f"number of objects must be >= 1, got {n}")
    n_furn = int(np.clip(rng.integers(2, 7), 1, max(1, n - 2)))
    kinds = list(rng.choice(S.FURNITURE, size=n_furn, p=[0.3, 0.25, 0.2, 0.25]))
    if not any(k in ("table", "shelf", "cabinet") for k in kinds):
        kinds[0] = "table"
    # Tables first so chairs can join them.
    kinds.sort(key=lambda k: ("table", "shelf", "cabinet", "chair").index(k))
    for kind in kinds:
        p = _place_furniture(str(kind), lay, rng, len(lay.objects) + 1)
        if p is not None:
            lay.objects.append(p)
    small_kinds = rng.choice(S.SMALL, size=n - len(lay.objects), p=[0.35, 0.25, 0.2, 0.2])
    for kind in small_kinds:
        for _ in range(3):  # another kind if this one found no room
            p = _place_small(str(kind), lay, rng, len(lay.objects) + 1)
            if p is not None:
                lay.objects.append(p)
                break
            kind = S.SMALL[int(rng.integers(len(S.SMALL)))]
    for p in lay.objects:
        p.solid = S.place(p.shape.solid, p.yaw, p.xyz)
    _drop_interpenetrating(lay)
    return lay


def _drop_interpenetrating(lay: Layout, tol_volume: float = 1e-7) -> None:
    """Exact check with manifold3d: drop any later object that overlaps an earlier one by volume."""
    keep: list[Placed] = []
    boxes = []
    for p in lay.objects:
        if p.support and p.support not in {q.instance_id for q in keep}:
            continue  # its support was dropped: it would float
        bb = np.asarray(p.solid.bounding_box()).reshape(2, 3)
        clash = False
        for q, qb in zip(keep, boxes):
            if np.any(bb[0] > qb[1]) or np.any(qb[0] > bb[1]):
                continue
            if (p.solid ^ q.solid).volume() > tol_volume:
                clash = True
                break
        if not clash:
            keep.append(p)
            boxes.append(bb)
    # Renumber so instance ids stay 1..n; supports follow.
    remap = {p.instance_id: i + 1 for i, p in enumerate(keep)}
    for p in keep:
        p.instance_id = remap[p.instance_id]
        p.support = remap.get(p.support, 0)
    lay.objects = keep


# ----------------------------------------------------------------------------------------- cameras
def intrinsics(width: int, height: int) -> np.ndarray:
    f = (width / 2) / math.tan(math.radians(HFOV_DEG) / 2)
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])


def _object_centre(p: Placed) -> np.ndarray:
    lo, hi = np.asarray(p.solid.bounding_box()).reshape(2, 3)
    return (lo + hi) / 2


def trajectory(lay: Layout, n_frames: int, rng: np.random.Generator) -> np.ndarray:
    """[F, 4, 4] camera-to-world poses: two orbits inside the room at changing heights. The gaze
    tours the objects (sorted by azimuth) three times while the camera circles twice, so each
    object is looked at from several positions; what faces a wall or the floor is never seen."""
    ax, ay = lay.orbit
    theta0 = rng.uniform(0, 2 * math.pi)
    ph = rng.uniform(0, 2 * math.pi, size=4)
    loops = 2.0 if n_frames >= 8 else 1.0
    tours = 1.5 * loops
    stops = sorted((_object_centre(p) for p in lay.objects), key=lambda c: math.atan2(c[1], c[0]))
    stops = np.array(stops or [[0.0, 0.0, 0.5]])
    poses = []
    for i in range(n_frames):
        t = i / max(n_frames, 1)
        th = theta0 + 2 * math.pi * loops * t
        s = 1.0 + 0.05 * math.sin(3 * th + ph[0])
        z = float(np.clip(1.25 + 0.5 * math.sin(2 * math.pi * t + ph[1]) + 0.15 * math.sin(5 * th + ph[2]),
                          0.6, lay.height - 0.4))
        eye = np.array([ax * s * math.cos(th), ay * s * math.sin(th), z])
        # Dwell on each stop, then glide to the next (smoothstep), so views stay steady.
        u = tours * len(stops) * t + ph[3] / (2 * math.pi) * len(stops)
        target = _tour(stops, u)
        if np.linalg.norm(target[:2] - eye[:2]) < 0.3:  # never look straight down at the feet
            target = target + 0.5 * np.r_[-eye[:2] / max(np.linalg.norm(eye[:2]), 1e-9), 0.0]
        poses.append(look_at(eye, target))
    return np.stack(poses)


def _tour(stops: np.ndarray, u: float) -> np.ndarray:
    """Gaze target at tour position u over stops [S, 3]: dwell on stop int(u), then glide to the next
    (smoothstep), so views stay steady."""
    k, f = int(u) % len(stops), u - int(u)
    f = f * f * (3 - 2 * f)
    return (1 - f) * stops[k] + f * stops[(k + 1) % len(stops)]


# ---------------------------------------------------------------------------------------- tabletop
# Kinds of things on a generated tabletop: class, builder, weight. Balls come in three sizes: large
# ones (a basketball is 12 cm in radius), the room's and apple-sized ones.
TABLETOP_KINDS = {
    "box": ("box", lambda rng: S.box(rng, sides=(0.05, 0.25)), 0.25),
    "bottle": ("bottle", S.bottle, 0.2),
    "mug": ("mug", S.mug, 0.2),
    "ball": ("ball", S.ball, 0.1),
    "large ball": ("ball", lambda rng: S.ball(rng, radii=(0.10, 0.20)), 0.1),
    "small ball": ("ball", lambda rng: S.ball(rng, radii=(0.03, 0.04)), 0.15),
}
# Every tabletop starts with these (the sizes issue #17 found hardest: a large ball fused no
# surface, an apple got too few surfels for a rigid body); the rest are drawn by weight.
TABLETOP_FIRST = ("large ball", "small ball")
WALL_DISTANCE = (1.5, 3.0)    # from the table centre to each wall, metres
TOP_GAP = 0.02                # free space between two things on the table (and to its edge)
CAMERA_DISTANCE = (0.7, 1.5)  # from the table centre, horizontally
CAMERA_HEIGHT = (1.0, 1.6)
MIN_SEEN_SHARE = 0.7          # of a nominal orbit, from which each thing on the table is not hidden


def _top(table: Placed):
    """(rect, z) of the table top in the world."""
    rect, z, _ = _world_supports(table)[0]
    return rect, z


def _place_on_top(shape: S.Shape, lay: Layout, rng: np.random.Generator, iid: int,
                  tries: int = 60) -> Placed | None:
    """A spot for `shape` on the table top (lay.objects[0]): its whole footprint on the top, TOP_GAP
    from the edge and from every other thing there; None when none was found in `tries` draws."""
    table = lay.objects[0]
    (c, h, tyaw), z = _top(table)
    for _ in range(tries):
        yaw = 0.0 if shape.round else float(rng.uniform(0, 2 * math.pi))
        # Half extents of the footprint along the top's axes: the centre is drawn where it fits.
        reach = np.abs(_rot2(yaw - tyaw)) @ np.asarray(shape.half)
        room = h - reach - TOP_GAP
        if np.any(room <= 0):
            return None
        xy = c + _rot2(tyaw) @ (rng.uniform(-1, 1, 2) * room)
        rect = (xy, np.asarray(shape.half), yaw)
        if any(rects_overlap(rect, o.rect, TOP_GAP) for o in lay.objects[1:]):
            continue
        p = Placed(iid, shape, yaw, np.array([xy[0], xy[1], z]), table.instance_id)
        if _seen_share(lay.objects[1:] + [p], table).min() < MIN_SEEN_SHARE:
            continue   # it would hide, or be hidden, most of the way round
        return p
    return None


def _seen_share(things: list[Placed], table: Placed, views: int = 24) -> np.ndarray:
    """[T] share of the views on a nominal orbit round the table (the middle of the cameras' range)
    from which the middle of each thing, at 60 % of its height, is not hidden by another. Each thing
    hides as a vertical cylinder of its inscribed radius and its height: a cheap, lenient stand-in
    for ray casting, so placement can keep small things from ending up behind big ones."""
    (c, h, tyaw), top = _top(table)
    a = np.linspace(0, 2 * np.pi, views, endpoint=False)
    radii = np.clip(h + 0.55, *CAMERA_DISTANCE)
    eyes = c + (np.column_stack([radii[0] * np.cos(a), radii[1] * np.sin(a)]) @ _rot2(tyaw).T)  # [V, 2]
    eye_z = float(np.mean(CAMERA_HEIGHT)) + 0.05
    xy = np.array([p.xyz[:2] for p in things])                                       # [T, 2]
    r = np.array([min(p.shape.half) for p in things])
    z_top = np.array([p.xyz[2] + p.shape.height for p in things])
    z_mid = np.array([p.xyz[2] + 0.6 * p.shape.height for p in things])
    seen = np.ones((len(things), views), bool)
    for i in range(len(things)):
        d = xy[i] - eyes                                                              # [V, 2]
        for j in range(len(things)):
            if j == i:
                continue
            # Closest approach of the sight line (eye -> target, s in [0, 1]) to j's axis.
            s_ = np.clip(((xy[j] - eyes) * d).sum(1) / (d * d).sum(1), 0.0, 1.0)
            gap = np.linalg.norm(eyes + s_[:, None] * d - xy[j], axis=1)
            z_line = eye_z + s_ * (z_mid[i] - eye_z)
            seen[i] &= ~((gap < r[j]) & (z_line < z_top[j]))
    return seen.mean(1)


def make_tabletop(rng: np.random.Generator, n_objects: int | None = None, ceiling: bool | None = None,
                  extra: list[S.Shape] = ()) -> Layout:
    """A table in a room, things on its top: the `extra` shapes first (each must fit, else
    PsimapError), then n_objects generated ones (None = random in 4..8): TABLETOP_FIRST, then kinds
    drawn from TABLETOP_KINDS (one that finds no spot is tried as another kind, then left out).
    Walls are WALL_DISTANCE from the table centre."""
    d = rng.uniform(*WALL_DISTANCE, size=4)          # to the -x, +x, -y, +y walls
    lay = Layout(float(d[0] + d[1]) / 2, float(d[2] + d[3]) / 2, float(rng.uniform(2.5, 3.0)),
                 bool(rng.random() < 0.5) if ceiling is None else bool(ceiling), kind="tabletop")
    # A dining / work table: 1-1.8 m by 0.7-1 m, 68-78 cm high.
    table = S.table(rng, max_half=0.9, lengths=(1.0, 1.8), depths=(0.7, 1.0))
    centre = np.array([(d[0] - d[1]) / 2, (d[2] - d[3]) / 2, 0.0])   # room centred on the origin
    lay.objects.append(Placed(1, table, float(rng.uniform(0, 2 * math.pi)), centre, 0))
    for shape in extra:
        p = _place_on_top(shape, lay, rng, len(lay.objects) + 1, tries=400)
        if p is None:
            raise PsimapError(f"extra object {shape.kind!r} ({2 * shape.half[0]:.2f} x {2 * shape.half[1]:.2f} m) "
                              f"finds no free spot on the {2 * table.half[0]:.2f} x {2 * table.half[1]:.2f} m table")
        lay.objects.append(p)
    n = int(rng.integers(4, 9)) if not n_objects else int(n_objects)
    names = list(TABLETOP_KINDS)
    weights = np.array([w for _, _, w in TABLETOP_KINDS.values()])
    drawn = rng.choice(names, size=max(0, n - len(TABLETOP_FIRST)), p=weights / weights.sum())
    for kind in [*TABLETOP_FIRST[:n], *drawn]:
        for _ in range(3):  # another kind if this one found no room
            cls, build, _ = TABLETOP_KINDS[str(kind)]
            shape = build(rng)
            shape.kind = cls
            p = _place_on_top(shape, lay, rng, len(lay.objects) + 1)
            if p is not None:
                lay.objects.append(p)
                break
            kind = names[int(rng.integers(len(names)))]
    for p in lay.objects:
        p.solid = S.place(p.shape.solid, p.yaw, p.xyz)
    _drop_interpenetrating(lay)
    # Footprints are disjoint, so nothing should be dropped; an extra object never silently is.
    if sum(p.shape.surface is not None for p in lay.objects) < len(extra):
        raise PsimapError("an extra object overlaps another thing on the table")
    return lay


def tabletop_trajectory(lay: Layout, n_frames: int, rng: np.random.Generator) -> np.ndarray:
    """[F, 4, 4] camera-to-world poses of a hand-held capture of the table: one orbit around it on an
    ellipse that follows the table's shape (CAMERA_DISTANCE from its centre, CAMERA_HEIGHT above the
    floor), with a wobble in distance and height and a small shake; the gaze tours the things on the
    top (sorted by azimuth) but stays near the mean direction to them, so every thing is in view most
    of the time."""
    table = lay.objects[0]
    (c, h, tyaw), top = _top(table)
    rx, ry = np.clip(h + rng.uniform(0.45, 0.65, size=2), *CAMERA_DISTANCE)
    theta0 = rng.uniform(0, 2 * math.pi)
    turn = rng.choice([-1.0, 1.0])
    ph = rng.uniform(0, 2 * math.pi, size=4)
    z_mid = rng.uniform(1.3, 1.42)      # high enough to see over the big things most of the orbit
    centre = np.array([c[0], c[1], top + 0.05])
    things = lay.objects[1:]
    stops = sorted((_object_centre(p) for p in things), key=lambda q: math.atan2(q[1] - c[1], q[0] - c[0]))
    stops = np.array(stops) if stops else centre[None]
    wall = np.array([lay.half_x, lay.half_y]) - 0.3
    poses = []
    for i in range(n_frames):
        t = i / max(n_frames, 1)
        th = theta0 + turn * 2 * math.pi * t
        shake = rng.normal(0.0, 0.005, 3)
        s = 1.0 + 0.06 * math.sin(3 * th + ph[0])
        local = s * np.array([rx * math.cos(th), ry * math.sin(th)]) + shake[:2]
        local *= np.clip(np.linalg.norm(local), *CAMERA_DISTANCE) / np.linalg.norm(local)
        xy = np.clip(c + _rot2(tyaw) @ local, -wall, wall)
        z = np.clip(z_mid + 0.15 * math.sin(2 * math.pi * t + ph[1]) + 0.04 * math.sin(5 * th + ph[2])
                    + shake[2], *CAMERA_HEIGHT)
        eye = np.array([xy[0], xy[1], z])
        # Aim along the mean direction to the things (which keeps near ones, far below the horizon, in
        # the frame as well as the far end of a long table), turned a little towards the tour's stop.
        to_things = stops - eye
        ahead = (to_things / np.linalg.norm(to_things, axis=1, keepdims=True)).mean(0)
        gaze = _tour(stops, 1.5 * len(stops) * t + ph[3] / (2 * math.pi) * len(stops)) - eye
        view = 0.7 * ahead / np.linalg.norm(ahead) + 0.3 * gaze / np.linalg.norm(gaze)
        poses.append(look_at(eye, eye + view + rng.normal(0.0, 0.01, 3)))
    return np.stack(poses)


# --------------------------------------------------------------------------------------- rendering
@dataclass
class SceneMesh:
    """The whole scene as one triangle soup: vertices [V, 3] float32, faces [F, 3] int64 and per
    face instance id, class id and material index (textures are per material)."""

    vertices: np.ndarray
    faces: np.ndarray
    face_instance: np.ndarray
    face_semantic: np.ndarray
    face_material: np.ndarray
    objects: dict            # instance id -> trimesh.Trimesh (complete; watertight unless given open)


def _world_surface(p: Placed):
    """The placed object's surface as a trimesh in the world: its solid, or its given surface moved
    the same way (yaw about z, then the translation)."""
    if p.shape.surface is None:
        return S.to_trimesh(p.solid)
    m = p.shape.surface.copy()
    T = np.eye(4)
    T[:2, :2], T[:3, 3] = _rot2(p.yaw), p.xyz
    return m.apply_transform(T)


def build_mesh(lay: Layout, class_id: dict[str, int] | None = None) -> SceneMesh:
    """class_id: class name -> id (default CLASS_ID; `class_ids` when there are extra classes)."""
    class_id = CLASS_ID if class_id is None else class_id
    verts, faces, inst, sem, mat, objects = [], [], [], [], [], {}
    nv = 0
    parts = [(name, m, 0) for name, m in S.room_parts(lay.half_x, lay.half_y, lay.height, lay.ceiling)]
    parts += [(p.shape.kind, _world_surface(p), p.instance_id) for p in lay.objects]
    for k, (name, m, iid) in enumerate(parts):
        if iid:
            objects[iid] = m
        verts.append(np.asarray(m.vertices, np.float32))
        faces.append(np.asarray(m.faces, np.int64) + nv)
        nv += len(m.vertices)
        nf = len(m.faces)
        inst.append(np.full(nf, iid, np.int64))
        sem.append(np.full(nf, class_id[name], np.int64))
        mat.append(np.full(nf, k, np.int64))
    return SceneMesh(np.concatenate(verts), np.concatenate(faces), np.concatenate(inst),
                     np.concatenate(sem), np.concatenate(mat), objects)


@dataclass
class Materials:
    """Per material k: base colour [M, 3], texture waves (direction [M, W, 3], cycles per metre
    [M, W], phase [M, W], amplitude [M, W]) and LiDAR reflectance [M]."""

    base: np.ndarray
    wave_dir: np.ndarray
    wave_freq: np.ndarray
    wave_phase: np.ndarray
    wave_amp: np.ndarray
    reflectance: np.ndarray

    def albedo(self, material: np.ndarray, points: np.ndarray) -> np.ndarray:
        """material [P] int, points [P, 3] world -> albedo [P, 3] float32 in [0, 1] (smooth in space)."""
        # Group pixels by material once (a boolean mask per material costs a full pass each).
        order = np.argsort(material, kind="stable")
        pts = points[order]
        bounds = np.searchsorted(material[order], np.arange(len(self.base) + 1))
        col = np.empty((len(material), 3), np.float32)
        for m in range(len(self.base)):
            lo, hi = bounds[m], bounds[m + 1]
            if lo == hi:
                continue
            # np.dot, not @: numpy's matmul is several times slower on tall, 3-wide operands.
            arg = np.dot(pts[lo:hi], (self.wave_dir[m] * self.wave_freq[m][:, None]).T.astype(np.float32))
            mod = 1.0 + np.dot(np.sin(2 * np.pi * arg + self.wave_phase[m].astype(np.float32)),
                               self.wave_amp[m].astype(np.float32))
            col[lo:hi] = self.base[m].astype(np.float32) * mod[:, None]
        out = np.empty_like(col)
        out[order] = col
        return np.clip(out, 0.0, 1.0)


def make_materials(n_materials: int, sizes: np.ndarray, rng: np.random.Generator,
                   n_waves: int = 3) -> Materials:
    """sizes: [M] characteristic size (m) of each material's object: texture frequency scales with it,
    so small objects get as many stripes as large ones."""
    import colorsys

    hsv = np.column_stack([rng.uniform(0, 1, n_materials), rng.uniform(0.2, 0.8, n_materials),
                           rng.uniform(0.35, 0.9, n_materials)])
    base = np.array([colorsys.hsv_to_rgb(*c) for c in hsv])
    d = rng.normal(size=(n_materials, n_waves, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    freq = rng.uniform(1.0, 4.0, size=(n_materials, n_waves)) / np.clip(sizes, 0.1, 1.5)[:, None]
    phase = rng.uniform(0, 2 * np.pi, size=(n_materials, n_waves))
    amp = rng.uniform(0.04, 0.15, size=(n_materials, n_waves))
    refl = rng.uniform(0.3, 1.0, n_materials)
    return Materials(base, d, freq, phase, amp, refl)


def _raycaster(mesh: SceneMesh):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    return scene


def camera_rays(K: np.ndarray, c2ws: np.ndarray, width: int, height: int) -> np.ndarray:
    """[F, H, W, 6] float32 rays (origin, direction) with direction = R K^-1 [u, v, 1], so the hit
    distance is the z-depth."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    pix = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ np.linalg.inv(K).T     # [HW, 3]
    rays = np.empty((len(c2ws), height * width, 6), np.float32)
    rays[..., 3:] = pix[None] @ c2ws[:, :3, :3].transpose(0, 2, 1)
    rays[..., :3] = c2ws[:, None, :3, 3]
    return rays.reshape(len(c2ws), height, width, 6)


def cast(scene, rays: np.ndarray):
    """rays [..., 6] -> (t_hit [...] (inf = miss), primitive id [...] int64 (-1 = miss),
    normals [..., 3])."""
    import open3d as o3d

    r = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays)))
    t = r["t_hit"].numpy()
    prim = r["primitive_ids"].numpy().astype(np.int64)
    prim[~np.isfinite(t)] = -1
    return t, prim, r["primitive_normals"].numpy()


def label_maps(prim: np.ndarray, mesh: SceneMesh):
    """Per pixel primitive ids [...] -> (instance, semantic) uint16 maps, 0 where nothing was hit."""
    hit = prim >= 0
    idx = np.where(hit, prim, 0)
    inst = np.where(hit, mesh.face_instance[idx], 0).astype(np.uint16)
    sem = np.where(hit, mesh.face_semantic[idx], 0).astype(np.uint16)
    return inst, sem


def shade(mats: Materials, material: np.ndarray, points: np.ndarray, normals: np.ndarray,
          lights: np.ndarray) -> np.ndarray:
    """Lambertian colour [P, 3] in [0, 1] of surface points [P, 3] with outward normals [P, 3] and
    material [P]; lights: [L, 4] (unit direction towards the light, power). View-independent."""
    light = 0.3 + np.dot(np.clip(np.dot(normals, lights[:, :3].T.astype(np.float32)), 0, None),
                         lights[:, 3].astype(np.float32))
    return np.clip(mats.albedo(material, points) * light[:, None], 0.0, 1.0)


def lidar_sweep(scene, mesh: SceneMesh, mats: Materials, origin: np.ndarray, rng: np.random.Generator,
                beams: int = 16, azimuths: int = 720, max_range: float = 8.0) -> np.ndarray:
    """A spinning-LiDAR sweep from `origin` [3]: [N, 4] float32 (x, y, z world, intensity in [0, 1]).
    Intensity = material reflectance x albedo brightness x cos(incidence), plus noise."""
    el = np.radians(np.linspace(-25.0, 15.0, beams))
    az = np.linspace(0, 2 * np.pi, azimuths, endpoint=False)
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    rays = np.concatenate([np.broadcast_to(origin, d.shape), d], -1).astype(np.float32)
    t, prim, n = cast(scene, rays)
    ok = (prim >= 0) & (t < max_range)
    t, prim, n, d = t[ok], prim[ok], n[ok], d[ok]
    r = t + rng.normal(0.0, 0.01, t.shape)
    pts = origin + d * r[:, None]
    mat = mesh.face_material[prim]
    bright = mats.albedo(mat, origin + d * t[:, None]).mean(1)
    inten = mats.reflectance[mat] * (0.5 + 0.5 * bright) * np.abs((n * d).sum(1))
    inten = np.clip(inten + rng.normal(0.0, 0.02, inten.shape), 0.0, 1.0)
    return np.column_stack([pts, inten]).astype(np.float32)


def render(scene, mesh: SceneMesh, mats: Materials, lights: np.ndarray, K: np.ndarray, c2ws: np.ndarray,
           width: int, height: int, noise_rng: np.random.Generator | None,
           depth_model: N.DepthNoise | None = None) -> dict:
    """Ray cast frames c2ws [B, 4, 4]. Returns [B, H, W(, 3)] arrays: rgb (float32, [0, 1]), depth (true
    z-depth, 0 = no surface), sensor_depth (with the sensor model when `noise_rng` is given, else the
    true depth; `depth_model` None = the default DepthNoise), gt_instance / gt_semantic (uint16)."""
    rays = camera_rays(K, c2ws, width, height)
    t, prim, normals = cast(scene, rays)
    hit = prim >= 0
    depth = np.where(hit, t, 0.0).astype(np.float32)
    d_hit, n_hit = rays[..., 3:][hit], normals[hit]
    points = rays[..., :3][hit] + d_hit * t[hit][:, None]
    rgb = np.zeros(t.shape + (3,), np.float32)
    rgb[hit] = shade(mats, mesh.face_material[prim[hit]], points, n_hit, lights)
    gt_inst, gt_sem = label_maps(prim, mesh)
    sensor_depth = depth
    if noise_rng is not None:
        cos_inc = np.zeros(t.shape, np.float32)
        cos_inc[hit] = np.abs((n_hit * d_hit).sum(-1)) / np.linalg.norm(d_hit, axis=-1)
        sensor_depth = N.noisy_depth(depth, cos_inc, noise_rng, depth_model)
        rgb = np.clip(rgb + noise_rng.normal(0.0, 0.008, rgb.shape).astype(np.float32), 0, 1)
    return {"rgb": rgb, "depth": depth, "sensor_depth": sensor_depth, "gt_instance": gt_inst,
            "gt_semantic": gt_sem}


# ---------------------------------------------------------------------------------------- generate
def generate(out_dir, seed: int = 0, *, frames: int = 60, width: int = 160, height: int = 120,
             n_objects: int | None = None, label_noise: float = 0.15, lidar: bool = False,
             pose_noise: float = 0.0, depth_noise: bool | N.DepthNoise = True, ceiling: bool | None = None,
             labels: N.LabelNoise | None = None, lidar_every: int = 10, progress: bool | None = None,
             overwrite: bool = False, layout: str = "room", extra_objects=None) -> dict:
    """Write a synthetic scene with exact ground truth to `out_dir` (docs/scene-format.md).

    layout: "room" (furniture and small objects in a room, n_objects in all, None = 5..15) or
    "tabletop" (a table in a room, n_objects generated things on its top, None = 4..8, seen by a
    hand-held orbit around the table). extra_objects (tabletop only): [(name, trimesh mesh in metres,
    +z up; mass_kg or None)], e.g. scanned YCB models, placed upright on the top before the generated
    things; a name not in the class table becomes a new thing class, and gt/instances.json carries
    "mass_kg" where it is given.

    label_noise: one knob for the pseudo-label errors (`LabelNoise.from_rate`); `labels` overrides
    it with explicit rates. depth_noise: sensor noise and invalid pixels on the written depth (True:
    the default sensor model; a DepthNoise: that model, e.g. `DepthNoise.degraded(3.0)`; False: none).
    pose_noise: std (m / rad) of the error on the written poses (ground truth renders use the true
    ones). lidar: a sweep every `lidar_every` frames from the camera position. overwrite: write into
    a folder psimap did not write (psimap.io_utils rules). Returns a summary dict.
    """
    from tqdm import tqdm

    from psimap.data.frames import Frame
    from psimap.data.scene_format import write_scene

    for name, v, lo in (("frames", frames, 1), ("width", width, 8), ("height", height, 8)):
        if int(v) < lo:
            raise PsimapError(f"{name} must be >= {lo}, got {v}")
    if not 0.0 <= label_noise <= 1.0:
        raise PsimapError(f"label noise must lie in 0..1, got {label_noise}")
    if not (pose_noise >= 0 and math.isfinite(pose_noise)):
        raise PsimapError(f"pose noise must be a finite value >= 0, got {pose_noise}")
    if n_objects is not None and n_objects != 0 and not 1 <= n_objects <= 40:
        raise PsimapError(f"number of objects must lie in 1..40, got {n_objects}")
    if layout not in LAYOUTS:
        raise PsimapError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    if extra_objects and layout != "tabletop":
        raise PsimapError("extra objects are placed on a table: they need layout='tabletop'")
    extra = _extra_shapes(extra_objects or [])
    class_id = class_ids(e.kind for e in extra)
    from psimap.io_utils import check_output_dir

    check_output_dir(out_dir, "scene", overwrite=overwrite)        # before the work, not after it
    t0 = time.perf_counter()
    progress = sys.stderr.isatty() if progress is None else progress
    stream = np.random.SeedSequence(int(seed)).spawn(7)
    r_layout, r_cam, r_tex, r_depth, r_label, r_pose, r_lidar = (np.random.default_rng(s) for s in stream)
    noise = labels or N.LabelNoise.from_rate(label_noise)
    timings = {}

    if layout == "room":
        lay = make_layout(r_layout, n_objects or None, ceiling)
    else:
        lay = make_tabletop(r_layout, n_objects or None, ceiling, extra)
    mesh = build_mesh(lay, class_id)
    timings["layout"] = time.perf_counter() - t0

    # Texture frequency scales with the material's object size (room surfaces count as 2 m).
    n_room = int(mesh.face_material.max()) + 1 - len(lay.objects)
    sizes = [2.0] * n_room + [max(2 * max(p.shape.half), p.shape.height) for p in lay.objects]
    mats = make_materials(len(sizes), np.asarray(sizes), r_tex)
    # A key light from above and a weaker fill from the other side (world frame: view-independent).
    towards = np.array([[-0.4, -0.3, 0.87], [0.5, 0.6, 0.62]])
    towards /= np.linalg.norm(towards, axis=1, keepdims=True)
    lights = np.column_stack([towards, [0.55, 0.25]])

    K = intrinsics(width, height)
    c2ws = (trajectory if layout == "room" else tabletop_trajectory)(lay, frames, r_cam)
    scene = _raycaster(mesh)
    thing_ids = [c.id for c in classes(class_id) if c.isthing]
    stats_total: dict[str, int] = {}
    out_frames = []
    n_surface = n_valid = 0
    # Frames are ray cast in batches of a bounded number of rays, so memory stays flat at any size.
    batch = max(1, RAYS_PER_BATCH // (width * height))
    bar = tqdm(total=frames, desc="psimap generate: frames", disable=not progress, leave=False)
    for start in range(0, frames, batch):
        idx = range(start, min(frames, start + batch))
        tb = time.perf_counter()
        r = render(scene, mesh, mats, lights, K, c2ws[idx.start:idx.stop], width, height,
                   r_depth if depth_noise else None,
                   depth_noise if isinstance(depth_noise, N.DepthNoise) else None)
        n_surface += int((r["depth"] > 0).sum())
        n_valid += int((r["sensor_depth"] > 0).sum())
        timings["render"] = timings.get("render", 0.0) + time.perf_counter() - tb
        tb = time.perf_counter()
        for j, i in enumerate(idx):
            inst, sem, st = N.pseudo_labels(r["gt_instance"][j], r["gt_semantic"][j], thing_ids, noise, r_label)
            for k, v in st.items():
                stats_total[k] = stats_total.get(k, 0) + v
            pose = N.perturb_pose(c2ws[i], pose_noise, r_pose)
            pts = None
            if lidar and i % max(1, lidar_every) == 0:
                pts = lidar_sweep(scene, mesh, mats, c2ws[i][:3, 3], r_lidar)
            out_frames.append(Frame(rgb=r["rgb"][j], depth=r["sensor_depth"][j], K=K.copy(), c2w=pose,
                                    semantic=sem, instance=inst, lidar=pts, name=f"frame_{i:05d}",
                                    gt_semantic=r["gt_semantic"][j], gt_instance=r["gt_instance"][j]))
            bar.update(1)
        timings["labels"] = timings.get("labels", 0.0) + time.perf_counter() - tb
    bar.close()

    import trimesh

    instances = [{"id": p.instance_id, "semantic": class_id[p.shape.kind], "name": p.shape.kind,
                  "support": p.support} | ({} if p.shape.mass_kg is None else {"mass_kg": p.shape.mass_kg})
                 for p in lay.objects]
    write_scene(out_dir, out_frames, classes(class_id), gt_mesh=trimesh.Trimesh(mesh.vertices, mesh.faces, process=False),
                gt_face_instance=mesh.face_instance, gt_face_semantic=mesh.face_semantic,
                gt_objects=mesh.objects, gt_instances=instances, overwrite=overwrite)
    timings["write"] = time.perf_counter() - t0 - sum(timings.values())

    return {
        "out": str(Path(out_dir)), "seed": int(seed), "frames": int(frames), "width": int(width),
        "height": int(height), "objects": len(lay.objects),
        "layout": layout,
        "room": {"half_x": lay.half_x, "half_y": lay.half_y, "height": lay.height, "ceiling": lay.ceiling},
        "instances": instances,
        "invalid_depth_fraction": float(1.0 - n_valid / max(n_surface, 1)),
        "label_noise": stats_total,
        "timings": timings, "seconds": time.perf_counter() - t0,
    } | ({} if layout == "room" else {"table": _table_summary(lay.objects[0])})


def _table_summary(table: Placed) -> dict:
    (c, h, yaw), top = _top(table)
    return {"length": 2 * float(h[0]), "depth": 2 * float(h[1]), "top": float(top),
            "centre": [float(c[0]), float(c[1])], "yaw": float(yaw)}


def _extra_shapes(extra_objects) -> list[S.Shape]:
    """Checked (name, mesh, mass_kg) items -> given Shapes; any bad item is one PsimapError."""
    shapes = []
    for k, item in enumerate(extra_objects):
        try:
            name, mesh, mass = item
            verts = np.asarray(mesh.vertices, np.float64)
            faces = np.asarray(mesh.faces, np.int64)
        except (TypeError, ValueError, AttributeError):
            raise PsimapError(f"extra object {k}: expected (name, trimesh mesh, mass_kg or None)") from None
        what = f"extra object {k} ({name!r})"
        if not isinstance(name, str) or not name.strip():
            raise PsimapError(f"{what}: the name must be a non-empty string")
        if name in S.STUFF_CLASSES:
            raise PsimapError(f"{what}: {name!r} is a stuff class, not a thing")
        if len(faces) == 0 or verts.ndim != 2 or verts.shape[1] != 3 or not np.all(np.isfinite(verts)):
            raise PsimapError(f"{what}: the mesh needs faces and finite vertices")
        size = np.ptp(verts, axis=0)
        if size.min() < 0.005 or size.max() > 1.0:
            raise PsimapError(f"{what}: its size {size.round(3).tolist()} m is not that of a thing on a "
                              "table (5 mm .. 1 m a side; the mesh must be in metres)")
        if mass is not None and not (isinstance(mass, numbers.Real) and not isinstance(mass, bool)
                                     and math.isfinite(mass) and mass > 0):
            raise PsimapError(f"{what}: mass_kg must be a positive number or None, got {mass!r}")
        shapes.append(S.given(name, mesh, None if mass is None else float(mass)))
    return shapes


def cli_generate(opts) -> int:
    """`psimap generate OUT --seed N ...`: write the scene, print what was written and the time."""
    if not opts.out:
        raise PsimapError("an output folder is required")
    s = generate(opts.out, seed=opts.seed, frames=opts.frames, width=opts.width, height=opts.height,
                 n_objects=opts.objects or None, label_noise=opts.noise, lidar=opts.lidar,
                 pose_noise=opts.pose_noise, overwrite=opts.overwrite, layout=opts.layout)
    print(describe(s))
    return 0


def describe(s: dict) -> str:
    """Human summary of a `generate` result."""
    from collections import Counter

    kinds = Counter(r["name"] for r in s["instances"])
    room = s["room"]
    ln = s["label_noise"]
    return (f"wrote {s['out']}: {s['frames']} frames {s['width']}x{s['height']}, "
            f"room {2 * room['half_x']:.1f} x {2 * room['half_y']:.1f} x {room['height']:.1f} m"
            f"{' with ceiling' if room['ceiling'] else ''}, "
            + (f"a {tab['length']:.2f} x {tab['depth']:.2f} m table (top at {tab['top']:.2f} m) and "
               if (tab := s.get("table")) else "")
            + f"{s['objects']} objects "
            f"({', '.join(f'{n} {k}' for k, n in sorted(kinds.items()))})\n"
            f"  invalid depth {100 * s['invalid_depth_fraction']:.1f}% of surface pixels; pseudo-label errors: "
            f"{ln.get('merged', 0)} merges, {ln.get('split', 0)} splits, {ln.get('missed', 0)} misses, "
            f"{ln.get('flipped', 0)} flips over {ln.get('instances', 0)} instance views\n"
            f"  {s['seconds']:.2f} s (" + ", ".join(f"{k} {v:.2f}" for k, v in s["timings"].items()) + ")")
