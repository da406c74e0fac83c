"""The static world's colliders from an observed background surface (issue #16 §1).

The background is built the way a fused capture sees it: open surfaces with normals towards free
space, a table top with a hole where a mug stood (occluded), a wall with a door opening, an unlabelled
box on the floor, table legs. Then the colliders are loaded into MuJoCo and things are dropped on them.
"""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from psimap.exporters.environment import Support, static_environment


def rect(origin, u, v, step=0.05, hole=None):
    """An open grid surface origin + a u + b v (a, b in [0, 1]), normal u x v. hole: (a0, a1, b0, b1)
    in the same unit square, left out."""
    origin, u, v = (np.asarray(x, np.float64) for x in (origin, u, v))
    nu = max(2, int(np.ceil(np.linalg.norm(u) / step)) + 1)
    nv = max(2, int(np.ceil(np.linalg.norm(v) / step)) + 1)
    a, b = np.meshgrid(np.linspace(0, 1, nu), np.linspace(0, 1, nv), indexing="ij")
    verts = origin + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
    faces = []
    for i in range(nu - 1):
        for j in range(nv - 1):
            ca, cb = (a[i, j] + a[i + 1, j]) / 2, (b[i, j] + b[i, j + 1]) / 2
            if hole and hole[0] < ca < hole[1] and hole[2] < cb < hole[3]:
                continue
            p, q, r, s = i * nv + j, (i + 1) * nv + j, (i + 1) * nv + j + 1, i * nv + j + 1
            faces += [[p, q, r], [p, r, s]]
    return trimesh.Trimesh(verts, np.array(faces), process=False)


def box_surface(lo, hi, step=0.05, bottom=False):
    """The outward faces of an axis-aligned box as seen by cameras (no bottom)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    d = hi - lo
    ex, ey, ez = np.eye(3) * d
    parts = [rect([lo[0], lo[1], hi[2]], ex, ey, step),                  # top, normal +z
             rect(lo, ez, ey, step), rect([hi[0], lo[1], lo[2]], ey, ez, step),   # -x, +x
             rect(lo, ex, ez, step), rect([lo[0], hi[1], lo[2]], ez, ex, step)]   # -y, +y
    if bottom:
        parts.append(rect(lo, ey, ex, step))
    return trimesh.util.concatenate(parts)


W, D, H = 4.0, 3.0, 2.5
TABLE = (np.array([0.2, -0.6, 0.0]), np.array([1.4, 0.2, 0.75]))        # a stuff-class desk
CLUTTER = (np.array([-1.2, 0.5, 0.0]), np.array([-0.8, 0.9, 0.3]))      # an unlabelled box


def room_background():
    lo, hi = TABLE
    parts = [
        rect([-W / 2, -D / 2, 0], [W, 0, 0], [0, D, 0], hole=(0.45, 0.75, 0.25, 0.55)),  # floor, furniture shadow
        rect([-W / 2, -D / 2, 0], [0, D, 0], [0, 0, H]),                    # wall x = -W/2, normal +x
        rect([W / 2, -D / 2, 0], [0, 0, H], [0, D, 0]),                     # wall x = +W/2, normal -x
        rect([-W / 2, D / 2, 0], [0, 0, H], [W, 0, 0],                      # wall y = +D/2 with a door
             hole=(0.0, 0.85, 0.6, 0.8)),
        # the desk top, a hole where a mug stood on it; its front edge; four legs (thin boxes)
        rect([lo[0], lo[1], hi[2]], [hi[0] - lo[0], 0, 0], [0, hi[1] - lo[1], 0], step=0.04,
             hole=(0.4, 0.55, 0.3, 0.55)),
        *[box_surface([x, y, 0], [x + 0.05, y + 0.05, hi[2] - 0.01], step=0.05)
          for x in (lo[0], hi[0] - 0.05) for y in (lo[1], hi[1] - 0.05)],
        box_surface(*CLUTTER, step=0.05),
    ]
    return trimesh.util.concatenate(parts)


@pytest.fixture(scope="module")
def env():
    return static_environment(room_background(), voxel=0.01)


def test_floor_supports_walls_found(env):
    assert env.floor_observed and abs(env.floor_z) < 2e-3
    desk = [s for s in env.supports if abs(s.height - 0.75) < 0.01]
    assert len(desk) == 1, [(s.height, s.area) for s in env.supports]
    # the mug's hole is filled: the desk collider covers the whole top
    area = desk[0].polygon
    from psimap.exporters.environment import _polygon_area

    assert abs(_polygon_area(area) - 1.2 * 0.8) < 0.06
    assert desk[0].contains([0.8, -0.2]) and not desk[0].contains([-0.5, -0.2])
    box_top = [s for s in env.supports if abs(s.height - 0.3) < 0.01]
    assert len(box_top) == 1 and box_top[0].contains([-1.0, 0.7])
    roles = env.summary()["colliders"]
    assert roles["support"] == 2 and roles["wall"] >= 4 and roles["clutter"] >= 1
    # every collider is a convex solid
    assert all(c.mesh.is_watertight and c.mesh.is_convex for c in env.colliders)


def test_door_opening_stays_open(env):
    """No wall collider may block the door: a point in the doorway is inside none of them."""
    door = np.array([[0.8, D / 2 - 0.01, 1.0], [0.5, D / 2 - 0.02, 1.9], [1.1, D / 2 - 0.03, 0.1]])
    for c in env.colliders:
        if c.role == "wall":
            assert not c.mesh.contains(door).any(), c.name


def test_colliders_follow_the_surface_within_budget(env):
    assert env.error_m <= env.budget_m, env.summary()
    assert env.coverage >= 0.95
    # and nothing fills the free space above the desk where objects stand
    above = np.array([[0.8, -0.2, 0.80], [0.5, -0.4, 0.9], [0.0, 0.0, 1.2]])
    for c in env.colliders:
        assert not c.mesh.contains(above).any(), c.name


def test_support_under(env):
    s = env.support_under([0.8, -0.2], 0.745)               # a mug's fused bottom sank 5 mm in
    assert s is not None and abs(s.height - 0.75) < 0.01
    assert env.support_under([0.8, -0.2], 0.5) is None       # half way down: not resting on it
    assert env.support_under([1.43, -0.2], 0.75) is not None  # over the edge by 3 cm: grown margin


def test_no_floor_seen_gives_a_safety_plane():
    lo, hi = TABLE
    top = rect([lo[0], lo[1], hi[2]], [hi[0] - lo[0], 0, 0], [0, hi[1] - lo[1], 0])
    wall = rect([-W / 2, D / 2, 0.5], [0, 0, 1.5], [W, 0, 0])
    env = static_environment(trimesh.util.concatenate([top, wall]), voxel=0.01)
    # the desk is the only support: it is not the floor, and the safety plane is under everything
    assert not env.floor_observed and env.floor_z <= 0.5 + 1e-9
    assert any(c.role == "support" and abs(c.height - 0.75) < 0.01 for c in env.colliders)


def test_empty_background():
    env = static_environment(None)
    assert env.floor_z is None and env.colliders == []
    assert not Support(0.0, np.zeros((0, 2)), 0.0).contains([0, 0])


def _mjcf(env, bodies):
    """A MuJoCo model of the environment's colliders plus free boxes {name: (pos, half size)}."""
    import mujoco

    spec = mujoco.MjSpec()
    spec.option.timestep = 0.002
    w = spec.worldbody
    w.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1], pos=[0, 0, env.floor_z])
    for c in env.colliders:
        m = spec.add_mesh(name=c.name)
        m.uservert = np.asarray(c.mesh.vertices, np.float64).ravel().tolist()
        m.userface = np.asarray(c.mesh.faces, np.int32).ravel().tolist()
        w.add_geom(type=mujoco.mjtGeom.mjGEOM_MESH, meshname=c.name)
    for name, (pos, half) in bodies.items():
        b = w.add_body(name=name, pos=pos)
        b.add_freejoint()
        b.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=half, mass=0.2, friction=[0.7, 0.005, 0.0001])
    model = spec.compile()
    return model, mujoco.MjData(model)


def test_boxes_rest_on_the_stuff_desk_and_stop_at_the_wall(env):
    """A box put on the desk stays there (the whole reason for this module); a box shoved towards
    the wall stops at it instead of passing through; a box on the unlabelled clutter stays on it."""
    import mujoco

    bodies = {"on_desk": ([0.8, -0.2, 0.75 + 0.04 + 0.002], [0.05, 0.04, 0.04]),
              "on_clutter": ([-1.0, 0.7, 0.3 + 0.03 + 0.002], [0.04, 0.04, 0.03]),
              "to_wall": ([1.5, 0.0, 0.05 + 0.002], [0.05, 0.05, 0.05])}
    model, data = _mjcf(env, bodies)
    wall_box = model.body("to_wall").id
    data.qvel[model.body_dofadr[wall_box]:model.body_dofadr[wall_box] + 3] = [3.0, 0.0, 0.0]
    mujoco.mj_forward(model, data)
    start = {n: data.xpos[model.body(n).id].copy() for n in bodies}
    for _ in range(1000):                                       # 2 s
        mujoco.mj_step(model, data)
    for n in ("on_desk", "on_clutter"):
        moved = np.linalg.norm(data.xpos[model.body(n).id] - start[n])
        assert moved < 0.01, (n, moved)
    x = data.xpos[wall_box][0]
    assert 1.8 < x < W / 2 - 0.05 + 0.005, x                    # reached the wall, did not pass it


def test_a_wavy_furniture_top_is_one_level_and_shelf_boards_stay_apart():
    """Issue #17: a table top fused 1.3 cm higher over one patch got a second slab there; the ball
    on the patch was pushed out of it and pinned. Levels within 3 cm on one footprint are one top;
    a shelf's boards 30 cm apart stay two."""
    import trimesh

    from psimap.exporters.environment import furniture_tops

    top = trimesh.creation.box(extents=[1.2, 0.8, 0.04]).apply_translation([0, 0, 0.70])
    bump = trimesh.creation.box(extents=[0.35, 0.3, 0.013]).apply_translation([0.2, 0.1, 0.7265])
    table = trimesh.util.concatenate([top, bump]).subdivide_to_size(0.02)      # fused meshes: small faces
    tops = furniture_tops(table, voxel=0.005)
    assert len(tops) == 1 and tops[0].height == pytest.approx(0.72, abs=2e-3)
    boards = trimesh.util.concatenate([trimesh.creation.box(extents=[0.8, 0.3, 0.02]).apply_translation([0, 0, z])
                                       for z in (0.4, 0.7)]).subdivide_to_size(0.02)
    assert sorted(round(s.height, 2) for s in furniture_tops(boards, voxel=0.005)) == [0.41, 0.71]


def test_a_board_seen_edge_on_is_found_where_things_stand_on_it():
    """A shelf board seen from the front fuses to a thin up-facing strip (room: 0.005 m² for a
    0.3 m² board), below MIN_SUPPORT_AREA: furniture_tops misses it, its coarse decomposition
    stood in and a bottle on it tipped and was pinned. The bottle marks the level; a thing on the
    floor, one on the found bottom board, one on a book on the board (beside a ledge at the book's
    height) and one in mid-air mark none."""
    import trimesh

    from psimap.exporters.environment import furniture_tops, tops_under_things

    def box(ext, at):
        return trimesh.creation.box(extents=ext).apply_translation(at)

    shelf = trimesh.util.concatenate([
        box([0.02, 0.3, 1.0], [-0.41, 0, 0.5]), box([0.02, 0.3, 1.0], [0.41, 0, 0.5]),     # sides
        box([0.8, 0.3, 0.04], [0, 0, 0.02]),                                                # bottom board, seen
        box([0.8, 0.01, 0.02], [0, -0.145, 0.70]),                                         # the board's front edge
        box([0.25, 0.01, 0.02], [0.275, -0.145, 0.78])]).subdivide_to_size(0.02)          # a ledge as high as the book
    known = furniture_tops(shelf, voxel=0.005)
    assert [round(s.height, 2) for s in known] == [0.04]          # the side panels' tops are too small too
    bottle = trimesh.creation.cylinder(radius=0.035, height=0.2).apply_translation([0.1, 0.05, 0.71 + 0.1])
    book = box([0.2, 0.15, 0.08], [-0.2, 0.0, 0.71 + 0.04])
    on_book = box([0.06, 0.06, 0.06], [-0.2, 0.0, 0.79 + 0.03])
    on_floor = box([0.1, 0.1, 0.1], [0.0, 0.0, 0.05])             # inside the shelf's plan, on the floor
    on_bottom = box([0.1, 0.1, 0.1], [0.2, 0.0, 0.04 + 0.05])
    mid_air = box([0.05, 0.05, 0.05], [0.0, 0.0, 0.45])
    found = tops_under_things(shelf, known, [bottle, book, on_book, on_floor, on_bottom, mid_air])
    assert len(found) == 1
    assert found[0].height == pytest.approx(0.71, abs=2e-3)
    assert found[0].contains([0.1, 0.05]) and found[0].contains([-0.2, 0.0])     # under the bottle and the book
    assert tops_under_things(shelf, known, [on_floor, on_bottom, mid_air]) == []
    assert tops_under_things(shelf, known + found, [bottle]) == []               # a level once


def test_a_box_on_a_board_seen_edge_on_is_exported_and_rests(tmp_path):
    """Through the export: a shelf (static furniture) whose middle board the cameras see from 5 mm
    above its top, a box standing on it. Without the board's level the shelf's solid filled the
    space over it and the box was skipped, "inside the collider of shelf_7: 1 % of its volume
    left after the cut"; with it the box is exported dynamic and rests on a slab at the board."""
    from psimap.camera import camera_rig, look_at
    from psimap.data.frames import ClassInfo
    from psimap.exporters.pipeline import export_scene
    from psimap.scene import scene_from_meshes

    def box(ext, at):
        return trimesh.creation.box(extents=ext).apply_translation(at)

    floor = box([3, 3, 0.02], [0, 0, -0.01])
    shelf = trimesh.util.concatenate([box([0.02, 0.3, 1.0], [-0.41, 0, 0.5]), box([0.02, 0.3, 1.0], [0.41, 0, 0.5]),
                                      box([0.8, 0.3, 0.04], [0, 0, 0.02]), box([0.8, 0.3, 0.02], [0, 0, 0.70]),
                                      box([0.84, 0.02, 1.0], [0, 0.16, 0.5])])
    thing = box([0.1, 0.08, 0.14], [0.1, 0.0, 0.71 + 0.07])
    c2ws = [look_at(np.array([1.3 * np.sin(a), -1.3 * np.cos(a), 0.715]), np.array([0, 0, 0.6]))
            for a in np.linspace(-0.9, 0.9, 8)]
    classes = [ClassInfo(1, "floor", False), ClassInfo(2, "shelf", True), ClassInfo(3, "box", True)]
    scene = scene_from_meshes([floor, shelf, thing], [0, 7, 8], [1, 2, 3], classes, camera_rig(c2ws, 96, 72, 80.0))
    r = export_scene(scene, tmp_path / "out", "mjcf", completion="auto")
    assert r["skipped"] == [], r["skipped"]
    assert {o["name"]: o["static"] for o in r["objects"]} == {"shelf_7": True, "box_8": False}
    assert any(abs(s["height"] - 0.71) < 0.015 for s in r["environment"]["supports"])
    c = r["check"]
    assert c["passed"] and c["pinned"] == {} and c["drift"]["box_8"] < 0.005, c


def test_the_space_over_a_top_under_a_thing_is_the_things():
    """Issue #17: carving kept what the things on a table hide (and the table's label bled onto
    their bottoms): the table rose 6 cm above its top under them and cut every thing. Over its top,
    under each thing standing there, the table's solid is cleared up to the thing's height."""
    import trimesh

    from psimap.exporters.environment import clear_above_top, furniture_tops

    slab = trimesh.creation.box(extents=[1.2, 0.8, 0.04]).apply_translation([0, 0, 0.70])
    bleed = trimesh.creation.box(extents=[0.16, 0.16, 0.06]).apply_translation([0.2, 0.1, 0.75])   # hidden space
    table = trimesh.boolean.union([slab, bleed], engine="manifold")
    top = [s for s in furniture_tops(slab.subdivide_to_size(0.02), voxel=0.005)][0]
    ball = trimesh.creation.icosphere(3, radius=0.12).apply_translation([0.2, 0.1, 0.72 + 0.12])
    far = trimesh.creation.box(extents=[0.1, 0.1, 0.1]).apply_translation([3.0, 0.0, 0.77])     # not on this top
    out, steps = clear_above_top(table, top, [ball, far])
    assert out.is_watertight and len(steps) == 1
    assert out.bounds[1, 2] == pytest.approx(0.72 + 0.01, abs=2e-3)          # the top stays, the rise goes
    assert out.volume == pytest.approx(slab.volume + 0.16 * 0.16 * 0.01, rel=0.02)
    assert clear_above_top(slab, top, [far])[1] == []


def test_furniture_keeps_its_collider_clear_of_the_things_on_its_tops():
    """The space over a top where a thing stands is the thing's for the furniture's collider too
    (SceneObject.keep_clear, read as obstacles when the collider is built): a room shelf's hulls
    spanned a bottle's compartment and cut half of it away. Things elsewhere (another table, the
    floor under this one) are not kept clear of."""
    import trimesh

    from psimap.exporters.environment import furniture_tops
    from psimap.exporters.objects import SceneObject, clear_tops

    slab = trimesh.creation.box(extents=[1.2, 0.8, 0.04]).apply_translation([0, 0, 0.70])
    top = furniture_tops(slab.subdivide_to_size(0.02), voxel=0.005)[0]
    table = SceneObject(1, "table", slab.copy())
    ball = SceneObject(2, "ball", trimesh.creation.icosphere(3, radius=0.12).apply_translation([0.2, 0.1, 0.84]))
    far = SceneObject(3, "box", trimesh.creation.box(extents=[0.1, 0.1, 0.1]).apply_translation([3.0, 0.0, 0.77]))
    under = SceneObject(4, "box", trimesh.creation.box(extents=[0.2, 0.2, 0.2]).apply_translation([0.0, 0.0, 0.1]))
    sunk = SceneObject(5, "mug", trimesh.creation.box(extents=[0.08, 0.08, 0.1]).apply_translation([-0.3, 0, 0.74]))
    clear_tops(table, [top], [ball, far, under, sunk])
    assert table.keep_clear == [ball, sunk]
    clear_tops(table, [top], [ball])                                   # listed once
    assert table.keep_clear == [ball, sunk]


# ---- the static world's speed-ups give the plain computation's floats (issue #20) ------------------
def _plain_split(points, areas, *, cell, min_area, depth=0):
    """split_footprint as first written: every cut's two sides measured from scratch, each side's
    hull and gap measured again when it is split."""
    from psimap.exporters import environment as E

    poly = E._hull_2d(points)
    observed = float(areas.sum())
    if E._polygon_area(poly) <= 0 or observed < min_area:
        return []
    radius, gap = E._largest_gap(points, poly, cell)
    if radius < E.GAP_RADIUS or depth >= E.MAX_SPLIT_DEPTH:
        return [(poly, observed)]
    c = points.mean(axis=0)
    axes = np.linalg.eigh(np.cov((points - c).T))[1].T
    best = None
    for ax in axes:
        t_pts, t_gap = points @ ax, gap @ ax
        for cut in (t_gap.min() - 0.5 * cell, t_gap.max() + 0.5 * cell):
            side = t_pts < cut
            if side.all() or not side.any():
                continue
            worst = max(E._largest_gap(points[s], E._hull_2d(points[s]), cell)[0] if s.sum() >= 3 else 0.0
                        for s in (side, ~side))
            if best is None or worst < best[0]:
                best = (worst, side)
    if best is None:
        return [(poly, observed)]
    out = []
    for s in (best[1], ~best[1]):
        out += _plain_split(points[s], areas[s], cell=cell, min_area=min_area, depth=depth + 1)
    return out


def _shape_points(boxes, holes=(), step=0.01, seed=0):
    """Plan-view sample points [n, 2] (a jittered grid of `step`) covering the union of boxes
    (x0, x1, y0, y1) minus the holes, and their areas [n]."""
    rng = np.random.default_rng(seed)
    x0, x1 = min(b[0] for b in boxes), max(b[1] for b in boxes)
    y0, y1 = min(b[2] for b in boxes), max(b[3] for b in boxes)
    g = np.stack(np.meshgrid(np.arange(x0, x1 + 1e-9, step), np.arange(y0, y1 + 1e-9, step), indexing="ij"), -1)
    g = g.reshape(-1, 2) + rng.uniform(-0.2, 0.2, (g.size // 2, 2)) * step

    def within(b):
        return (g[:, 0] >= b[0]) & (g[:, 0] <= b[1]) & (g[:, 1] >= b[2]) & (g[:, 1] <= b[3])

    keep = np.any([within(b) for b in boxes], axis=0) & ~np.any([within(h) for h in holes] or [np.zeros(len(g), bool)],
                                                                 axis=0)
    return g[keep], np.full(int(keep.sum()), step * step)


@pytest.mark.parametrize("boxes,holes", [
    ([(0, 1.0, 0, 0.3), (0, 0.3, 0, 1.0)], ()),                            # an L-shaped counter
    ([(0, 3.0, 0, 2.5)], [(1.05, 1.95, -1, 2.0)]),                        # a wall, a door in its middle
    ([(0, 3.0, 0, 2.5)], [(0.4, 1.2, -1, 2.0), (1.8, 2.6, -1, 2.0)]),     # two doors: cuts of equal gaps
    ([(0, 1.2, 0, 0.3), (0, 0.3, 0, 1.2), (0.9, 1.2, 0, 1.2)], ()),       # a U: split twice
])
def test_split_footprint_is_the_plain_split(boxes, holes):
    """split_footprint hands each side's hull and gap, measured for the winning cut, down to that
    side, and stops measuring a cut that cannot win: the pieces are the plain computation's, bit for
    bit, and a measurement reused for the wrong side (or a winner lost to the pruning) shows."""
    from psimap.exporters.environment import split_footprint

    pts, areas = _shape_points(boxes, holes)
    fast = split_footprint(pts, areas, cell=0.02, min_area=0.01)
    plain = _plain_split(pts, areas, cell=0.02, min_area=0.01)
    assert len(plain) >= 2                      # the shape was split
    assert len(fast) == len(plain)
    for (p, a), (q, b) in zip(fast, plain):
        assert np.array_equal(p, q) and a == b


def test_direction_sums_are_numpys_floats():
    """The window mass, the settled direction's weighted sum, the face centres and the column
    extremes are numpy's own expressions to the bit (order of addition, signed zeros)."""
    from psimap.exporters import environment as E

    rng = np.random.default_rng(3)
    # weights over 16 decades: a sum in another order rounds differently
    w = rng.uniform(0.5, 1.0, 20000) * 10.0 ** rng.integers(-8, 8, 20000)
    ang = np.radians(rng.choice([0.0, 90.0, 180.0, 270.0], 20000) + rng.normal(0, 8, 20000))
    d = np.stack([np.cos(ang), np.sin(ang)], 1)
    d[:50] = -0.0
    probes = np.stack([np.cos(a := np.radians(np.arange(0.0, 360.0, 2.5))), np.sin(a)], 1)
    dots = d @ probes.T
    cos_tol = np.cos(np.radians(12.0))
    mass = ((dots >= cos_tol) * w[:, None]).sum(0)
    assert np.array_equal(E._window_mass(dots, cos_tol, w).view(np.uint64), mass.view(np.uint64))
    for sel in (slice(None), slice(0, 50), slice(0, 0)):
        ref = (d[sel] * w[sel, None]).sum(0)
        assert np.array_equal(E._weighted_column_sum(d[sel], w[sel]).view(np.uint64), ref.view(np.uint64))
    t = rng.choice([-0.0, 0.0, 1e-300, -1.0, 3.3], (5000, 3, 3))
    t = np.concatenate([t, rng.normal(size=(5000, 3, 3)) * 10.0 ** rng.integers(-9, 9, (5000, 3, 3))])
    assert np.array_equal(E._face_centres(t).view(np.uint64), t.mean(axis=1).view(np.uint64))
    ij = rng.integers(-50, 50, (1000, 2))
    assert np.array_equal(E._column_extreme(ij, np.max), ij.max(axis=0)) and E._column_extreme(ij, np.max).dtype == ij.dtype
    assert np.array_equal(E._column_extreme(t[:, 0]), t[:, 0].min(axis=0))
