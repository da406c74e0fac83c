"""The writer registry (exporters.formats): one signature, the settle nudges applied once to the
export scene so every format places an object at the same height, `--format` read from the
registry without importing a writer, and a new format added as one module."""
from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import trimesh

from psimap import PsimapError

SUNK = 0.003        # the box starts this far inside the table top
HOVER = 0.008       # the can starts this far above the floor


def _scene():
    from psimap.exporters.objects import build_object

    table = trimesh.creation.box(extents=[0.8, 0.6, 0.4]).apply_translation([0, 0, 0.2])
    box = trimesh.creation.box(extents=[0.12, 0.08, 0.1]).apply_translation([0.1, 0.05, 0.45 - SUNK])
    can = trimesh.creation.cylinder(radius=0.04, height=0.14, sections=24)
    can.apply_translation([1.0, 0, 0.07 + HOVER])
    return [build_object(m, lab, i + 1, completion="none")
            for i, (m, lab) in enumerate([(table, "table"), (box, "box"), (can, "can")])]


@pytest.fixture(scope="module")
def nudged_export(tmp_path_factory):
    from psimap.exporters.pipeline import export_scene

    out = tmp_path_factory.mktemp("nudged") / "all"
    objs = _scene()
    report = export_scene(objs, out, "all")
    return objs, report, out


def test_nudges_found_once_and_every_format_places_objects_alike(nudged_export):
    from pxr import Usd, UsdGeom

    from psimap.sim.check import check_mjcf

    objs, report, out = nudged_export
    nudges = report["check"]["nudges"]
    # lifted out of the table (depth + the check's 0.2 mm margin), lowered onto the floor
    assert nudges["box_2"] == pytest.approx([0, 0, SUNK + 2e-4], abs=3e-4)
    assert nudges["can_3"] == pytest.approx([0, 0, -HOVER + 2e-4], abs=1e-3)
    assert "table_1" not in nudges                      # static: a support, never moved
    com = {o.name: np.asarray(o.physics.com, np.float64) for o in objs}
    # MJCF: the body frame (at the centre of mass) moved by the nudge
    bodies = {b.get("name"): b for b in ET.parse(out / "scene.xml").getroot().iter("body")}
    for name, d in nudges.items():
        pos = np.array([float(x) for x in bodies[name].get("pos").split()])
        np.testing.assert_allclose(pos, com[name] + d, atol=1e-8)
    # USD: the Xform's world translation likewise
    stage = Usd.Stage.Open(str(out / "scene.usda"))
    cache = UsdGeom.XformCache()
    for name in com:
        t = np.array(cache.GetLocalToWorldTransform(stage.GetPrimAtPath(f"/World/{name}")).ExtractTranslation())
        np.testing.assert_allclose(t, com[name] + nudges.get(name, [0.0, 0.0, 0.0]), atol=1e-6)
    # GLB (Y-up): the visual mesh moved by the same amount, so its lowest point is the object's plus dz
    glb = trimesh.load(out / "scene.glb", force="scene")
    for o in objs:
        lo = glb.geometry[o.name].copy().apply_transform(glb.graph[o.name][0]).bounds[0]
        assert lo[1] == pytest.approx(o.mesh.bounds[0, 2] + nudges.get(o.name, [0.0, 0.0, 0.0])[2], abs=1e-6)
    # meshes/ and report.json describe the objects as reconstructed (no nudge)
    rep = json.loads((out / "report.json").read_text())
    box = trimesh.load(out / "meshes" / "box_2.obj", force="mesh")
    entry = {e["name"]: e for e in rep["objects"]}["box_2"]
    assert box.bounds[0, 2] == pytest.approx(entry["bounds"][0][2], abs=1e-6)
    assert entry["bounds"][0][2] == pytest.approx(0.4 - SUNK, abs=1e-6)
    # the MJCF written is the resolved scene: checked again, nothing is left to nudge
    again = check_mjcf(out / "scene.xml")
    assert again["nudges"] == {} and again["passed"], again["failures"]
    assert not (out / ".check").exists()


def test_export_leaves_the_callers_objects_alone(nudged_export):
    from psimap.exporters.roles import Role

    objs, report, _ = nudged_export
    assert report["objects"][0]["static"] is True               # the table, for this export
    assert [o.role for o in objs] == [Role.DYNAMIC] * 3          # the objects passed in keep theirs


def test_a_new_format_is_one_module(tmp_path, monkeypatch):
    """A writer registered by name and "module:function" gets the export scene with the check's
    nudges already applied and the roles decided, and writes where it is told."""
    from psimap.exporters import formats
    from psimap.exporters.pipeline import export_scene

    (tmp_path / "fake_sdf.py").write_text(
        "import json\n"
        "def write_sdf(scene, out_dir):\n"
        "    path = out_dir / 'scene.sdf'\n"
        "    path.write_text(json.dumps({'floor_z': scene.floor_z, 'nudges': dict(scene.nudges),\n"
        "        'roles': {o.name: o.role.value for o in scene.objects},\n"
        "        'offset': {o.name: [float(x) for x in scene.offset(o)] for o in scene.objects}}))\n"
        "    return path\n"
        "def validate(path):\n"
        "    return {'errors': [] if path.name == 'scene.sdf' else ['wrong file']}\n"
        "def reject(path):\n"
        "    return {'errors': ['no <world> element']}\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    sdf = formats.Format("sdf", "SDF", "fake_sdf:write_sdf", "fake_sdf:validate")
    monkeypatch.setitem(formats.FORMATS, "sdf", sdf)
    r = export_scene(_scene(), tmp_path / "out", "sdf")
    written = json.loads((tmp_path / "out" / "scene.sdf").read_text())
    assert written["nudges"] == r["check"]["nudges"] and set(written["nudges"]) == {"box_2", "can_3"}
    assert written["offset"]["box_2"] == pytest.approx(written["nudges"]["box_2"])
    assert written["offset"]["table_1"] == [0, 0, 0]
    assert written["roles"] == {"table_1": "static", "box_2": "dynamic", "can_3": "dynamic"}
    assert written["floor_z"] == pytest.approx(r["floor_z"])
    assert r["sdf_validation"] == {"errors": []} and r["format"] == ["sdf"]
    assert not (tmp_path / "out" / "scene.xml").exists()        # the check's MJCF is not an output
    # a validator's error fails the export, and nothing is left behind
    monkeypatch.setitem(formats.FORMATS, "sdf", dataclasses.replace(sdf, validator="fake_sdf:reject"))
    with pytest.raises(PsimapError, match="SDF validation failed: no <world> element"):
        export_scene(_scene(), tmp_path / "bad", "sdf", check=False)
    assert not (tmp_path / "bad").exists()


def test_format_names_follow_the_registry():
    from psimap.exporters.formats import FORMATS, format_names

    assert list(FORMATS) == ["mjcf", "usd", "glb"]
    assert format_names("all") == ["mjcf", "usd", "glb"]
    assert format_names(["glb", "mjcf"]) == ["mjcf", "glb"]        # writers run in registry order
    with pytest.raises(PsimapError, match="unknown export format 'fbx'.*mjcf, usd, glb, all"):
        format_names("fbx")


def test_cli_choices_come_from_the_registries_without_heavy_imports():
    """`psimap --help` reads the format and completion names from stdlib-only registries: no
    numpy, trimesh, pxr, writer, nor the entry-point scan (importlib.metadata) at parser build."""
    code = ("import sys, psimap.cli\n"
            "parser = psimap.cli.build_parser()\n"
            "heavy = ('numpy', 'trimesh', 'pxr', 'psimap.exporters.mjcf', 'importlib.metadata')\n"
            "print(sorted(m for m in heavy if m in sys.modules))\n"
            "import dataclasses, psimap.options as O\n"
            "f = {x.name: x for x in dataclasses.fields(O.ExportOptions)}\n"
            "print(list(f['format'].metadata['choices']))\n"
            "print('mirror' in f['completion'].metadata['choices'])\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.splitlines() == ["[]", "['mjcf', 'usd', 'glb', 'all']", "True"]
