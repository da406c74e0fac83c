"""Object-level evaluation (psimap.metrics.objects, `psimap eval EXPORT DATA`, `--objects`).

Closed-form cases first (meshes whose distances are known exactly), then a tiny scene exported by
`psimap export` and evaluated through the console script, upright and turned.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from psimap import PsimapError
from psimap.metrics.objects import GTThing, PredictedObject, SurfaceSamples, evaluate_objects

PSIMAP = Path(sys.executable).parent / "psimap"


def cube(side=0.1, at=(0.0, 0.0, 0.0)):
    return trimesh.creation.box(extents=[side] * 3).apply_translation(at)


def thing(mesh, iid=1, label="box", observed=None, mass=None):
    """A GT thing; `observed`: the mesh whose surface counts as its observed part (None: unseen)."""
    samples = None
    if observed is not None:
        samples = SurfaceSamples(np.asarray(observed.vertices, float), np.asarray(observed.faces), (0, 2, iid))
    return GTThing(id=iid, label=label, name=label, mesh=mesh, observed=samples, mass_kg=mass,
                   scene_area=float(mesh.area))


def pred(mesh, name="box_1", label="box", **kw):
    return PredictedObject(name=name, label=label, mesh=mesh, **kw)


def row(result, iid):
    return next(r for r in result["per_object"] if r["id"] == iid)


def test_cube_shifted_5mm_is_within_1cm_everywhere():
    gt = cube()
    r = row(evaluate_objects([pred(cube(at=(0.005, 0, 0)))], [thing(gt, observed=gt)]), 1)
    assert r["found"] and r["prediction"] == "box_1"
    # every point of either cube lies within 5 mm of the other
    for k in ("fscore", "precision", "recall", "observed_completeness"):
        assert r[f"{k}_10mm"] == 1.0 and r[f"{k}_25mm"] == 1.0, k
    assert r["match_score"] == 1.0 and abs(r["size_m"] - 0.1 * np.sqrt(3)) < 1e-9


def test_cube_shifted_2cm_closed_form():
    """10 cm cube moved 2 cm along x: of each face parallel to the move, 9 of 10 cm lie within 1 cm of
    the other cube; the leading face lies 2 cm out; the trailing face, inside the other cube, is within
    1 cm only in its outer 1 cm ring (1 - 0.8^2 = 0.36). P = R = (4 * 0.9 + 0.36) / 6 = 0.66 at 1 cm;
    everything is within 2 cm, so 1 at 2.5 cm."""
    gt = cube()
    r = row(evaluate_objects([pred(cube(at=(0.02, 0, 0)))], [thing(gt, observed=gt)]), 1)
    assert r["found"]
    for k in ("precision", "recall", "fscore"):
        assert abs(r[f"{k}_10mm"] - 0.66) < 0.015, (k, r[f"{k}_10mm"])
        assert r[f"{k}_25mm"] == 1.0


def test_sphere_grown_by_2cm_is_0_at_1cm_and_1_at_2_5cm():
    gt = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    grown = trimesh.creation.icosphere(subdivisions=4, radius=0.07)
    r = row(evaluate_objects([pred(grown, name="ball_3", label="ball")], [thing(gt, 3, "ball", observed=gt)]), 3)
    assert r["found"] and r["fscore_10mm"] == 0.0 and r["fscore_25mm"] == 1.0
    assert r["observed_completeness_10mm"] == 0.0 and r["observed_completeness_25mm"] == 1.0


def test_missed_swapped_and_false_objects():
    a, b, c = cube(at=(0, 0, 0)), cube(0.08, at=(0.5, 0, 0)), cube(0.12, at=(0, 0.6, 0))
    things = [thing(a, 1, observed=a, mass=0.5), thing(b, 2, observed=b), thing(c, 3, observed=c)]
    # listed in the other order, named after the wrong ids; one on nothing; c missed
    preds = [pred(b.copy(), "box_7", role="dynamic", mass_kg=0.4), pred(a.copy(), "box_9", role="dynamic", mass_kg=0.6),
             pred(cube(at=(-0.6, 0, 0)), "box_4", role="static", reason="too little evidence")]
    res = evaluate_objects(preds, things)
    assert [row(res, i)["prediction"] for i in (1, 2, 3)] == ["box_9", "box_7", None]
    assert row(res, 3)["found"] is False and row(res, 3)["fscore_25mm"] == 0.0 and row(res, 3)["role"] == "n/a"
    assert res["false_objects"] == ["box_4"]
    assert abs(row(res, 1)["mass_error"] - 0.2) < 1e-12 and row(res, 2)["mass_error"] is None
    s = res["summary"]
    assert s["n_gt_things"] == 3 and s["n_found"] == 2 and abs(s["found_share"] - 2 / 3) < 1e-12
    # the missed thing counts 0 in the mean over all, not in the mean over the found
    assert abs(s["mean_fscore_25mm"] - 2 / 3) < 1e-12 and s["mean_fscore_25mm_found"] == 1.0
    assert s["n_false_objects"] == 1 and s["dynamic_share"] == 1.0 and abs(s["median_abs_mass_error"] - 0.2) < 1e-12


def test_half_an_object_is_found_on_its_observed_part_and_scored_on_the_complete_one():
    """A prediction of only the seen top half of a 10 cm cube (top + upper half of the sides): found
    (recall over the observed part is 1), but against the complete cube its recall is the half it
    holds plus the lower sides' upper 1 (2.5) cm: (0.03 + 0.004) / 0.06 at 1 cm, (0.03 + 0.01) / 0.06
    at 2.5 cm (the bottom is 5 cm away)."""
    gt = cube()
    top = trimesh.creation.box(extents=[0.1, 0.1, 0.05]).apply_translation([0, 0, 0.025])
    top.update_faces(top.face_normals[:, 2] > -0.5)
    r = row(evaluate_objects([pred(top)], [thing(gt, observed=top)]), 1)
    assert r["found"] and r["observed_completeness_10mm"] == 1.0 and r["precision_10mm"] == 1.0
    assert r["match_score"] == 1.0          # matched on what was seen (against the whole cube: 0.8)
    assert abs(r["recall_10mm"] - 0.034 / 0.06) < 0.015 and abs(r["recall_25mm"] - 0.04 / 0.06) < 0.015
    assert abs(r["fscore_25mm"] - 0.8) < 0.015


def test_skipped_prediction_is_attributed_to_a_missed_thing_of_its_class():
    small, big = cube(0.05, at=(0, 0, 0)), cube(0.3, at=(1, 0, 0))
    res = evaluate_objects([PredictedObject("box_5", "box", None, role="skipped", reason="no surface fused")],
                           [thing(small, 1), thing(big, 2)])
    assert row(res, 2)["role"] == "skipped" and row(res, 2)["reason"] == "no surface fused"
    assert row(res, 1)["role"] == "n/a" and res["summary"]["n_skipped"] == 1 and res["false_objects"] == []


def test_sample_count_follows_the_error_budget():
    """The count starts at one point per (2 cm)^2 (at least 500) and doubles until every share's
    standard error is within 0.5 points: a share of 0.66 needs 0.66 * 0.34 / 0.005^2 = 8976 points,
    i.e. 16 000 after doubling from 500; shares of 1 need no more than the first draw."""
    from psimap.metrics.geometry import raycasting_scene
    from psimap.metrics.objects import distances_within_budget

    def count(p, g):
        samples = SurfaceSamples(np.asarray(p.vertices, float), np.asarray(p.faces), (0, 0, 0))
        return len(distances_within_budget(samples, raycasting_scene(np.asarray(g.vertices, float), np.asarray(g.faces))))

    assert count(cube(at=(0.02, 0, 0)), cube()) == 16_000
    assert count(cube(at=(0.005, 0, 0)), cube()) == 500
    assert count(cube(1.0), cube(1.0)) == 15_000            # 6 m^2 at (2 cm)^2


def test_deterministic_and_seeded():
    gt = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    p = trimesh.creation.icosphere(subdivisions=3, radius=0.057)
    run = lambda seed: row(evaluate_objects([pred(p)], [thing(gt, observed=gt)], seed=seed), 1)   # noqa: E731
    assert run(0) == run(0)
    assert run(0)["precision_10mm"] == 1.0


# --------------------------------------------------------------------------------------------------
# an export folder, end to end

CLASSES = [(1, "floor", False), (2, "table", True), (3, "box", True), (4, "ball", True)]
TABLE_H = 0.4


def gt_scene():
    """(meshes, instance ids, semantic ids): a floor, a table (a static furniture class), a box on it and
    a ball on the floor."""
    floor = trimesh.creation.box(extents=[2.0, 2.0, 0.02]).apply_translation([0, 0, -0.01])
    table = trimesh.creation.box(extents=[0.6, 0.4, TABLE_H]).apply_translation([0, 0, TABLE_H / 2])
    box = trimesh.creation.box(extents=[0.12, 0.08, 0.07]).apply_translation([0.05, 0.0, TABLE_H + 0.035])
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.06).apply_translation([0.0, -0.45, 0.06])
    return [floor, table, box, ball], [0, 11, 12, 13], [1, 2, 3, 4]


def cameras(R):
    from psimap.camera import camera_rig, look_at

    c2ws = [look_at(np.array([1.1 * np.cos(a), 1.1 * np.sin(a), 0.9]), np.array([0.0, -0.1, 0.25]))
            for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
    rig = camera_rig(c2ws, 96, 72, 80.0)
    T = np.eye(4)
    T[:3, :3] = R
    rig["c2w"] = np.stack([T @ c for c in rig["c2w"]])
    return rig


def write_data(root, R):
    """DATA (turned by R): frames rendered from the GT scene, gt/mesh.ply, gt/objects (the ball too),
    gt/instances.json with the box's mass."""
    import open3d as o3d

    from psimap.data.frames import ClassInfo, Frame
    from psimap.data.scene_format import write_scene
    from raycast import labelled_depth

    meshes, iids, sids = gt_scene()
    meshes = [m.copy().apply_transform(np.block([[R, np.zeros((3, 1))], [np.zeros((1, 3)), 1]])) for m in meshes]
    scene = trimesh.util.concatenate(meshes)
    finst = np.concatenate([np.full(len(m.faces), i) for m, i in zip(meshes, iids)])
    fsem = np.concatenate([np.full(len(m.faces), s) for m, s in zip(meshes, sids)])
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(scene.vertices.astype(np.float32)), o3d.core.Tensor(scene.faces.astype(np.uint32)))
    rig, frames = cameras(R), []
    for i, c2w in enumerate(rig["c2w"]):
        K, (w, h) = rig["K"][i], (rig["width"], rig["height"])
        depth, inst, sem = labelled_depth(rc, K, c2w, w, h, finst, fsem)
        frames.append(Frame(rgb=np.full((h, w, 3), 0.5, np.float32), depth=depth, K=K, c2w=c2w, semantic=sem,
                            instance=inst, gt_semantic=sem, gt_instance=inst, name=f"frame_{i:03d}"))
    instances = [{"id": 11, "semantic": 2, "name": "table"}, {"id": 12, "semantic": 3, "name": "box", "mass_kg": 0.2},
                 {"id": 13, "semantic": 4, "name": "ball"}]
    write_scene(root, frames, [ClassInfo(*c) for c in CLASSES], gt_mesh=scene, gt_face_instance=finst,
                gt_face_semantic=fsem, gt_objects={i: m for m, i in zip(meshes, iids) if i},
                gt_instances=instances)
    return root


def checkpoint(path, R):
    """The map predicts the floor, table and box, not the ball, and a box on the floor that is not there."""
    from psimap.scene import scene_from_meshes

    meshes, iids, sids = gt_scene()
    ghost = trimesh.creation.box(extents=[0.1, 0.1, 0.1]).apply_translation([0.0, 0.45, 0.05])
    meshes, iids, sids = meshes[:3] + [ghost], iids[:3] + [14], sids[:3] + [3]
    scene = scene_from_meshes(meshes, iids, sids, [{"id": i, "name": n, "isthing": t} for i, n, t in CLASSES],
                              cameras(np.eye(3)), colors=[(0.5, 0.5, 0.5), (0.6, 0.4, 0.2), (0.9, 0.2, 0.1),
                                                          (0.1, 0.3, 0.9)])
    if not np.array_equal(R, np.eye(3)):
        scene = scene.rotated(R)
    scene.save(path)
    return path


TURNED = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])       # z -> y: what phones give


def cli(*args):
    return subprocess.run([str(PSIMAP), *map(str, args)], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """{frame: (DATA, export folder)} for the upright and the turned capture."""
    out = {}
    for frame, R in (("upright", np.eye(3)), ("turned", TURNED)):
        tmp = tmp_path_factory.mktemp(frame)
        data = write_data(tmp / "data", R)
        ckpt = checkpoint(tmp / "scene.ckpt", R)
        r = cli("export", ckpt, "--out", tmp / "export", "--completion", "none", "--no-check", "--min-dynamic", "0")
        assert r.returncode == 0, r.stderr[-2000:]
        out[frame] = (data, tmp / "export", ckpt)
    return out


@pytest.fixture(scope="module")
def upright(exported, tmp_path_factory):
    """`psimap eval EXPORT DATA --json --plot` of the upright capture: (result, plot path)."""
    data, export, _ = exported["upright"]
    plot = tmp_path_factory.mktemp("plot") / "objects.png"
    r = cli("eval", export, data, "--json", "--plot", plot)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout), plot


def test_export_folder_rows_roles_and_false_objects(upright):
    res, plot = upright
    assert set(res) == {"objects"}
    rows = {x["class"]: x for x in res["objects"]["per_object"]}
    assert set(rows) == {"table", "box", "ball"}
    table, box, ball = rows["table"], rows["box"], rows["ball"]
    assert table["found"] and table["prediction"] == "table_11" and table["role"] == "static"
    assert table["static_class"] and "furniture" in table["reason"]
    assert box["found"] and box["prediction"] == "box_12" and box["role"] == "dynamic" and box["reason"] is None
    assert box["fscore_25mm"] > 0.85 and box["observed_completeness_25mm"] > 0.9
    # the ring of cameras sees all but the bottom: 376 of 472 cm^2
    assert 0.72 < box["seen_fraction"] <= 0.80 and abs(box["size_m"] - np.linalg.norm([0.12, 0.08, 0.07])) < 1e-6
    assert box["gt_mass_kg"] == 0.2 and box["mass_kg"] > 0 and abs(box["mass_error"] - (box["mass_kg"] / 0.2 - 1)) < 1e-9
    assert not ball["found"] and ball["fscore_10mm"] == 0 and ball["role"] == "n/a"
    s = res["objects"]["summary"]
    assert s["n_gt_things"] == 3 and s["n_found"] == 2 and s["n_movable_found"] == 1 and s["dynamic_share"] == 1.0
    assert res["objects"]["false_objects"] == ["box_14"] and s["n_false_objects"] == 1
    assert abs(s["mean_fscore_25mm"] - (table["fscore_25mm"] + box["fscore_25mm"]) / 3) < 1e-9
    assert plot.stat().st_size > 10_000


def test_turned_capture_gives_the_same_scores(exported, upright):
    """report.json's gravity rotation takes the turned capture to Z-up; the meshes turned back land on
    DATA's turned ground truth with the same scores."""
    data, export, _ = exported["turned"]
    rep = json.loads((export / "report.json").read_text())
    assert not np.allclose(rep["gravity"]["rotation"], np.eye(3))
    r = cli("eval", export, data, "--json")
    assert r.returncode == 0, r.stderr[-2000:]
    turned = {x["class"]: x for x in json.loads(r.stdout)["objects"]["per_object"]}
    for x in upright[0]["objects"]["per_object"]:
        t = turned[x["class"]]
        assert t["found"] == x["found"] and t["prediction"] == x["prediction"]
        for k in ("fscore_10mm", "fscore_25mm", "observed_completeness_25mm"):
            assert abs(t[k] - x[k]) < 0.02, (x["class"], k, t[k], x[k])


def test_checkpoint_objects_of_a_turned_capture(exported, upright, monkeypatch, capsys, tmp_path):
    """`--objects` on a checkpoint: the objects the export would make (extracted Z-up, turned back into
    the capture's frame), no roles, beside the checkpoint's geometry; then the table output."""
    import functools

    import psimap.api
    from psimap.cli import main

    # completion "none", as the fixture's exports: the same objects, and seconds instead of a minute
    monkeypatch.setattr(psimap.api, "predicted_objects",
                        functools.partial(psimap.api.predicted_objects, completion="none"))
    data, _, ckpt = exported["turned"]
    plot = tmp_path / "eval.png"
    assert main(["eval", str(ckpt), str(data), "--objects", "--json", "--samples", "20000", "--plot", str(plot)]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["geometry"]["f1"] > 0.9 and res["panoptic"]["pq"] > 0.5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eval_fit.png", "eval_geometry.png", "eval_objects.png",
                                                          "eval_panoptic.png"]
    assert res["fit"]["coverage"] > 0.9          # the map covers the depth of its own frames
    rows = {x["class"]: x for x in res["objects"]["per_object"]}
    for x in upright[0]["objects"]["per_object"]:
        r = rows[x["class"]]
        assert (r["found"], r["prediction"]) == (x["found"], x["prediction"])
        assert abs(r["fscore_25mm"] - x["fscore_25mm"]) < 0.05, (x["class"], r["fscore_25mm"], x["fscore_25mm"])
        assert r["role"] == "n/a" and r["static_class"] is False
    assert rows["box"]["mass_kg"] > 0 and res["objects"]["false_objects"] == ["box_14"]
    s = res["objects"]["summary"]
    assert s["n_predicted"] == 3 and s["n_found"] == 2 and s["dynamic_share"] is None


def test_table_output(exported, capsys):
    from psimap.cli import main

    data, export, _ = exported["upright"]
    assert main(["eval", str(export), str(data)]) == 0
    text = capsys.readouterr().out
    assert text.startswith("objects (3 GT things, 3 predicted") and "geometry" not in text
    assert "found 2/3 (67%)" in text and "dynamic 1/1 of found movable (100%)" in text
    assert "false objects 1: box_14" in text
    box = next(x for x in text.splitlines() if " box_12 " in x).split()
    assert box[:5] == ["12", "box", box[2], "yes", "box_12"] and "dynamic" in box
    ball = next(x for x in text.splitlines() if " ball " in x).split()
    assert ball[3:5] == ["no", "-"] and ball[5:7] == ["0.000", "0.000"]


def test_bad_inputs_are_one_line(exported, tmp_path):
    data, export, ckpt = exported["upright"]
    nojson = tmp_path / "nojson"
    (nojson / "meshes").mkdir(parents=True)
    r = cli("eval", nojson, data)
    assert r.returncode == 1 and "no report.json" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    # an export whose report lists a mesh that is gone
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(export, broken)
    (broken / "meshes" / "box_12.obj").unlink()
    r = cli("eval", broken, data)
    assert r.returncode == 1 and "missing mesh file" in r.stderr and "box_12" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    # DATA without gt/objects
    nogt = tmp_path / "nogt"
    shutil.copytree(data, nogt, ignore=shutil.ignore_patterns("objects"))
    for args in ((export, nogt), (ckpt, nogt, "--objects")):
        r = cli("eval", *args)
        assert r.returncode == 1 and "gt/objects not found" in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1
    # --objects with a mesh file; no samples
    r = cli("eval", data / "gt" / "mesh.ply", data, "--objects")
    assert r.returncode == 1 and "--objects needs a checkpoint" in r.stderr
    r = cli("eval", export, data, "--samples", "0")
    assert r.returncode == 1 and "samples must be positive" in r.stderr


def test_read_export_roles_masses_and_frame(tmp_path):
    """report.json's entries as predictions: meshes turned back by gravity.rotation, static furniture
    told from objects static for another reason by the outcome's not_dynamic, skipped ones meshless."""
    from psimap.metrics.objects import read_export

    (tmp_path / "meshes").mkdir()
    capture = {"table_1": cube(0.5, at=(0, 0, 0.25)), "box_2": cube(at=(0.3, 0.1, 0.55)), "cup_3": cube(0.06)}
    for name, m in capture.items():
        m.copy().apply_transform(np.block([[TURNED, np.zeros((3, 1))], [np.zeros((1, 3)), 1]])).export(
            tmp_path / "meshes" / f"{name}.obj")
    entry = lambda name, cls, static, why, mass: {      # noqa: E731
        "name": name, "class": cls, "static": static, "static_reason": why, "observed_coverage": 0.8,
        "physics": {"mass_kg": mass}, "files": {"mesh": f"meshes/{name}.obj"}}
    report = {"gravity": {"rotation": TURNED.tolist()},
              "objects": [entry("table_1", "table", True, "static furniture class: 'table'", 20.0),
                          entry("box_2", "box", False, None, 0.3),
                          entry("cup_3", "cup", True, "too little evidence for a rigid body", 0.1)],
              "skipped": [{"name": "ball_4", "instance_id": 4, "class": "ball", "reason": "no surface fused"}],
              "outcome": {"not_dynamic": {"cup_3": "too little evidence for a rigid body"}}}
    (tmp_path / "report.json").write_text(json.dumps(report))
    preds = {p.name: p for p in read_export(tmp_path)}
    assert [(p.role, p.static_class) for p in preds.values()] == [
        ("static", True), ("dynamic", False), ("static", False), ("skipped", False)]
    assert preds["ball_4"].mesh is None and preds["ball_4"].reason == "no surface fused"
    assert preds["box_2"].mass_kg == 0.3 and preds["box_2"].reason is None and preds["cup_3"].observed_coverage == 0.8
    for name, m in capture.items():
        np.testing.assert_allclose(preds[name].mesh.bounds, m.bounds, atol=1e-6)


def test_read_export_rejects_a_bad_report(tmp_path):
    from psimap.metrics.objects import read_export

    (tmp_path / "report.json").write_text("{\"objects\": [{\"class\": \"box\"}]}")
    with pytest.raises(PsimapError, match="not a psimap export report"):
        read_export(tmp_path)
