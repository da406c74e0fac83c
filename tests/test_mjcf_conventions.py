"""MJCF conventions (docs/outputs.md "The MJCF scene"), read back through MuJoCo: the `visual` and
`collision` default classes reach every geom, names are stable, the scene loads from any working
directory and wherever the folder is moved, and the viewer's camera frames every object."""
from __future__ import annotations

import shutil
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import trimesh


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    """A table-top export with a background (so the static world's env_ colliders are written)."""
    from psimap.exporters.objects import build_object
    from psimap.exporters.pipeline import export_scene

    table = trimesh.creation.box(extents=[0.8, 0.6, 0.4]).apply_translation([0, 0, 0.2])
    box = trimesh.creation.box(extents=[0.16, 0.07, 0.1]).apply_translation([-0.1, 0, 0.45])
    can = trimesh.creation.cylinder(radius=0.033, height=0.12, sections=32).apply_translation([0.2, 0.1, 0.46])
    toy = trimesh.creation.box(extents=[0.1, 0.1, 0.1]).apply_translation([1.2, -0.9, 0.05])
    objs = [build_object(m, lab, i + 1, completion="none")
            for i, (m, lab) in enumerate([(table, "table"), (box, "box"), (can, "can"), (toy, "toy")])]
    floor = trimesh.creation.box(extents=[3.0, 2.4, 0.02]).apply_translation([0, 0, -0.01])
    wall = trimesh.creation.box(extents=[3.0, 0.02, 1.0]).apply_translation([0, 1.21, 0.5])
    background = build_object(trimesh.util.concatenate([floor, wall]), "background", 0, completion="none")
    out = tmp_path_factory.mktemp("conventions") / "export"
    report = export_scene(objs, out, "mjcf", background=background)
    assert report["check"]["passed"], report["check"]["failures"]
    return out


def _model(path):
    import mujoco

    return mujoco.MjModel.from_xml_path(str(path))


def test_default_classes_reach_every_geom(export):
    import mujoco

    root = ET.parse(export / "scene.xml").getroot()
    geoms = {g.get("name"): g.get("class") for g in root.find("worldbody").iter("geom")}
    assert set(geoms.values()) == {"visual", "collision", None} and geoms["floor"] is None
    assert all(c is not None for n, c in geoms.items() if n != "floor")       # every other geom names its class
    m = _model(export / "scene.xml")
    by_class = {"visual": [], "collision": []}
    for g in range(m.ngeom):
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g)
        if geoms[name] is not None:
            by_class[geoms[name]].append(g)
    env = [g for g in by_class["collision"] if mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g).startswith("env_")]
    assert len(env) >= 2 and len(by_class["visual"]) == 5          # the static world; 4 objects + background
    for g in by_class["visual"]:        # drawn, no mass, never collides
        assert (m.geom_group[g], m.geom_contype[g], m.geom_conaffinity[g]) == (2, 0, 0)
    for g in by_class["collision"]:     # hidden by default, collides
        assert m.geom_group[g] == 3 and m.geom_contype[g] == 1 and m.geom_conaffinity[g] == 1
    # what the object's class says, not the class default, for the friction of an object's collider
    can = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "can_3_collision_0")
    assert m.geom_friction[can][0] == pytest.approx(0.4) and m.geom_friction[env[0]][0] == pytest.approx(0.8)
    # density 0 on every geom: the explicit <inertial> is the body's whole mass
    box = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "box_2")
    assert m.body_mass[box] == pytest.approx(0.16 * 0.07 * 0.1 * 200.0, rel=1e-3)
    # one switch hides every collider: the viewer's group 3 toggle
    opt = mujoco.MjvOption()
    assert opt.geomgroup[3] == 0 and opt.geomgroup[2] == 1


def test_names_are_stable_and_meshes_sit_under_the_meshdir(export):
    root = ET.parse(export / "scene.xml").getroot()
    assert root.find("compiler").get("meshdir") == "assets" and root.find("compiler").get("texturedir") == "assets"
    bodies = [b.get("name") for b in root.iter("body")]
    assert bodies == ["background_0", "table_1", "box_2", "can_3", "toy_4"]
    for b in root.iter("body"):
        names = [g.get("name") for g in b.iter("geom")]
        assert names[0] == f"{b.get('name')}_visual"
        assert names[1:] == [f"{b.get('name')}_collision_{k}" for k in range(len(names) - 1)]
    for el in root.find("asset"):
        if el.get("file"):
            assert "/" not in el.get("file") and (export / "assets" / el.get("file")).is_file()


def test_scene_loads_from_any_working_directory_and_when_moved(export, tmp_path, monkeypatch):
    m0 = _model(export / "scene.xml")
    monkeypatch.chdir(tmp_path)
    assert _model(export / "scene.xml").nmesh == m0.nmesh
    moved = tmp_path / "elsewhere" / "my scene"
    shutil.copytree(export, moved)
    monkeypatch.chdir(moved.parent)
    m = _model("my scene/scene.xml")          # a relative path, from the folder above
    assert m.nmesh == m0.nmesh and m.ntex == m0.ntex
    np.testing.assert_array_equal(m.mesh_vert, m0.mesh_vert)


def test_the_viewer_frames_every_object(export):
    """MuJoCo's free camera (the viewer's start) and the fixed `overview` camera coincide and see
    every object's centre inside the image, none closer than 10 % of the frame to its edge."""
    import mujoco

    m = _model(export / "scene.xml")
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    free = mujoco.MjvCamera()
    mujoco.mjv_defaultFreeCamera(m, free)
    scn, opt = mujoco.MjvScene(m, maxgeom=1000), mujoco.MjvOption()
    mujoco.mjv_updateScene(m, d, opt, None, free, mujoco.mjtCatBit.mjCAT_ALL, scn)
    eye = np.asarray(scn.camera[0].pos) + np.asarray(scn.camera[1].pos)
    cam = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, "overview")
    np.testing.assert_allclose(eye / 2, d.cam_xpos[cam], atol=1e-3)
    R = d.cam_xmat[cam].reshape(3, 3)
    np.testing.assert_allclose(-R[:, 2], scn.camera[0].forward, atol=1e-3)
    half = np.tan(np.radians(m.cam_fovy[cam]) / 2)
    for b in range(1, m.nbody):
        if m.body_geomnum[b] and mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) != "background_0":
            x, y, z = (d.xipos[b] - d.cam_xpos[cam]) @ R
            assert z < 0                                            # in front (the camera looks along -z)
            assert abs(y / -z) < 0.9 * half and abs(x / -z) < 0.9 * half * 4 / 3, mujoco.mj_id2name(
                m, mujoco.mjtObj.mjOBJ_BODY, b)
    # the statistic is the objects' bounds (table corner to toy), not the room's around them
    np.testing.assert_allclose(m.stat.center, [(-0.4 + 1.25) / 2, (-0.95 + 0.3) / 2, 0.52 / 2], atol=5e-3)
    assert m.stat.extent < 2.0
