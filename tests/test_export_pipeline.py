"""export_scene end to end: every format, determinism, degenerate objects never reach a writer,
USD validation, the checkpoint path (Python API + `psimap export`), bad checkpoints."""
from __future__ import annotations

import hashlib
import io
import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import trimesh

from psimap import PsimapError
from psimap.exporters.roles import Reason, Role


def _objects():
    from psimap.exporters.objects import build_object

    box = trimesh.creation.box(extents=[0.2, 0.1, 0.08]).apply_translation([0, 0, 0.04])
    box.visual.vertex_colors = [200, 40, 40, 255]
    can = trimesh.creation.cylinder(radius=0.04, height=0.14, sections=24).apply_translation([0.3, 0, 0.07])
    can.visual.vertex_colors = [40, 40, 200, 255]
    flat = trimesh.creation.box(extents=[0.2, 0.2, 0.0004]).apply_translation([-0.3, 0, 0.0002])
    objs = [build_object(m, lab, i + 1, completion="none")
            for i, (m, lab) in enumerate([(box, "cracker box"), (can, "can"), (flat, "paper")])]
    return objs


@pytest.fixture(scope="module")
def objects():
    return _objects()


def _files(root):
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_all_formats_deterministic_and_degenerate_skipped(objects, tmp_path):
    from psimap.exporters.pipeline import export_scene

    assert objects[2].role is Role.SKIPPED and objects[2].reason is Reason.REPAIR and "flat" in objects[2].why
    r1 = export_scene(objects, tmp_path / "a", "all")
    r2 = export_scene(_objects(), tmp_path / "b", "all")
    f1, f2 = _files(tmp_path / "a"), _files(tmp_path / "b")
    f1.pop("timings.json"), f2.pop("timings.json")
    assert sorted(f1) == sorted(f2)
    differing = [k for k in f1 if f1[k] != f2[k]]
    assert differing == []
    for name in ("scene.xml", "scene.usda", "scene.glb", "report.json", "meshes/cracker_box_1.obj",
                 "meshes/cracker_box_1.png", "meshes/can_2.obj"):
        assert name in f1, name
    # the degenerate object is reported, never written
    assert [s["name"] for s in r1["skipped"]] == ["paper_3"]
    assert not any("paper" in k for k in f1)
    assert "paper" not in f1["scene.xml"].decode() and "paper" not in f1["scene.usda"].decode()
    rep = json.loads(f1["report.json"])
    o = {e["name"]: e for e in rep["objects"]}
    assert o["cracker_box_1"]["collision"]["kind"] == "box"
    assert o["cracker_box_1"]["physics"]["mass_kg"] == pytest.approx(0.2 * 0.1 * 0.08 * 200.0, rel=1e-4)
    assert o["can_2"]["collision"]["kind"] == "cylinder"
    np.testing.assert_allclose(o["can_2"]["bounds"], [[0.26, -0.04, 0], [0.34, 0.04, 0.14]], atol=2e-3)
    assert o["can_2"]["watertight"] and not o["can_2"]["completed"]
    assert rep["check"]["passed"] and rep["usd_validation"]["errors"] == []
    assert r1["check"]["max_drift"] < 0.01



def test_each_texture_is_encoded_once_for_every_writer(objects, tmp_path, monkeypatch):
    """meshes/, the settle check's and the final MJCF's assets/ and the USD write one PNG file per
    texture, encoded once (exporters.objfile.texture_png; the GLB's own encode is trimesh's): each
    texture is encoded at most twice where it was six times; the files are the texture, and the
    OBJ's material names its PNG as trimesh wrote it."""
    from PIL import Image

    from psimap.exporters import objfile
    from psimap.exporters.pipeline import export_scene

    objfile._PNG_CACHE.clear()
    encodes, real = {}, Image.Image.save

    def counting(self, fp, format=None, **params):
        key = hashlib.sha1(np.asarray(self).tobytes()).hexdigest()
        encodes[key] = encodes.get(key, 0) + 1
        return real(self, fp, format, **params)

    monkeypatch.setattr(Image.Image, "save", counting)
    export_scene(objects, tmp_path / "t", "all")
    monkeypatch.setattr(Image.Image, "save", real)
    textured = [o for o in objects if o.texture is not None and (tmp_path / "t" / "meshes" / f"{o.name}.obj").exists()]
    assert len(textured) >= 2
    files = _files(tmp_path / "t")
    for o in textured:
        key = hashlib.sha1(np.ascontiguousarray(o.texture).tobytes()).hexdigest()
        assert 1 <= encodes.get(key, 0) <= 2, (o.name, encodes.get(key))
        pngs = [v for k, v in files.items() if k.endswith(f"/{o.name}.png")]
        assert len(pngs) >= 2 and all(v == pngs[0] for v in pngs)
        np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(pngs[0])).convert("RGB")), o.texture)
        mtl = files[f"meshes/{o.name}.mtl"].decode()
        assert mtl.splitlines()[-1] == f"map_Kd {o.name}.png" and mtl.startswith(f"newmtl {o.name}")
        mesh = trimesh.load(tmp_path / "t" / "meshes" / f"{o.name}.obj", process=False)
        assert mesh.visual.material.image.size == o.texture.shape[1::-1]

def test_mjcf_structure(objects, tmp_path):
    import mujoco

    from psimap.exporters.pipeline import export_scene

    export_scene(objects, tmp_path / "m", "mjcf", check=False)
    root = ET.parse(tmp_path / "m" / "scene.xml").getroot()
    body = [b for b in root.iter("body") if b.get("name") == "can_2"][0]
    assert body.find("freejoint") is not None and body.find("inertial") is not None
    assert [(g.get("name"), g.get("class")) for g in body.iter("geom")] == [
        ("can_2_visual", "visual"), ("can_2_collision_0", "collision")]
    m = mujoco.MjModel.from_xml_path(str(tmp_path / "m" / "scene.xml"))
    vis, col = (mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("can_2_visual", "can_2_collision_0"))
    assert (m.geom_group[vis], m.geom_contype[vis], m.geom_conaffinity[vis]) == (2, 0, 0)
    assert m.geom_group[col] == 3 and m.geom_type[col] == mujoco.mjtGeom.mjGEOM_CYLINDER
    bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "can_2")
    assert m.body_mass[bid] == pytest.approx(np.pi * 0.04**2 * 0.14 * 900.0, rel=0.03)   # 24-gon < circle
    # visual mesh lands where the object is (MuJoCo recentres meshes; the geom frame compensates)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    gid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "can_2_visual")
    np.testing.assert_allclose(d.geom_xpos[gid][:2], [0.3, 0.0], atol=2e-3)


def test_usd_content(objects, tmp_path):
    from pxr import Usd, UsdGeom, UsdPhysics, UsdSemantics

    from psimap.exporters.pipeline import export_scene

    r = export_scene(objects, tmp_path / "u", "usd", check=False)
    assert r["usd_validation"]["validators"] >= 20 and r["usd_validation"]["errors"] == []
    stage = Usd.Stage.Open(str(tmp_path / "u" / "scene.usda"))
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert UsdPhysics.GetStageKilogramsPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath().pathString == "/World"
    prim = stage.GetPrimAtPath("/World/cracker_box_1")
    assert prim.HasAPI(UsdPhysics.RigidBodyAPI) and prim.HasAPI(UsdPhysics.MassAPI)
    assert UsdPhysics.MassAPI(prim).GetMassAttr().Get() == pytest.approx(0.32, rel=1e-4)
    labels = UsdSemantics.LabelsAPI(prim, "class").GetLabelsAttr().Get()
    assert list(labels) == ["cracker box"]
    assert prim.GetAttribute("psimap:instanceId").Get() == 1
    vis = UsdGeom.Mesh(stage.GetPrimAtPath("/World/cracker_box_1/visual"))
    assert UsdGeom.PrimvarsAPI(vis).GetPrimvar("st").IsDefined()
    col = stage.GetPrimAtPath("/World/cracker_box_1/collision_0")
    assert col.HasAPI(UsdPhysics.CollisionAPI)


def test_bad_format_and_inputs(objects, tmp_path):
    from psimap.exporters.pipeline import export_scene

    with pytest.raises(PsimapError, match="unknown export format"):
        export_scene(objects, tmp_path / "x", "fbx")
    with pytest.raises(PsimapError, match="SceneObject"):
        export_scene([1, 2], tmp_path / "x", "mjcf")
    assert not (tmp_path / "x").exists()


# ---------------------------------------------------------------- checkpoint path

@pytest.fixture(scope="module")
def ckpt(ring_checkpoint):
    from psimap.data.frames import ClassInfo

    floor = trimesh.creation.box(extents=[1.2, 1.2, 0.02]).apply_translation([0, 0, -0.01])
    box = trimesh.creation.box(extents=[0.2, 0.14, 0.12]).apply_translation([0.15, 0.05, 0.06])
    return ring_checkpoint([floor, box], [0, 7], [1, 2], [ClassInfo(1, "floor", False), ClassInfo(2, "box", True)],
                           colors=[(0.5, 0.5, 0.5), (0.9, 0.1, 0.1)], target=[0.1, 0.05, 0.04])


def test_python_api_objects_in_world_frame(ckpt):
    import psimap

    objs = psimap.load(ckpt).objects(completion="none")
    assert [(o.instance_id, o.label) for o in objs] == [(7, "box")]
    o = objs[0]
    assert isinstance(o.mesh, trimesh.Trimesh) and o.mesh.is_watertight
    # metres, world frame: the fused box sits where the GT box is (TSDF + partial view tolerance)
    np.testing.assert_allclose(o.mesh.bounds.mean(0)[:2], [0.15, 0.05], atol=0.02)
    np.testing.assert_allclose(o.mesh.extents[:2], [0.2, 0.14], atol=0.04)
    assert 0.5 * 0.2 * 0.14 * 0.12 * 200 < o.mass < 1.6 * 0.2 * 0.14 * 0.12 * 200
    assert o.texture is not None and o.texture_source == "views"
    red = o.texture.reshape(-1, 3).astype(float)
    assert red[:, 0].mean() > 1.5 * red[:, 1].mean()          # the box was red in every view


def test_cli_export_and_bad_checkpoints(ckpt, tmp_path, capsys):
    from psimap.cli import main

    rc = main(["export", str(ckpt), "--format", "mjcf", "--out", str(tmp_path / "out"), "--completion", "none"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "simulation check passed" in out.out
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert rep["objects"][0]["name"] == "box_7" and rep["background"] is not None
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(ckpt.read_bytes()[:200])
    rc = main(["export", str(bad), "--out", str(tmp_path / "o2")])
    err = capsys.readouterr().err
    # a clean error naming the file, not a crash ("internal error: RuntimeError: PytorchStreamReader...")
    assert rc == 1 and len(err.strip().splitlines()) == 1 and err.startswith("psimap export: error: ")
    assert "internal error" not in err and f"{bad}: truncated or corrupt checkpoint" in err
    foreign = tmp_path / "foreign.ckpt"
    import torch

    torch.save({"weights": torch.zeros(3)}, foreign)
    rc = main(["export", str(foreign), "--out", str(tmp_path / "o3")])
    err = capsys.readouterr().err
    assert rc == 1 and len(err.strip().splitlines()) == 1 and "internal error" not in err
    assert f"{foreign}: not a psimap scene checkpoint" in err
    bad_table = tmp_path / "d.json"
    bad_table.write_text('{"box": "heavy"}')
    rc = main(["export", str(ckpt), "--densities", str(bad_table), "--out", str(tmp_path / "o4")])
    err = capsys.readouterr().err
    assert rc == 1 and "density table" in err
    assert not any((tmp_path / d).exists() for d in ("o2", "o3", "o4"))


def test_static_classes_get_the_larger_hull_cap(ckpt, monkeypatch):
    """Static furniture's colliders may use STATIC_MAX_HULLS parts; other objects keep the default."""
    import psimap
    from psimap.exporters import objects as O

    seen = {}
    real = O.finish_object

    def spy(o, **kw):
        seen[o.label] = kw.get("max_hulls", 8)
        return real(o, **kw)

    monkeypatch.setattr(O, "finish_object", spy)
    scene = psimap.load(ckpt)
    O.extract_scene(scene, completion="none")
    assert seen == {"box": 8}
    O.extract_scene(scene, completion="none", static_classes=frozenset({"box"}))
    assert seen == {"box": O.STATIC_MAX_HULLS} and O.STATIC_MAX_HULLS > 8


def test_the_texture_cache_holds_the_newest_and_serves_threads():
    """texture_png: PIL's PNG of the texture, the newest TEXTURE_CACHE_SIZE kept; writers on
    several threads get the same bytes."""
    from concurrent.futures import ThreadPoolExecutor

    from PIL import Image

    from psimap.exporters import objfile

    objfile._PNG_CACHE.clear()
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 255, (8, 8, 3), dtype=np.uint8) for _ in range(objfile.TEXTURE_CACHE_SIZE + 5)]
    with ThreadPoolExecutor(4) as pool:
        out = list(pool.map(objfile.texture_png, images + images[-3:]))
    assert len(objfile._PNG_CACHE) == objfile.TEXTURE_CACHE_SIZE
    for img, png in zip(images + images[-3:], out):
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, format="png")
        assert png == buf.getvalue()
    assert objfile.texture_png(images[-1]) is objfile.texture_png(images[-1].copy())   # by content
