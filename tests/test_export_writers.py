"""What the writers put in the files, read back by the consumers' own libraries: MuJoCo compiles
scene.xml, pxr composes scene.usda, trimesh loads scene.glb. Every body / prim / node must sit
where report.json says (bounds, centre of mass, the settle check's nudges), carry the mass, inertia
and friction computed for it, and keep every collider part. The oracles are independent of the
writers: analytic box inertia, trimesh's mass properties, the report and the collision/ folder.

One export (all formats, with the simulation check) of a small scene serves every test:
  cracker_box_1  a box on the floor (box primitive)
  can_2          a can sunk 1 cm into the box's top: the check lifts it (a non-zero nudge)
  book_3         a box turned 0.6 rad about z: principal axes off the world axes
  toy_4          an L-shaped solid: a convex decomposition (several hull parts)
"""
from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import trimesh

BOOK_EXTENTS = (0.16, 0.06, 0.05)
BOOK_YAW = 0.6


def _scene_meshes():
    box = trimesh.creation.box(extents=[0.2, 0.1, 0.08]).apply_translation([0, 0, 0.04])
    can = trimesh.creation.cylinder(radius=0.04, height=0.14, sections=24).apply_translation([0.05, 0, 0.14])
    book = trimesh.creation.box(extents=BOOK_EXTENTS).apply_transform(
        trimesh.transformations.rotation_matrix(BOOK_YAW, [0, 0, 1])).apply_translation([-0.35, 0.2, 0.025])
    toy = trimesh.boolean.union([trimesh.creation.box(extents=[0.3, 0.06, 0.06]),
                                 trimesh.creation.box(extents=[0.06, 0.06, 0.3]).apply_translation([0.12, 0, 0.18])],
                                engine="manifold").apply_translation([0.5, -0.4, 0.03])
    return [(box, "cracker box"), (can, "can"), (book, "book"), (toy, "toy")]


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    from psimap.exporters.objects import build_object
    from psimap.exporters.pipeline import export_scene

    objs = [build_object(m, label, i + 1, completion="none", max_hulls=4)
            for i, (m, label) in enumerate(_scene_meshes())]
    out = tmp_path_factory.mktemp("writers") / "export"
    report = export_scene(objs, out, "all")
    assert report["check"]["passed"], report["check"]["failures"]
    on_disk = json.loads((out / "report.json").read_text())
    return out, on_disk, {o.name: o for o in objs}


def _entries(report):
    return {e["name"]: e for e in report["objects"]}


def _nudge(report, name):
    """[3] the settle check's nudge of `name` (m; zero when it was not moved)."""
    return np.asarray(report["check"]["nudges"].get(name, (0.0, 0.0, 0.0)), np.float64)


def test_the_scene_exercises_what_the_writers_must_get_right(exported):
    _, report, objs = exported
    e = _entries(report)
    assert sorted(e) == ["book_3", "can_2", "cracker_box_1", "toy_4"]
    assert report["check"]["nudges"]["can_2"] == pytest.approx([0, 0, 0.0104], abs=1.5e-3)   # lifted out of the box
    assert set(report["check"]["nudges"]) == {"can_2"}
    assert e["toy_4"]["collision"]["kind"] == "decomposition" and e["toy_4"]["collision"]["hull_count"] >= 2
    assert e["book_3"]["collision"]["kind"] == "box"
    # the book's principal axes are turned (the writers must rotate the inertia, not drop it)
    axes = objs["book_3"].physics.principal_axes
    assert np.abs(np.abs(axes) - np.eye(3)).max() > 0.3
    assert not any(o["static"] for o in e.values())
    # the class tables reached each object (exporters.physics DENSITY_KG_M3 / FRICTION)
    assert {n: o["physics"]["density_kg_m3"] for n, o in e.items()} == {
        "cracker_box_1": 200.0, "can_2": 900.0, "book_3": 700.0, "toy_4": 300.0}
    assert {n: o["physics"]["friction"] for n, o in e.items()} == {
        "cracker_box_1": 0.5, "can_2": 0.4, "book_3": 0.5, "toy_4": 0.7}


def _expected_world_inertia(obj) -> np.ndarray:
    """Inertia about the COM in world axes from trimesh (an independent integration) x density."""
    return np.asarray(obj.mesh.moment_inertia) * obj.physics.density


def test_book_inertia_is_the_rotated_analytic_box(exported):
    _, report, objs = exported
    a, b, c = BOOK_EXTENTS
    m = a * b * c * 700.0                                   # "book": 700 kg/m^3
    local = m / 12 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])
    R = trimesh.transformations.rotation_matrix(BOOK_YAW, [0, 0, 1])[:3, :3]
    ph = objs["book_3"].physics
    assert ph.mass == pytest.approx(m, rel=1e-9)
    np.testing.assert_allclose(ph.inertia, R @ local @ R.T, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(_entries(report)["book_3"]["physics"]["com"], [-0.35, 0.2, 0.025], atol=1e-9)


# ---------------------------------------------------------------- MJCF, compiled by MuJoCo

@pytest.fixture(scope="module")
def mj(exported):
    import mujoco

    out, _, _ = exported
    m = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    return m, d


def test_mjcf_bodies_mass_inertia_and_placement(exported, mj):
    import mujoco

    _, report, objs = exported
    m, d = mj
    for name, e in _entries(report).items():
        b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)
        ph = objs[name].physics
        # the body frame is the COM, lifted by the check's nudge
        np.testing.assert_allclose(d.xpos[b], np.asarray(e["physics"]["com"]) + _nudge(report, name),
                                   atol=1e-6, err_msg=name)
        np.testing.assert_allclose(d.xipos[b], d.xpos[b], atol=1e-9, err_msg=name)
        assert m.body_mass[b] == pytest.approx(e["physics"]["mass_kg"], rel=1e-6), name
        # world inertia = R diag(I) R^T from MuJoCo's compiled principal frame
        R = d.ximat[b].reshape(3, 3)
        world = R @ np.diag(m.body_inertia[b]) @ R.T
        np.testing.assert_allclose(world, _expected_world_inertia(objs[name]), rtol=1e-4,
                                   atol=1e-5 * np.abs(ph.principal_inertia).max(), err_msg=name)


def test_mjcf_colliders_friction_and_parts(exported, mj):
    import mujoco

    out, report, objs = exported
    m, d = mj
    for name, e in _entries(report).items():
        b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)
        geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] == b and m.geom_group[g] == 3]
        col = e["collision"]
        assert len(geoms) == max(1, col["hull_count"]) == len(e["files"]["collision"]), name
        for g in geoms:
            assert m.geom_friction[g][0] == pytest.approx(e["physics"]["friction"]), name
            assert m.geom_contype[g] and m.geom_conaffinity[g], name
        # every collider part sits on its world-frame copy in collision/ (lifted by the nudge)
        lift = _nudge(report, name)
        for k, g in enumerate(sorted(geoms)):
            part = trimesh.load(out / e["files"]["collision"][k], process=False)
            centre = part.bounds.mean(axis=0) + lift
            if col["kind"] == "decomposition":
                mesh_id = m.geom_dataid[g]
                start, count = m.mesh_vertadr[mesh_id], m.mesh_vertnum[mesh_id]
                verts = m.mesh_vert[start:start + count] @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g]
                np.testing.assert_allclose(verts.min(0), part.bounds[0] + lift, atol=1e-5, err_msg=name)
                np.testing.assert_allclose(verts.max(0), part.bounds[1] + lift, atol=1e-5, err_msg=name)
            else:
                np.testing.assert_allclose(d.geom_xpos[g], centre, atol=2e-3, err_msg=name)
                # the primitive's axes: its size along each world axis matches the part's extents
                R = d.geom_xmat[g].reshape(3, 3)
                if col["kind"] == "box":
                    half = np.abs(R) @ m.geom_size[g]
                    np.testing.assert_allclose(2 * half, part.extents, atol=2e-3, err_msg=name)


def test_mjcf_visual_meshes_land_on_the_object(exported, mj):
    import mujoco

    _, report, _ = exported
    m, d = mj
    for name, e in _entries(report).items():
        g = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"{name}_visual")
        mesh_id = m.geom_dataid[g]
        start, count = m.mesh_vertadr[mesh_id], m.mesh_vertnum[mesh_id]
        verts = m.mesh_vert[start:start + count] @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g]
        lo, hi = np.asarray(e["bounds"]) + _nudge(report, name)
        np.testing.assert_allclose(verts.min(0), lo, atol=1e-5, err_msg=name)
        np.testing.assert_allclose(verts.max(0), hi, atol=1e-5, err_msg=name)
        assert m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0


def test_mjcf_writes_every_body_with_a_freejoint(exported):
    out, report, _ = exported
    root = ET.parse(out / "scene.xml").getroot()
    bodies = {b.get("name"): b for b in root.iter("body")}
    for name in _entries(report):
        assert bodies[name].find("freejoint") is not None, name


# ---------------------------------------------------------------- USD, composed by pxr

@pytest.fixture(scope="module")
def stage(exported):
    from pxr import Usd

    out, _, _ = exported
    return Usd.Stage.Open(str(out / "scene.usda"))


def _world_points(prim, cache):
    from pxr import UsdGeom

    pts = np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get(), np.float64)
    M = np.asarray(cache.GetLocalToWorldTransform(prim), np.float64)     # row-vector convention
    return pts @ M[:3, :3] + M[3, :3]


def test_usd_prims_sit_where_the_report_says(exported, stage):
    from pxr import Usd, UsdGeom

    _, report, _ = exported
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    for name, e in _entries(report).items():
        prim = stage.GetPrimAtPath(f"/World/{name}")
        M = np.asarray(cache.GetLocalToWorldTransform(prim), np.float64)
        np.testing.assert_allclose(M[:3, :3], np.eye(3), atol=1e-12, err_msg=name)
        np.testing.assert_allclose(M[3, :3], np.asarray(e["physics"]["com"]) + _nudge(report, name),
                                   atol=1e-6, err_msg=name)
        pts = _world_points(stage.GetPrimAtPath(f"/World/{name}/visual"), cache)
        lo, hi = np.asarray(e["bounds"]) + _nudge(report, name)
        np.testing.assert_allclose(pts.min(0), lo, atol=1e-5, err_msg=name)
        np.testing.assert_allclose(pts.max(0), hi, atol=1e-5, err_msg=name)


def test_usd_colliders_every_part_in_place(exported, stage):
    from pxr import Usd, UsdGeom, UsdPhysics

    out, report, _ = exported
    bbox = UsdGeom.BBoxCache(Usd.TimeCode.Default(), [UsdGeom.Tokens.guide])
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    for name, e in _entries(report).items():
        parts = [c for c in stage.GetPrimAtPath(f"/World/{name}").GetChildren()
                 if c.GetName().startswith("collision_")]
        assert len(parts) == max(1, e["collision"]["hull_count"]), name
        lift = _nudge(report, name)
        for k, prim in enumerate(sorted(parts, key=lambda p: p.GetName())):
            assert prim.HasAPI(UsdPhysics.CollisionAPI), name
            ref = trimesh.load(out / e["files"]["collision"][k], process=False)
            if prim.IsA(UsdGeom.Mesh):
                pts = _world_points(prim, cache)
                np.testing.assert_allclose(pts.min(0), ref.bounds[0] + lift, atol=1e-5, err_msg=name)
                np.testing.assert_allclose(pts.max(0), ref.bounds[1] + lift, atol=1e-5, err_msg=name)
            else:
                world = bbox.ComputeWorldBound(prim)
                np.testing.assert_allclose(np.asarray(world.ComputeCentroid()), ref.bounds.mean(0) + lift,
                                           atol=2e-3, err_msg=name)
                if e["collision"]["kind"] == "box":     # a cube's extent box is the box itself
                    rng = world.ComputeAlignedRange()
                    np.testing.assert_allclose(rng.GetMin(), ref.bounds[0] + lift, atol=1e-5, err_msg=name)
                    np.testing.assert_allclose(rng.GetMax(), ref.bounds[1] + lift, atol=1e-5, err_msg=name)


def test_usd_mass_inertia_and_friction(exported, stage):
    from pxr import UsdPhysics, UsdShade

    _, report, objs = exported
    for name, e in _entries(report).items():
        prim = stage.GetPrimAtPath(f"/World/{name}")
        assert prim.HasAPI(UsdPhysics.RigidBodyAPI) and prim.HasAPI(UsdPhysics.MassAPI), name
        api = UsdPhysics.MassAPI(prim)
        assert api.GetMassAttr().Get() == pytest.approx(e["physics"]["mass_kg"], rel=1e-6), name
        np.testing.assert_allclose(api.GetCenterOfMassAttr().Get(), [0, 0, 0], atol=1e-9)
        diag = np.asarray(api.GetDiagonalInertiaAttr().Get(), np.float64)
        q = api.GetPrincipalAxesAttr().Get()
        w, xyz = q.GetReal(), np.asarray(q.GetImaginary(), np.float64)
        from scipy.spatial.transform import Rotation

        R = Rotation.from_quat([*xyz, w]).as_matrix()
        np.testing.assert_allclose(R @ np.diag(diag) @ R.T, _expected_world_inertia(objs[name]), rtol=1e-4,
                                   atol=1e-5 * diag.max(), err_msg=name)
        # the physics material bound to the colliders carries the object's friction
        for child in prim.GetChildren():
            if not child.HasAPI(UsdPhysics.CollisionAPI):
                continue
            mat, _ = UsdShade.MaterialBindingAPI(child).ComputeBoundMaterial("physics")
            assert mat, (name, child.GetName())
            phys = UsdPhysics.MaterialAPI(mat.GetPrim())
            assert phys.GetStaticFrictionAttr().Get() == pytest.approx(e["physics"]["friction"]), name
            assert phys.GetDynamicFrictionAttr().Get() == pytest.approx(e["physics"]["friction"]), name


# ---------------------------------------------------------------- GLB, loaded by trimesh

def test_glb_has_every_object_y_up_where_the_report_says(exported):
    out, report, _ = exported
    scene = trimesh.load(out / "scene.glb")
    assert isinstance(scene, trimesh.Scene)
    entries = _entries(report)
    nodes = {n for n in scene.graph.nodes_geometry}
    assert nodes == set(entries)
    for name, e in entries.items():
        T, geom = scene.graph[name]
        mesh = scene.geometry[geom]
        assert len(mesh.faces) == e["faces_after"], name
        pts = trimesh.transform_points(mesh.vertices, T)
        lo, hi = np.asarray(e["bounds"]) + _nudge(report, name)
        # glTF is Y-up: world (x, y, z) -> (x, z, -y)
        np.testing.assert_allclose(pts.min(0), [lo[0], lo[2], -hi[1]], atol=1e-5, err_msg=name)
        np.testing.assert_allclose(pts.max(0), [hi[0], hi[2], -lo[1]], atol=1e-5, err_msg=name)
