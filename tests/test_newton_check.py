"""The second engine: an export's scene.usda settled in Newton (psimap.sim.newton_check) agrees with
the MuJoCo check of its scene.xml; broken scenes fail in Newton too; `psimap check` reads a folder
without changing it. The demo-like scene (a fused background around the objects) is
tests/test_real_world.py::test_newton_settles_the_desk_like_mujoco.

A fresh Warp kernel cache compiles Newton's CPU kernels once (about 30 s on a quiet 2-core machine);
with a warm cache a check of these scenes takes a few seconds.
"""
from __future__ import annotations

import hashlib
import json
import shutil
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import trimesh

from psimap import PsimapError

YCB = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ycb"


@pytest.fixture(scope="module")
def newton():
    pytest.importorskip("newton_usd_schemas")
    return pytest.importorskip("newton")


def _objects():
    """A box, a can and a ball standing on the floor (primitive colliders: box, cylinder, sphere)."""
    from psimap.exporters.objects import build_object

    box = trimesh.creation.box(extents=[0.2, 0.1, 0.08]).apply_translation([0, 0, 0.04])
    can = trimesh.creation.cylinder(radius=0.04, height=0.14, sections=24).apply_translation([0.3, 0, 0.07])
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.04).apply_translation([0, 0.3, 0.04])
    # a bowl-ish convex lump: a hull collider (CONVEX_MESH in Newton, a mesh geom in MuJoCo). Its
    # rounded bottom must hold it up: radii of curvature there (a^2 / c: 10 and 7.2 cm) above its
    # centre of mass (4 cm). At [1, 0.7, 0.6] the y one (4.1 cm) sat under the centre of mass
    # (4.8 cm): it stood on the facets of its hull, and a decimation that placed them otherwise
    # rolled it 7 cm in Newton
    lump = trimesh.convex.convex_hull(trimesh.creation.capsule(height=0.06, radius=0.05).vertices
                                      * [1.0, 0.85, 0.5]).apply_translation([-0.3, 0, 0.0])
    lump.apply_translation([0, 0, -lump.bounds[0][2]])
    return [build_object(m, lab, i + 1, completion="none")
            for i, (m, lab) in enumerate([(box, "box"), (can, "can"), (ball, "ball"), (lump, "lump")])]


@pytest.fixture(scope="module")
def export_dir(newton, tmp_path_factory):
    from psimap.exporters.pipeline import export_scene

    out = tmp_path_factory.mktemp("newton") / "small"
    report = export_scene(_objects(), out, "all", check_engine="all")
    return out, report


def test_both_engines_settle_the_small_scene(export_dir):
    out, report = export_dir
    mj, nw = report["check"], report["check_newton"]
    assert {o["collision"]["kind"] for o in report["objects"]} >= {"box", "cylinder", "sphere", "hull"}
    assert mj["passed"] and nw["passed"], (mj["failures"], nw["failures"])
    assert nw["engine"] == "newton" and nw["bodies"] == 4 and nw["nudges"] == {}
    # the same bodies under the same names (USD prim names = MJCF body names), all resting
    assert set(nw["drift"]) == set(mj["drift"]) == {"box_1", "can_2", "ball_3", "lump_4"}
    assert nw["unsupported"] == [] and nw["fell"] == {}
    assert nw["max_drift"] <= 0.01 and mj["max_drift"] <= 0.01
    # the deepest contact at t = 0 is the same contact in both engines (sub-millimetre, measured
    # -0.20 mm in each)
    assert nw["min_contact_dist"] == pytest.approx(mj["min_contact_dist"], abs=3e-4)
    assert -1e-3 <= nw["min_contact_dist"] < 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["check_newton"]["passed"] and "sim_seconds_per_wall_second" not in rep["check_newton"]
    timings = json.loads((out / "timings.json").read_text())
    assert timings["newton_check_s"] > 0 and timings["newton_sim_seconds_per_wall_second"] > 0


def test_newton_reads_what_the_writer_meant(export_dir):
    """Bodies, masses, inertia and colliders as Newton builds them from scene.usda, against MuJoCo's
    model of scene.xml: every dynamic object a body with the same mass and world inertia, every
    visual mesh a shape that collides with nothing."""
    import mujoco

    from psimap.sim.newton_check import load_usd_newton

    out, _ = export_dir
    model, _ = load_usd_newton(out / "scene.usda")
    mj = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    data = mujoco.MjData(mj)
    mujoco.mj_forward(mj, data)
    q, inertia, mass = model.body_q.numpy(), model.body_inertia.numpy(), model.body_mass.numpy()
    for i, label in enumerate(model.body_label):
        name = str(label).rsplit("/", 1)[-1]
        b = mj.body(name).id
        assert mass[i] == pytest.approx(mj.body_mass[b], rel=1e-5)
        x, y, z, w = q[i, 3:]
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        Ri = data.ximat[b].reshape(3, 3)
        np.testing.assert_allclose(R @ inertia[i] @ R.T, Ri @ np.diag(mj.body_inertia[b]) @ Ri.T,
                                   atol=1e-5 * mj.body_inertia[b].max())
        np.testing.assert_allclose(q[i, :3], data.xipos[b], atol=1e-6)
    flags = model.shape_flags.numpy()
    labels = [str(s) for s in model.shape_label]
    import newton as nt

    collide = int(nt.ShapeFlags.COLLIDE_SHAPES)
    visual = [f for f, s in zip(flags, labels) if s.endswith("/visual")]
    assert len(visual) == 4 and not any(f & collide for f in visual)
    colliders = {s for f, s in zip(flags, labels) if f & collide}
    assert "/World/floor" in colliders and "/World/lump_4/collision_0" in colliders
    assert not any("visual" in s for s in colliders)
    # every collider's friction is the MJCF geom's (the floor too: without a USD material Newton
    # takes 1.0 where the MJCF says 0.8)
    mu = model.shape_material_mu.numpy()
    friction = {}
    for f, s, m in zip(flags, labels, mu):
        if f & collide:
            geom = "floor" if s == "/World/floor" else "_".join(s.split("/")[2:])
            friction[geom] = (float(m), float(mj.geom_friction[mj.geom(geom).id][0]))
    assert len(friction) == 5 and friction["floor"][1] == pytest.approx(0.8)
    for geom, (newton_mu, mujoco_mu) in friction.items():
        assert newton_mu == pytest.approx(mujoco_mu, abs=1e-6), geom


def _moved_copy(src: Path, dst: Path, prim: str, dz: float) -> Path:
    """A copy of the export folder with `prim` moved dz along +z in its scene.usda."""
    from pxr import Gf, Usd, UsdGeom

    shutil.copytree(src, dst)
    stage = Usd.Stage.Open(str(dst / "scene.usda"))
    op = UsdGeom.Xformable(stage.GetPrimAtPath(prim)).GetOrderedXformOps()[0]
    op.Set(op.Get() + Gf.Vec3d(0, 0, dz))
    stage.GetRootLayer().Save()
    return dst / "scene.usda"


def test_floating_and_penetrating_objects_fail_in_newton(export_dir, tmp_path):
    from psimap.sim.newton_check import check_usd_newton

    out, _ = export_dir
    # half a second: a 30 cm fall takes 0.25 s; a penetration is measured at t = 0
    r = check_usd_newton(_moved_copy(out, tmp_path / "float", "/World/box_1", 0.30), duration=0.5)
    assert r["unsupported"] == ["box_1"] and "box_1" not in r["drift"]
    assert r["fell"]["box_1"] == pytest.approx(0.30, abs=0.01)
    assert not r["passed"] and any("unsupported object(s) fell" in f for f in r["failures"])
    r = check_usd_newton(_moved_copy(out, tmp_path / "sunk", "/World/box_1", -0.01), duration=0.1)
    assert r["min_contact_dist"] == pytest.approx(-0.01, abs=1.5e-3)
    assert r["penetrating"] and not r["passed"] and "initial penetration" in r["failures"][0]
    # stood on its 10 cm side at the same centre (its half height 4 -> 5 cm): 1 cm into the floor,
    # measured through the body's rotation
    from pxr import Usd, UsdGeom

    usd = _moved_copy(out, tmp_path / "turned", "/World/box_1", 0.0)
    stage = Usd.Stage.Open(str(usd))
    UsdGeom.Xformable(stage.GetPrimAtPath("/World/box_1")).AddRotateXOp().Set(90.0)
    stage.GetRootLayer().Save()
    r = check_usd_newton(usd, duration=0.1)
    assert r["min_contact_dist"] == pytest.approx(-0.01, abs=1.5e-3) and r["penetrating"]


def _digest(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_psimap_check_reads_only(export_dir, tmp_path, capsys):
    from psimap.cli import main

    out, _ = export_dir
    before = _digest(out)
    assert main(["check", str(out), "--engine", "all"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("mujoco: passed") and "\nnewton: passed" in text and "engines: 4 resting" in text
    assert _digest(out) == before                  # nothing written, nothing added (dot files too)
    # a failing scene exits 2 and is not repaired: the box 1 cm into the floor in both files stays there
    bad = _moved_copy(out, tmp_path / "sunk", "/World/box_1", -0.01).parent
    xml = bad / "scene.xml"
    tree = ET.parse(xml)
    body = [b for b in tree.getroot().iter("body") if b.get("name") == "box_1"][0]
    pos = [float(v) for v in body.get("pos").split()]
    body.set("pos", f"{pos[0]} {pos[1]} {pos[2] - 0.01}")
    tree.write(xml)
    before = _digest(bad)
    assert main(["check", str(bad), "--engine", "all", "--json", "--duration", "0.1"]) == 2
    rep = json.loads(capsys.readouterr().out)
    assert list(rep) == ["mujoco", "newton"]
    for engine in rep.values():
        assert engine["penetrating"] and engine["nudges"] == {}
        assert engine["min_contact_dist"] == pytest.approx(-0.01, abs=1.5e-3)
    assert _digest(bad) == before
    # bad input: one line, exit 1
    assert main(["check", str(tmp_path / "nothing")]) == 1
    assert "export folder not found" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["check", str(tmp_path / "empty"), "--engine", "all"]) == 1
    assert "holds no scene.xml and no scene.usda" in capsys.readouterr().err


def test_missing_extra_is_one_clear_error(monkeypatch, tmp_path):
    from psimap.sim.newton_check import MISSING, check_usd_newton

    monkeypatch.setitem(sys.modules, "newton", None)        # import newton -> ImportError
    with pytest.raises(PsimapError) as e:
        check_usd_newton(tmp_path / "scene.usda")
    assert str(e.value) == MISSING == "the Newton check needs the optional extra: pip install 'psimap[newton]'"


@pytest.mark.shared
@pytest.mark.skipif(not YCB.is_dir(), reason="../shared/data/ycb not available")
def test_ycb_scans_settle_in_both_engines(newton, tmp_path):
    from psimap.exporters.objects import object_from_scan
    from psimap.exporters.pipeline import export_scene

    names = ["cracker_box", "banana"]
    objs = [object_from_scan(YCB / n / "textured.obj", n, i + 1, offset=(0.3 * i, 0, 0))
            for i, n in enumerate(names)]
    # MJCF only: the Newton check writes a USD of its own for the check and removes it
    r = export_scene(objs, tmp_path / "ycb", "mjcf", check_engine="all")
    assert sorted(p.name for p in (tmp_path / "ycb").iterdir() if p.suffix in (".usda", "")) == [
        ".psimap-output", "assets", "collision", "meshes"]
    mj, nw = r["check"], r["check_newton"]
    assert mj["passed"] and nw["passed"], (mj["failures"], nw["failures"])
    assert set(nw["drift"]) == set(mj["drift"]) == {"cracker_box_1", "banana_2"}
    assert mj["max_drift"] <= 0.01 and nw["max_drift"] <= 0.01
    assert nw["min_contact_dist"] == pytest.approx(mj["min_contact_dist"], abs=5e-4)

