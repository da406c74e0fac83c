"""Static furniture: per-class static rule (exporters.physics), MJCF without freejoint, USD without
RigidBodyAPI, report.json "static", the sim check treats them as supports; the CLI override."""
from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import pytest
import trimesh

from psimap import PsimapError


def test_static_class_rule_and_override():
    from psimap.exporters.physics import STATIC_CLASSES, is_static_class, parse_static_classes

    for label in ("table", "coffee table", "dining_tables", "Kitchen Cabinet", "bookshelf", "sofa"):
        assert is_static_class(label), label
    for label in ("mug", "chair", "box", "bottle", "tablet"):
        assert not is_static_class(label), label
    assert parse_static_classes("") == STATIC_CLASSES
    assert parse_static_classes("none") == frozenset() and parse_static_classes("table", True) == frozenset()
    custom = parse_static_classes("Mug, water bottle")
    assert custom == {"mug", "water_bottle"}
    assert is_static_class("mug", custom) and is_static_class("water bottle", custom)
    assert not is_static_class("table", custom) and not is_static_class("table", frozenset())
    with pytest.raises(PsimapError, match="static-classes"):
        parse_static_classes(" , ,")


def _scene():
    from psimap.exporters.objects import build_object

    table = trimesh.creation.box(extents=[0.8, 0.6, 0.4]).apply_translation([0, 0, 0.2])
    box = trimesh.creation.box(extents=[0.12, 0.08, 0.1]).apply_translation([0.1, 0.05, 0.45])
    return [build_object(m, lab, i + 1, completion="none") for i, (m, lab) in enumerate([(table, "table"),
                                                                                          (box, "box")])]


@pytest.fixture(scope="module")
def objects():
    return _scene()


def _bodies(xml):
    return {b.get("name"): b for b in ET.parse(xml).getroot().iter("body")}


def test_static_furniture_exported_static(objects, tmp_path):
    from pxr import Usd, UsdPhysics

    from psimap.exporters.pipeline import export_scene

    r = export_scene(objects, tmp_path / "s", ["mjcf", "usd"])
    b = _bodies(tmp_path / "s" / "scene.xml")
    assert b["table_1"].find("freejoint") is None and b["table_1"].find("inertial") is None
    import mujoco

    m = mujoco.MjModel.from_xml_path(str(tmp_path / "s" / "scene.xml"))     # groups come from classes
    table = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "table_1")
    assert [int(m.geom_group[g]) for g in range(m.ngeom) if m.geom_bodyid[g] == table] == [2, 3]
    assert b["box_2"].find("freejoint") is not None and b["box_2"].find("inertial") is not None
    stage = Usd.Stage.Open(str(tmp_path / "s" / "scene.usda"))
    table = stage.GetPrimAtPath("/World/table_1")
    assert not table.HasAPI(UsdPhysics.RigidBodyAPI) and not table.HasAPI(UsdPhysics.MassAPI)
    assert stage.GetPrimAtPath("/World/table_1/collision_0").HasAPI(UsdPhysics.CollisionAPI)
    assert stage.GetPrimAtPath("/World/box_2").HasAPI(UsdPhysics.RigidBodyAPI)
    assert r["usd_validation"]["errors"] == []
    rep = json.loads((tmp_path / "s" / "report.json").read_text())
    e = {o["name"]: o for o in rep["objects"]}
    assert e["table_1"]["static"] is True and "static furniture" in e["table_1"]["static_reason"]
    assert e["box_2"]["static"] is False and e["box_2"]["static_reason"] is None
    c = r["check"]
    assert c["passed"], c["failures"]
    # the static table is a support, not a mover; the box rests on it (in contact at t = 0)
    assert c["bodies"] == 1 and c["static_bodies"] == ["table_1"]
    assert list(c["drift"]) == ["box_2"] and c["drift"]["box_2"] < 2e-3 and c["unsupported"] == []


def test_override_makes_everything_dynamic(objects, tmp_path):
    from pxr import Usd, UsdPhysics

    from psimap.exporters.pipeline import export_scene

    r = export_scene(objects, tmp_path / "d", ["mjcf", "usd"], static_classes=frozenset())
    b = _bodies(tmp_path / "d" / "scene.xml")
    assert b["table_1"].find("freejoint") is not None and b["box_2"].find("freejoint") is not None
    stage = Usd.Stage.Open(str(tmp_path / "d" / "scene.usda"))
    assert stage.GetPrimAtPath("/World/table_1").HasAPI(UsdPhysics.RigidBodyAPI)
    assert r["check"]["bodies"] == 2 and r["check"]["static_bodies"] == []
    assert all(not o["static"] for o in r["objects"])
    # and the other way: the box made static by name
    r2 = export_scene(_scene(), tmp_path / "b", "mjcf", static_classes=frozenset({"box"}), check=False)
    b2 = _bodies(tmp_path / "b" / "scene.xml")
    assert b2["box_2"].find("freejoint") is None and b2["table_1"].find("freejoint") is not None
    assert [o["static"] for o in r2["objects"]] == [False, True]


@pytest.mark.parametrize("args, expect", [([], "default"), (["--dynamic-all"], set()),
                                          (["--static-classes", "none"], set()),
                                          (["--static-classes", "mug,shelf"], {"mug", "shelf"})])
def test_cli_static_flags_reach_export(monkeypatch, tmp_path, args, expect):
    import psimap.scene
    from psimap.cli import main
    from psimap.exporters import pipeline
    from psimap.exporters.physics import STATIC_CLASSES

    seen = {}

    def fake_export(scene, out, fmt, **kw):
        seen.update(kw)
        return {"objects": [], "skipped": [], "check": None, "timings": {},
                "outcome": {"passed": True, "summary": "0 of 0 thing(s) dynamic", "min_dynamic": 0.5}}

    monkeypatch.setattr(psimap.scene, "load_scene", lambda path: object())   # the CLI loads with it
    monkeypatch.setattr(pipeline, "export_scene", fake_export)
    assert main(["export", str(tmp_path / "x.ckpt"), "--out", str(tmp_path / "o"), *args]) == 0
    assert set(seen["static_classes"]) == (set(STATIC_CLASSES) if expect == "default" else expect)
    assert seen.get("min_coverage", 0.3) == (0.0 if "--dynamic-all" in args else 0.3)
    assert seen["pin_unstable"] is ("--dynamic-all" not in args)     # everything dynamic: nothing pinned
    seen.clear()
    assert main(["export", str(tmp_path / "x.ckpt"), "--out", str(tmp_path / "o"), "--no-pin-unstable"]) == 0
    assert seen["pin_unstable"] is False


def test_barely_seen_object_is_static_with_reason(tmp_path):
    from psimap.exporters.pipeline import MIN_COVERAGE, export_scene

    objs = _scene()
    objs[1].measured.coverage = MIN_COVERAGE - 0.01     # the box: its views saw a sliver of it
    r = export_scene(objs, tmp_path / "t", "mjcf", check=False)
    e = {o["name"]: o for o in r["objects"]}
    assert e["box_2"]["static"] and e["box_2"]["observed_coverage"] == pytest.approx(MIN_COVERAGE - 0.01)
    assert "too little evidence" in e["box_2"]["static_reason"] and "29% of its surface seen" in e["box_2"]["static_reason"]
    assert _bodies(tmp_path / "t" / "scene.xml")["box_2"].find("freejoint") is None
    assert r["outcome"]["little_evidence"] == 1
    # seen enough, unknown (-1: a scan), or the rule switched off: dynamic again (recomputed per export)
    for cov, kw in ((MIN_COVERAGE, {}), (-1.0, {}), (0.05, {"min_coverage": 0.0})):
        objs[1].measured.coverage = cov
        r = export_scene(objs, tmp_path / f"u{cov}", "mjcf", check=False, **kw)
        assert not {o["name"]: o for o in r["objects"]}["box_2"]["static"]


def _box_on_ramp(angle_deg=35.0):
    """A static ramp ("table": static class) and a box resting flush on its slope, steeper than
    the friction cone (tan 35 deg = 0.70 > 0.5): the box slides off in the settle check."""
    import numpy as np

    from psimap.exporters.objects import build_object

    a = np.radians(angle_deg)
    h = 0.6 * np.tan(a)
    # a wedge: its slope rises from z = 0 at x = -0.3 to h at x = 0.3
    ramp = trimesh.convex.convex_hull(np.array([[x, y, 0.0] for x in (-0.3, 0.3) for y in (-0.2, 0.2)]
                                               + [[0.3, y, h] for y in (-0.2, 0.2)]))
    n = np.array([-np.sin(a), 0.0, np.cos(a)])
    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1],
                               transform=trimesh.transformations.rotation_matrix(-a, [0, 1, 0]))
    box.apply_translation(np.array([0.0, 0.0, 0.3 * np.tan(a)]) + n * 0.0505)
    return [build_object(m, lab, i + 1, completion="none") for i, (m, lab) in enumerate([(ramp, "table"),
                                                                                         (box, "box")])]


def test_unstable_object_is_pinned_static_and_the_check_passes(tmp_path):
    from psimap.exporters.pipeline import export_scene

    objs = _box_on_ramp()
    r = export_scene(objs, tmp_path / "free", "mjcf", pin_unstable=False)
    c = r["check"]
    assert not c["passed"] and c["unstable"] == ["box_2"] and c["drift"]["box_2"] > 0.05
    assert c["pinned"] == {} and not c["penetrating"]
    r = export_scene(objs, tmp_path / "pin", ["mjcf", "usd"])
    c = r["check"]
    assert c["passed"], c["failures"]
    assert list(c["pinned"]) == ["box_2"] and "unstable in the settle check" in c["pinned"]["box_2"]
    e = {o["name"]: o for o in r["objects"]}
    assert e["box_2"]["static"] and e["box_2"]["static_reason"] == c["pinned"]["box_2"]
    assert _bodies(tmp_path / "pin" / "scene.xml")["box_2"].find("freejoint") is None
    assert c["bodies"] == 0 and sorted(c["static_bodies"]) == ["box_2", "table_1"]


def test_a_thing_with_nothing_under_it_is_pinned_for_that_reason(tmp_path):
    """A box 20 cm above the floor beside the ramp, nothing under it (on a real capture: a piece of
    a wall or of a chair that model-free masks called a thing): it falls in the settle check and is
    pinned, and its reason says so rather than "unstable"."""
    from psimap.exporters.objects import build_object
    from psimap.exporters.pipeline import export_scene

    ramp, sliding = _box_on_ramp()
    floating = build_object(trimesh.creation.box(extents=[0.1, 0.1, 0.1]).apply_translation([-0.6, 0.0, 0.25]),
                            "box", 3, completion="none")
    r = export_scene([ramp, sliding, floating], tmp_path / "out", "mjcf")
    c = r["check"]
    assert c["passed"], c["failures"]
    assert sorted(c["pinned"]) == ["box_2", "box_3"]
    assert c["pinned"]["box_3"].startswith("nothing under it in the settle check (fell 20.0 cm")
    assert c["pinned"]["box_2"].startswith("unstable in the settle check (moved ")


def test_one_role_maps_onto_the_report_keys():
    """report.json keeps its contract: "static" for every static role, "static_reason" for all but
    the environment (which needs none), "skipped" for a skipped object."""
    from psimap.exporters.objects import SceneObject
    from psimap.exporters.report import object_entry
    from psimap.exporters.roles import Reason, Role

    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    o = SceneObject(3, "mug", box)
    keys = ("static", "static_reason", "skipped")
    assert o.role is Role.DYNAMIC and [object_entry(o, {})[k] for k in keys] == [False, None, None]
    o.make_static(Reason.UNSTABLE, "unstable in the settle check (moved 4.0 cm in 2 s)")
    assert [object_entry(o, {})[k] for k in keys] == [True, "unstable in the settle check (moved 4.0 cm in 2 s)",
                                                      None]
    o.make_static(Reason.ENVIRONMENT, "static environment")
    assert [object_entry(o, {})[k] for k in keys] == [True, None, None]
    o.skip(Reason.REPAIR, "repair: flat")
    assert o.role is Role.SKIPPED and [object_entry(o, {})[k] for k in keys] == [False, None, "repair: flat"]
    o.make_dynamic()
    assert (o.role, o.reason, o.why) == (Role.DYNAMIC, None, "")


def test_a_thing_on_a_falling_thing_is_pinned_only_if_it_still_moves_on_its_pinned_support(tmp_path):
    """A board with nothing under it (a chair seat whose legs were not reconstructed) and a box on
    it: both fall in the first settle, but only the board is pinned; on the pinned board the box
    rests and stays dynamic (both were pinned in one round before)."""
    from psimap.exporters.objects import build_object
    from psimap.exporters.pipeline import export_scene

    ramp, _ = _box_on_ramp()
    board = build_object(trimesh.creation.box(extents=[0.4, 0.4, 0.04]).apply_translation([-0.8, 0.0, 0.32]),
                         "board", 3, completion="none")
    box = build_object(trimesh.creation.box(extents=[0.1, 0.1, 0.1]).apply_translation([-0.8, 0.0, 0.39]),
                       "box", 4, completion="none")
    r = export_scene([ramp, board, box], tmp_path / "out", "mjcf")
    c = r["check"]
    assert c["passed"], c["failures"]
    assert list(c["pinned"]) == ["board_3"], c["pinned"]
    e = {o["name"]: o for o in r["objects"]}
    assert not e["box_4"]["static"] and c["drift"]["box_4"] < 0.005, c["drift"]
    assert r["outcome"]["dynamic"] == 1 and r["outcome"]["pinned"] == 1


def test_a_thing_wedged_between_static_colliders_is_pinned_and_the_check_passes(tmp_path):
    """A 10 cm box standing between two static cabinets 9 cm apart (on a real capture: a thin thing
    squeezed between a static neighbour's hulls and the floor, its own hull a few mm past its
    mesh): every nudge out of one cabinet pushes it 5 mm into the other, so the penetration stays.
    It is pinned ("wedged"), static it collides with nothing static, and the scene passes; before,
    the whole check failed on the initial penetration (7-Scenes chess at 31 of 44 dynamic)."""
    from psimap.exporters.objects import build_object
    from psimap.exporters.pipeline import export_scene

    cab = [build_object(trimesh.creation.box(extents=[0.3, 0.4, 0.3]).apply_translation([sx * (0.045 + 0.15), 0, 0.15]),
                        "cabinet", i + 1, completion="none") for i, sx in enumerate((-1, 1))]
    box = build_object(trimesh.creation.box(extents=[0.1, 0.1, 0.1]).apply_translation([0, 0, 0.05]), "box", 3,
                       completion="none")
    free = export_scene([*cab, box], tmp_path / "free", "mjcf", pin_unstable=False)["check"]
    assert not free["passed"] and free["penetrating"] and free["pinned"] == {}
    depth, into = free["wedged"]["box_3"]
    assert 0.004 < depth < 0.0105 and into in ("cabinet_1", "cabinet_2")     # 1 cm of overlap in all
    r = export_scene([*cab, box], tmp_path / "pin", "mjcf")
    c = r["check"]
    assert c["passed"], c["failures"]
    assert list(c["pinned"]) == ["box_3"] and c["wedged"] == {} and not c["penetrating"]
    assert c["pinned"]["box_3"].startswith("wedged in the settle check: still ")
    assert f"mm inside cabinet_" in c["pinned"]["box_3"]
    assert _bodies(tmp_path / "pin" / "scene.xml")["box_3"].find("freejoint") is None
    assert r["outcome"]["pinned"] == 1 and r["outcome"]["dynamic"] == 0
