"""examples/usd_in_isaac.md cannot drift from the USD writer: its table of prim paths, types, schemas
and attributes is parsed and checked against a fresh export read with pxr, both ways (every row is
found with what it says; every prim of the stage is in some row)."""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import trimesh

DOC = Path(__file__).resolve().parents[1] / "examples" / "usd_in_isaac.md"
PRIMITIVES = ("sphere", "box", "cylinder")


def doc_rows() -> list[dict]:
    """The 'Prims and schemas' table: [{path, types, schemas, attributes, optional}]."""
    text = DOC.read_text()
    section = text[text.index("## Prims and schemas"):text.index("## Loading it")]
    rows = []
    for line in section.splitlines():
        if not line.startswith("| `/World"):
            continue
        path, types, schemas, attrs = [c.strip() for c in line.strip().strip("|").split("|")]
        rows.append({"path": path.strip("`"),
                     "types": [t.strip() for t in types.split(",") if t.strip()],
                     "schemas": [s.strip() for s in schemas.split(",") if s.strip()],
                     "attributes": re.findall(r"`([A-Za-z]+(?::[A-Za-z]+)+|size|purpose)`", attrs),
                     "optional": "when" in attrs})
    return rows


def doc_metadata() -> dict:
    text = DOC.read_text()
    return dict(re.findall(r"^\| `(\w+)` \| `([^`]+)`", text[:text.index("## Prims and schemas")], re.M))


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    """Every kind of prim the writer makes: a dynamic object with a primitive collider (can), one
    with a hull (cone), a static one (table), a background with static-world colliders."""
    from psimap.exporters.objects import build_object
    from psimap.exporters.pipeline import export_scene

    table = trimesh.creation.box(extents=[0.8, 0.6, 0.4]).apply_translation([0, 0, 0.2])
    can = trimesh.creation.cylinder(radius=0.033, height=0.12, sections=32).apply_translation([0.2, 0.1, 0.46])
    cone = trimesh.creation.cone(radius=0.05, height=0.1, sections=7).apply_translation([-0.2, 0.0, 0.4])
    meshes = [(table, "table", (150, 110, 70)), (can, "can", (200, 200, 60)), (cone, "toy", (60, 180, 90))]
    objs = []
    for i, (m, label, rgb) in enumerate(meshes):
        m.visual.vertex_colors = [*rgb, 255]
        objs.append(build_object(m, label, i + 1, completion="none"))
    floor = trimesh.creation.box(extents=[2.0, 2.0, 0.02]).apply_translation([0, 0, -0.01])
    wall = trimesh.creation.box(extents=[2.0, 0.02, 1.0]).apply_translation([0, 1.01, 0.5])
    background = build_object(trimesh.util.concatenate([floor, wall]), "background", 0, completion="none")
    out = tmp_path_factory.mktemp("usd_doc") / "export"
    export_scene(objs, out, "usd", background=background)
    return out


def _placeholders(report: dict) -> dict[str, str]:
    def alt(names):
        assert names, "the test scene lacks a kind of object the table names"
        return "(?:" + "|".join(re.escape(n) for n in names) + ")"

    objects = report["objects"]
    return {"<object>": alt([o["name"] for o in objects]),
            "<dynamic>": alt([o["name"] for o in objects if not o["static"]]),
            "<static>": alt([o["name"] for o in objects if o["static"]]),
            "<hull object>": alt([o["name"] for o in objects if o["collision"]["kind"] not in PRIMITIVES]),
            "<primitive object>": alt([o["name"] for o in objects if o["collision"]["kind"] in PRIMITIVES]),
            "<background>": alt([report["background"]["name"]]),
            "<env collider>": r"(?!Looks$)[^/]+",
            "<k>": r"\d+"}


def _pattern(path: str, subs: dict[str, str]) -> re.Pattern:
    out = re.escape(path).replace(r"\*", ".+")
    for key, regex in subs.items():
        out = out.replace(re.escape(key), regex)
    return re.compile(out + "$")


def test_the_doc_table_parses():
    rows = doc_rows()
    assert len(rows) >= 20 and rows[0]["path"] == "/World"
    dyn = next(r for r in rows if r["path"] == "/World/<dynamic>")
    assert dyn["schemas"] == ["PhysicsRigidBodyAPI", "PhysicsMassAPI", "SemanticsLabelsAPI:class"]
    assert "physics:mass" in dyn["attributes"] and "psimap:instanceId" in dyn["attributes"]
    assert doc_metadata() == {"upAxis": "Z", "metersPerUnit": "1", "kilogramsPerUnit": "1", "defaultPrim": "/World"}


def test_the_doc_table_matches_a_fresh_export(export):
    from pxr import Usd, UsdGeom, UsdPhysics

    stage = Usd.Stage.Open(str(export / "scene.usda"))
    meta = doc_metadata()
    assert UsdGeom.GetStageUpAxis(stage) == meta["upAxis"]
    assert UsdGeom.GetStageMetersPerUnit(stage) == float(meta["metersPerUnit"])
    assert UsdPhysics.GetStageKilogramsPerUnit(stage) == float(meta["kilogramsPerUnit"])
    assert stage.GetDefaultPrim().GetPath().pathString == meta["defaultPrim"]
    subs = _placeholders(json.loads((export / "report.json").read_text()))
    rows = [(r, _pattern(r["path"], subs)) for r in doc_rows()]
    prims = [p for p in stage.Traverse()]
    for row, pattern in rows:
        found = [p for p in prims if pattern.match(p.GetPath().pathString)]
        assert found, f"no prim for the doc's row {row['path']}"
        for p in found:
            where = p.GetPath().pathString
            assert p.GetTypeName() in (row["types"] or [""]), (where, p.GetTypeName(), row["types"])
            assert set(row["schemas"]) <= set(p.GetAppliedSchemas()), (where, p.GetAppliedSchemas())
            authored = {a.GetName() for a in p.GetAuthoredAttributes()}
            if not row["optional"]:
                assert set(row["attributes"]) <= authored, (where, set(row["attributes"]) - authored)
        if row["optional"]:
            assert any(set(row["attributes"]) <= {a.GetName() for a in p.GetAuthoredAttributes()} for p in found)
    for p in prims:                     # nothing the doc does not describe
        assert any(pattern.match(p.GetPath().pathString) for _, pattern in rows), p.GetPath().pathString
