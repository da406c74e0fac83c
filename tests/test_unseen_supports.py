"""Supports no camera saw (exporters.environment.unseen_supports): a black counter top returns no
depth, a table top seen edge-on fuses to no up-facing surface, and the things standing on them
used to fall through and be pinned. A slab is inferred under such a thing only when nothing was
observed under it and the space around its bottom was not seen empty; a picture on a wall or a
fragment floating in the room keeps falling (the settle check pins it)."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

COUNTER_TOP = 0.74
WALL_Y = 0.62


def _box(extents, centre):
    return trimesh.creation.box(extents=extents).apply_translation(centre)


def kitchen(black_top: bool = True, lone: bool = False):
    """(background meshes, thing meshes, cameras [(K, c2w, W, H)], depths [H, W]) of a counter by a
    wall; things: a box and a can on the counter (lone: the box alone), a picture on the wall, a
    fragment floating over the floor, a box on the floor. With black_top, the counter's top returns
    no depth (a black, glossy top)."""
    from psimap.camera import look_at
    from psimap.metrics.geometry import camera_rays, raycasting_scene

    floor = _box([2.4, 2.0, 0.02], [0, 0.3, -0.01])
    wall = _box([2.4, 0.04, 1.5], [0, WALL_Y + 0.02, 0.75])
    counter = _box([1.2, 0.6, COUNTER_TOP], [0, 0.3, COUNTER_TOP / 2])
    things = [_box([0.12, 0.08, 0.07], [-0.25, 0.25, COUNTER_TOP + 0.035]),    # on the black top
              _box([0.3, 0.02, 0.2], [0.2, WALL_Y - 0.01, 1.1]),                # hangs on the wall
              _box([0.1, 0.1, 0.05], [0.9, -0.35, 0.525]),                      # floats over the floor
              _box([0.1, 0.1, 0.06], [-0.9, -0.3, 0.03])]                       # on the floor
    if not lone:    # a can 35 cm from the box, on the same top
        things.append(trimesh.creation.cylinder(radius=0.035, height=0.12).apply_translation(
            [0.2, 0.3, COUNTER_TOP + 0.06]))
    background = [floor, wall, counter]
    allm = trimesh.util.concatenate(background + things)
    top_faces = np.zeros(len(allm.faces), bool)
    off = len(floor.faces) + len(wall.faces)
    top_faces[off:off + len(counter.faces)] = (counter.face_normals[:, 2] > 0.9)
    rc = raycasting_scene(np.asarray(allm.vertices), np.asarray(allm.faces))
    W, H, f = 96, 72, 80.0
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    cams, depths = [], []
    for a in np.linspace(-1.1, 1.1, 8):
        c2w = look_at([1.6 * np.sin(a), 0.25 - 1.6 * np.cos(a), 1.4], [0, 0.25, 0.6])
        hit = rc.cast_rays(camera_rays(K, c2w, W, H))
        ids = hit["primitive_ids"].numpy().astype(np.int64).reshape(H, W)
        ok = ids != 0xFFFFFFFF
        d = np.where(ok, hit["t_hit"].numpy().reshape(H, W), 0.0)
        if black_top:
            d[ok & top_faces[np.where(ok, ids, 0)]] = 0.0
        cams.append((K, c2w, W, H))
        depths.append(d.astype(np.float32))
    return background, things, cams, depths


def _surfaces(background, things, black_top: bool):
    """(centres, areas, normals, owner) of what a fusion of the depth holds: the background (its
    counter top only when it returned depth) and every thing."""
    parts = []
    for k, m in enumerate(background):
        # a fusion's faces are a voxel across, not a box's two triangles per side
        m = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=0.02))
        keep = np.ones(len(m.faces), bool)
        if black_top and k == 2:
            keep = m.face_normals[:, 2] <= 0.9
        parts.append((m.triangles_center[keep], m.area_faces[keep], m.face_normals[keep], np.full(keep.sum(), -1)))
    for i, m in enumerate(things):
        parts.append((m.triangles_center, m.area_faces, m.face_normals, np.full(len(m.faces), i)))
    return tuple(np.concatenate([p[j] for p in parts]) for j in range(4))


def _infer(black_top: bool, lone: bool = False):
    from psimap.completion.freespace import check_cameras, free_votes
    from psimap.exporters.environment import Support, unseen_supports

    background, things, cams, depths = kitchen(black_top, lone)
    cameras = check_cameras(cams, depths)
    floor = Support(0.0, np.array([[-1.2, -0.7], [1.2, -0.7], [1.2, 1.3], [-1.2, 1.3]]), 4.8)
    why = {}
    found = unseen_supports(things, [floor], _surfaces(background, things, black_top),
                            lambda q: free_votes(q, cameras, 0.01), floor_z=0.0, why=why)
    return things, found, why


def test_things_on_a_black_counter_get_slabs_and_nothing_else_does():
    from psimap.exporters.environment import _in_polygon

    things, found, why = _infer(black_top=True)
    assert [u.thing for u in found] == [0, 4], (found, why)
    for u, centre in zip(found, ([-0.25, 0.25], [0.2, 0.3])):
        t = things[u.thing]
        assert abs(u.support.height - COUNTER_TOP) < 1e-6         # the thing's bottom: it stands there
        assert u.free_share <= 0.2
        # under the thing, no further out than its footprint grown by a quarter of its size
        assert _in_polygon(u.support.polygon, np.array([centre]))[0]
        reach = max(0.02, 0.25 * np.sqrt(np.prod(t.extents[:2])))
        lo, hi = u.support.polygon.min(axis=0), u.support.polygon.max(axis=0)
        assert np.all(lo >= t.bounds[0, :2] - reach - 1e-3) and np.all(hi <= t.bounds[1, :2] + reach + 1e-3), (lo, hi)
        assert u.support.area >= 0.5 * np.prod(t.extents[:2])
    # the picture: the cameras saw the space under it empty; the fragment stands alone at its
    # level; the floor box stands on the floor
    assert why[1].startswith("the space under it seen empty"), why
    assert why[2].startswith("no other thing stands at its level") or why[2].startswith("the space under it seen empty"), why
    assert why[3] == "on the floor"


def test_a_lone_thing_over_unseen_space_gets_no_slab():
    things, found, why = _infer(black_top=True, lone=True)
    assert found == [] and why[0].startswith("no other thing stands at its level"), why


def test_a_seen_counter_top_infers_nothing():
    things, found, why = _infer(black_top=False)
    assert found == [], found
    assert why[0].startswith("observed surface under it"), why


def test_the_slab_collider_is_added_to_the_static_world():
    from psimap.exporters.environment import StaticEnvironment, add_unseen_supports

    things, found, _ = _infer(black_top=True)
    env = StaticEnvironment(0.0, True)
    found = found[:1]
    found[0].name = "box_11"
    add_unseen_supports(env, found)
    (c,) = env.colliders
    assert c.name == "unseen_support_0" and c.role == "support" and c.mesh.is_watertight
    assert c.mesh.bounds[1, 2] == pytest.approx(COUNTER_TOP, abs=1e-9)
    assert env.support_under([-0.25, 0.25], COUNTER_TOP) is found[0].support
    s = env.summary()["unseen_supports"]
    assert s == [{"height": found[0].support.height, "area_m2": found[0].support.area,
                  "free_share": found[0].free_share, "thing": "box_11"}]


# ---- through `psimap export` -----------------------------------------------------------------------
def counter_checkpoint(tmp_path_factory, *, top_seen: bool):
    """A scene.ckpt of a counter by a wall, a box and a can standing on it, 10 views on a half ring.
    top_seen=False: the top is not in the map (what a black top leaves of a capture) and the views
    are a robot's camera 2 cm below the top's edge, so none looks into the open counter either;
    top_seen=True: a capture from above of a counter with its top."""
    from psimap.camera import camera_rig, look_at
    from psimap.data.frames import ClassInfo
    from psimap.scene import scene_from_meshes

    floor = _box([2.4, 2.0, 0.02], [0, 0.3, -0.01])
    wall = _box([2.4, 0.04, 1.5], [0, WALL_Y + 0.02, 0.75])
    counter = _box([1.2, 0.6, COUNTER_TOP], [0, 0.3, COUNTER_TOP / 2])
    if not top_seen:
        counter.update_faces(counter.face_normals[:, 2] < 0.9)
        counter.remove_unreferenced_vertices()
    box = _box([0.12, 0.08, 0.07], [-0.25, 0.25, COUNTER_TOP + 0.035])
    can = trimesh.creation.cylinder(radius=0.035, height=0.12, sections=24).apply_translation(
        [0.2, 0.3, COUNTER_TOP + 0.06])
    classes = [ClassInfo(1, "floor", False), ClassInfo(2, "wall", False), ClassInfo(3, "counter", False),
               ClassInfo(4, "box", True), ClassInfo(5, "can", True)]
    eye_z = 1.3 if top_seen else COUNTER_TOP - 0.02
    c2ws = [look_at([1.3 * np.sin(a), 0.3 - 1.3 * np.cos(a), eye_z], [0.0, 0.3, min(eye_z - 0.05, COUNTER_TOP)])
            for a in np.linspace(-0.9, 0.9, 10)]
    scene = scene_from_meshes([floor, wall, counter, box, can], [0, 0, 0, 11, 12], [1, 2, 3, 4, 5], classes,
                              camera_rig(c2ws, 128, 96, 100.0),
                              colors=[(0.5, 0.5, 0.5), (0.8, 0.8, 0.75), (0.1, 0.1, 0.1), (0.9, 0.2, 0.1),
                                      (0.2, 0.6, 0.2)])
    path = tmp_path_factory.mktemp("counter") / "scene.ckpt"
    scene.save(path)
    return path


@pytest.fixture(scope="module")
def black_counter_export(tmp_path_factory):
    import contextlib
    import io

    from psimap.cli import main

    out = tmp_path_factory.mktemp("export") / "counter"
    ckpt = counter_checkpoint(tmp_path_factory, top_seen=False)
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        rc = main(["export", str(ckpt), "--format", "all", "--no-preview", "--completion", "none", "--out", str(out)])
    assert rc == 0, printed.getvalue()
    # the console says it, naming the things
    assert "2 slab(s) inferred under things standing on a support no camera saw: " in printed.getvalue()
    return out


def test_things_on_an_unseen_top_rest_on_inferred_slabs(black_counter_export):
    """Both things come out dynamic and stay put: each on a slab at its bottom, in the report, the
    MJCF (read back in MuJoCo and stepped) and the USD alike."""
    import json

    import mujoco
    from pxr import Usd, UsdGeom, UsdPhysics

    rep = json.loads((black_counter_export / "report.json").read_text())
    assert rep["outcome"]["dynamic"] == 2 and rep["check"]["passed"] and rep["check"]["pinned"] == {}, rep["outcome"]
    unseen = rep["environment"]["unseen_supports"]
    assert sorted(u["thing"] for u in unseen) == ["box_11", "can_12"], unseen
    assert all(abs(u["height"] - COUNTER_TOP) < 0.015 and u["free_share"] <= 0.2 for u in unseen), unseen
    for o in rep["objects"]:
        assert not o["static"] and any(r.startswith("stands on a support no camera saw") for r in o["repair"]), o
        assert abs(o["bounds"][0][2] - COUNTER_TOP) < 0.015, o["bounds"]
    model = mujoco.MjModel.from_xml_path(str(black_counter_export / "scene.xml"))
    slabs = [model.geom(i).name for i in range(model.ngeom) if model.geom(i).name.startswith("env_unseen_support_")]
    assert len(slabs) == 2, slabs
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    start = {n: data.body(n).xpos.copy() for n in ("box_11", "can_12")}
    for _ in range(500):                    # 1 s
        mujoco.mj_step(model, data)
    for n, p in start.items():
        assert np.linalg.norm(data.body(n).xpos - p) < 0.01, (n, data.body(n).xpos, p)
    stage = Usd.Stage.Open(str(black_counter_export / "scene.usda"))
    usd = [p.GetName() for p in stage.Traverse() if p.GetName().startswith("unseen_support_")
           and p.HasAPI(UsdPhysics.CollisionAPI) and p.IsA(UsdGeom.Mesh)]
    assert sorted(usd) == sorted(s[4:] for s in slabs), (usd, slabs)


def test_the_same_counter_seen_from_above_infers_nothing(tmp_path_factory):
    """With its top in the map and seen, the things stand on the top and no slab is inferred."""
    import json

    from psimap.cli import main

    out = tmp_path_factory.mktemp("export") / "counter_seen"
    ckpt = counter_checkpoint(tmp_path_factory, top_seen=True)
    assert main(["export", str(ckpt), "--format", "mjcf", "--no-preview", "--completion", "none", "--out", str(out)]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["environment"]["unseen_supports"] == [], rep["environment"]
    assert rep["outcome"]["dynamic"] == 2 and any(abs(s["height"] - COUNTER_TOP) < 0.015
                                                  for s in rep["environment"]["supports"]), rep["outcome"]


def test_report_html_names_the_things_on_inferred_slabs(black_counter_export, tmp_path):
    import json

    from psimap.exporters.html_report import write_html

    rep = json.loads((black_counter_export / "report.json").read_text())
    write_html(tmp_path / "report.html", rep, {})
    html = (tmp_path / "report.html").read_text()
    assert "slabs inferred under box_11, can_12 (standing on a support no camera saw)" in html \
        or "slabs inferred under can_12, box_11 (standing on a support no camera saw)" in html, html[:2000]
