"""Issue #16 through the whole export: a static world that collides, gravity that points down,
objects that rest, honest masses, honest outcomes.

The scene is the one a user brings from a desk: a stuff-class (or unlabelled) desk standing on the
floor by a wall, and on it a box, a mug (a real open cup: a wall around air) and a foam block. It is
turned into the frames phones (Y-up) and robots (z down) use. Everything is read back the way its
consumer reads it: the MJCF in MuJoCo, the USD through pxr.
"""
from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import trimesh

from psimap.data.frames import ClassInfo

CLASSES = [ClassInfo(1, "floor", False), ClassInfo(2, "wall", False), ClassInfo(3, "table", False),
           ClassInfo(4, "box", True), ClassInfo(5, "mug", True), ClassInfo(6, "foam block", True)]
DESK_TOP = 0.74
WALL_Y = 0.62


def cup(r=0.045, h=0.1, wall=0.006):
    outer = trimesh.creation.cylinder(radius=r, height=h, sections=32).apply_translation([0, 0, h / 2])
    inner = trimesh.creation.cylinder(radius=r - wall, height=h, sections=32).apply_translation([0, 0, h / 2 + wall])
    return trimesh.boolean.difference([outer, inner], engine="manifold")


def desk_scene(desk_labelled: bool = True):
    """meshes, instance ids, semantic ids, colours of the desk scene (world Z-up)."""
    floor = trimesh.creation.box(extents=[2.4, 2.0, 0.02]).apply_translation([0, 0, -0.01])
    wall = trimesh.creation.box(extents=[2.4, 0.04, 1.5]).apply_translation([0, WALL_Y + 0.02, 0.75])
    top = trimesh.creation.box(extents=[1.1, 0.6, 0.04]).apply_translation([0, 0.25, DESK_TOP - 0.02])
    legs = [trimesh.creation.box(extents=[0.05, 0.05, DESK_TOP - 0.04]).apply_translation(
        [x, y, (DESK_TOP - 0.04) / 2]) for x in (-0.5, 0.5) for y in (0.0, 0.5)]
    desk = trimesh.util.concatenate([top, *legs])
    box = trimesh.creation.box(extents=[0.12, 0.08, 0.07]).apply_translation([-0.25, 0.2, DESK_TOP + 0.035])
    mug = cup().apply_translation([0.05, 0.3, DESK_TOP])
    foam = trimesh.creation.box(extents=[0.1, 0.1, 0.05]).apply_translation([0.3, 0.15, DESK_TOP + 0.025])
    meshes = [floor, wall, desk, box, mug, foam]
    iids = [0, 0, 0, 11, 12, 13]
    sids = [1, 2, 3 if desk_labelled else 0, 4, 5, 6]
    colors = [(0.5, 0.5, 0.5), (0.8, 0.8, 0.75), (0.55, 0.35, 0.2), (0.9, 0.2, 0.1), (0.1, 0.3, 0.9),
              (0.9, 0.9, 0.2)]
    return meshes, iids, sids, colors


def checkpoint(tmp_path_factory, *, desk_labelled=True, rotation=None):
    """A scene.ckpt of the desk scene seen from 10 views (128x96) on a half ring in front of the desk."""
    from psimap.camera import camera_rig, look_at
    from psimap.scene import scene_from_meshes

    meshes, iids, sids, colors = desk_scene(desk_labelled)
    target = np.array([0.0, 0.25, DESK_TOP])
    c2ws = [look_at(np.array([1.1 * np.sin(a), 0.25 - 1.1 * np.cos(a), 1.35]), target)
            for a in np.linspace(-1.2, 1.2, 10)]
    cams = camera_rig(c2ws, 128, 96, 100.0)
    scene = scene_from_meshes(meshes, iids, sids, CLASSES, cams, colors=colors)
    if rotation is not None:
        scene = scene.rotated(rotation)
    path = tmp_path_factory.mktemp("desk") / "scene.ckpt"
    scene.save(path)
    return path


@pytest.fixture(scope="module")
def export_dir(tmp_path_factory):
    """The desk scene exported in every format (completion none: the scan sees the objects whole)."""
    from psimap.cli import main

    ckpt = checkpoint(tmp_path_factory)
    out = tmp_path_factory.mktemp("export") / "desk"
    rc = main(["export", str(ckpt), "--format", "all", "--completion", "none", "--out", str(out)])
    assert rc == 0
    return out


def _report(out):
    return json.loads((out / "report.json").read_text())


def test_things_rest_on_the_stuff_desk(export_dir):
    rep = _report(export_dir)
    by = {o["class"]: o for o in rep["objects"]}
    assert set(by) == {"box", "mug", "foam block"} and not rep["skipped"]
    out = rep["outcome"]
    assert out["passed"] and out["dynamic"] == 3 and out["pinned"] == 0, out
    assert rep["check"]["passed"] and rep["check"]["pinned"] == {}
    assert rep["check"]["max_drift"] < 0.01
    # the desk top is a support with its own flat collider; the floor is the floor, not the
    # lowest point and not the desk
    env = rep["environment"]
    assert env["floor_observed"] and abs(env["floor_z"]) < 0.01
    assert any(abs(s["height"] - DESK_TOP) < 0.01 for s in env["supports"])
    assert env["colliders"]["support"] >= 1 and env["colliders"]["wall"] >= 1
    # the objects stand on it: flat bottoms at the desk's height
    for o in rep["objects"]:
        assert abs(o["bounds"][0][2] - DESK_TOP) < 0.012, (o["name"], o["bounds"])


def _mjcf_env(xml):
    root = ET.parse(xml).getroot()
    return {g.get("name"): g for g in root.iter("geom") if g.get("name", "").startswith("env_")}


def test_mjcf_and_usd_have_the_same_static_world(export_dir):
    """The same colliders in both formats, at the same place (read back as each consumer reads)."""
    import mujoco
    from pxr import Usd, UsdGeom, UsdPhysics

    model = mujoco.MjModel.from_xml_path(str(export_dir / "scene.xml"))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    mj = {}
    for name in _mjcf_env(export_dir / "scene.xml"):
        g = model.geom(name)
        mid = model.geom_dataid[g.id]
        v = model.mesh_vert[model.mesh_vertadr[mid]:model.mesh_vertadr[mid] + model.mesh_vertnum[mid]]
        R = data.geom_xmat[g.id].reshape(3, 3)
        world = v @ R.T + data.geom_xpos[g.id]
        mj[name[4:]] = (world.min(0), world.max(0))
    stage = Usd.Stage.Open(str(export_dir / "scene.usda"))
    cache = UsdGeom.XformCache()
    usd = {}
    for prim in stage.Traverse():
        if str(prim.GetPath()).startswith("/World/environment/") and prim.HasAPI(UsdPhysics.CollisionAPI):
            pts = np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get(), np.float64)
            M = np.asarray(cache.GetLocalToWorldTransform(prim), np.float64)
            world = pts @ M[:3, :3] + M[3, :3]
            usd[prim.GetName()] = (world.min(0), world.max(0))
            assert UsdPhysics.MeshCollisionAPI(prim).GetApproximationAttr().Get() == "convexHull"
            assert not prim.HasAPI(UsdPhysics.RigidBodyAPI)
    assert set(mj) == set(usd) and len(mj) >= 3
    for k in mj:
        np.testing.assert_allclose(mj[k][0], usd[k][0], atol=1e-4)
        np.testing.assert_allclose(mj[k][1], usd[k][1], atol=1e-4)
    # the background itself collides nowhere (its triangle soup is not the world's collider)
    bg = [p for p in stage.Traverse() if "background" in str(p.GetPath()) and p.HasAPI(UsdPhysics.CollisionAPI)]
    assert bg == []


def test_box_pushed_into_the_wall_stops(export_dir):
    """The box, shoved towards the wall along the desk, stops at the wall's collider."""
    import mujoco

    model = mujoco.MjModel.from_xml_path(str(export_dir / "scene.xml"))
    data = mujoco.MjData(model)
    name = [b for b in (model.body(i).name for i in range(model.nbody)) if b.startswith("box_")][0]
    body = model.body(name)
    dof = model.body_dofadr[body.id]
    mujoco.mj_forward(model, data)
    data.qvel[dof:dof + 3] = [0.0, 2.5, 0.0]
    for _ in range(750):
        mujoco.mj_step(model, data)
    y = data.xpos[body.id][1]
    assert 0.35 < y < WALL_Y, y                       # reached the wall, never through it
    assert data.xpos[body.id][2] > DESK_TOP           # still on the desk


def test_mug_is_weighed_as_a_shell(export_dir):
    rep = _report(export_dir)
    mug = [o for o in rep["objects"] if o["class"] == "mug"][0]["physics"]
    assert mug["mass_model"] == "shell" and mug["density_key"] == "shell:mug"
    lo, hi = mug["mass_range_kg"]
    # a ceramic mug this size weighs 0.25-0.4 kg; its scan's shell weighed 0.301 kg with the
    # packages of 2026-11-28 (the former bound 0.3 failed by 1 g); its 0.79 l as solid ceramic
    # (2400 kg/m^3) would be 1.9 kg
    assert lo < mug["mass_kg"] < hi and 0.08 < mug["mass_kg"] < 0.4
    box = [o for o in rep["objects"] if o["class"] == "box"][0]["physics"]
    assert box["mass_model"] == "solid" and box["mass_range_kg"][0] < box["mass_kg"] < box["mass_range_kg"][1]


def test_visual_meshes_stay_small(export_dir):
    for o in _report(export_dir)["objects"]:
        assert o["faces_after"] <= o["face_budget"] <= max(200, o["faces_before"]), o["name"]
        assert o["faces_after"] <= 3000, (o["name"], o["faces_after"])


FRAMES = {"y-up": [[1, 0, 0], [0, 0, 1], [0, -1, 0]],       # z -> y: what phones give
          "z-down": [[1, 0, 0], [0, -1, 0], [0, 0, -1]]}    # a robot base with z down


@pytest.mark.parametrize("frame", list(FRAMES))
def test_a_turned_capture_exports_like_the_z_up_one(tmp_path_factory, export_dir, frame):
    from psimap.cli import main

    R = np.asarray(FRAMES[frame], np.float64)
    ckpt = checkpoint(tmp_path_factory, rotation=R)
    out = tmp_path_factory.mktemp("turned") / frame
    assert main(["export", str(ckpt), "--format", "mjcf", "--completion", "none", "--out", str(out)]) == 0
    a, b = _report(export_dir), _report(out)
    np.testing.assert_allclose(b["gravity"]["input_up"], R @ [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(np.asarray(b["gravity"]["rotation"]) @ R, np.eye(3), atol=1e-9)
    assert [(o["name"], o["static"]) for o in a["objects"]] == [(o["name"], o["static"]) for o in b["objects"]]
    assert b["outcome"]["dynamic"] == a["outcome"]["dynamic"] == 3
    for oa, ob in zip(a["objects"], b["objects"]):
        np.testing.assert_allclose(ob["bounds"], oa["bounds"], atol=0.01)
        assert abs(ob["physics"]["mass_kg"] / oa["physics"]["mass_kg"] - 1) < 0.05
    assert abs(b["environment"]["floor_z"] - a["environment"]["floor_z"]) < 0.01


def test_an_unlabelled_desk_holds_things_too(tmp_path_factory):
    from psimap.exporters.pipeline import export_scene
    from psimap.scene import load_scene

    ckpt = checkpoint(tmp_path_factory, desk_labelled=False)
    rep = export_scene(load_scene(ckpt), tmp_path_factory.mktemp("void") / "o", "mjcf", completion="none")
    assert rep["outcome"]["dynamic"] == 3 and rep["check"]["pinned"] == {}, rep["outcome"]
    assert any(abs(s["height"] - DESK_TOP) < 0.01 for s in rep["environment"]["supports"])


def test_export_fails_loudly_when_most_things_are_pinned(tmp_path_factory, capsys):
    """Two things on a steep unlabelled ramp slide off and are pinned: no success to report."""
    from psimap.camera import camera_rig, look_at
    from psimap.cli import main
    from psimap.scene import scene_from_meshes

    floor = trimesh.creation.box(extents=[2.0, 2.0, 0.02]).apply_translation([0, 0, -0.01])
    T = trimesh.transformations.rotation_matrix(np.radians(40), [1, 0, 0])
    ramp = trimesh.creation.box(extents=[0.8, 0.8, 0.05]).apply_transform(T).apply_translation([0, 0, 0.3])
    n_up = T[:3, 2]
    boxes = [trimesh.creation.box(extents=[0.1, 0.1, 0.1]).apply_transform(T).apply_translation(
        np.array([x, 0.0, 0.3]) + n_up * (0.025 + 0.05 + 0.015)) for x in (-0.2, 0.2)]   # 1.5 cm clear
    w, h, n = 96, 72, 8
    c2ws = [look_at(np.array([1.2 * np.cos(a), 1.2 * np.sin(a), 1.0]), [0, 0, 0.3])
            for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]
    cams = camera_rig(c2ws, w, h, 75.0)
    scene = scene_from_meshes([floor, ramp, *boxes], [0, 0, 21, 22], [1, 0, 4, 4], CLASSES, cams)
    ckpt = tmp_path_factory.mktemp("ramp") / "scene.ckpt"
    scene.save(ckpt)
    out = tmp_path_factory.mktemp("ramp_out") / "o"
    rc = main(["export", str(ckpt), "--format", "mjcf", "--completion", "none", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 2
    assert text.splitlines()[0].startswith("FAILED: 0 of 2 thing(s) dynamic, 2 pinned static (unstable)"), text
    rep = _report(out)
    assert not rep["outcome"]["passed"] and rep["outcome"]["pinned"] == 2
    # the user can accept it
    out2 = tmp_path_factory.mktemp("ramp_ok") / "o"
    assert main(["export", str(ckpt), "--format", "mjcf", "--completion", "none", "--out", str(out2),
                 "--min-dynamic", "0"]) == 0


def test_newton_settles_the_desk_like_mujoco(export_dir, capsys):
    """The second engine on the demo-like export: scene.usda in Newton (CPU, XPBD) agrees with
    MuJoCo on scene.xml. Issue #19 saw a ball thrown 1.2 m up in Newton: the USD gave the fused
    background a triangle-mesh collider the MJCF lacked, and things start inside a fused surface
    (this desk's top: 10.9 mm deep in Newton, box moved 5 cm, MuJoCo passed). The background is
    visual only now; both engines collide with the same static world."""
    pytest.importorskip("newton_usd_schemas")
    pytest.importorskip("newton")
    from psimap.cli import main

    assert main(["check", str(export_dir), "--engine", "all", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    mj, nw = rep["mujoco"], rep["newton"]
    assert mj["passed"] and nw["passed"], (mj["failures"], nw["failures"])
    assert set(nw["drift"]) == set(mj["drift"]) and len(nw["drift"]) == 3
    assert nw["max_drift"] <= 0.01 and mj["max_drift"] <= 0.01
    # the same deepest contact at t = 0 (measured -0.43 mm in both)
    assert nw["min_contact_dist"] == pytest.approx(mj["min_contact_dist"], abs=3e-4)
    assert nw["static_bodies"] == mj["static_bodies"]


def test_no_export_step_spends_more_system_than_user_time(export_dir):
    """timings.json: wall, user and system seconds of every step (exporters.clock); system time
    above user time is threads spinning or memory churn, not the step's work (issue #20)."""
    from psimap.exporters import clock

    t = json.loads((export_dir / "timings.json").read_text())
    names = clock.steps(t)
    assert {"objects", "instance_meshes", "environment", "repair", "decimation", "collision", "texture",
            "check", "mjcf", "usd", "glb", "writers", "total"} <= set(names)
    assert t["total_s"] >= t["objects_s"] >= t["instance_meshes_s"] > 0
    assert t["total_user_s"] + t["total_sys_s"] >= t["objects_user_s"] > 0
    for n in names:
        user, system = t[n + "_user_s"], t[n + "_sys_s"]
        if user + system >= 0.5:        # below it, rusage's clock ticks are noise
            assert system <= user, (n, user, system)
