"""Generated tabletops (`generate(layout="tabletop")`): things resting on the table and apart, sizes
from apple-sized to large balls, a hand-held orbit that keeps every thing in view, extra objects with
their own classes and masses."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh

from psimap import PsimapError
from psimap.cli import main
from psimap.data import synthetic as G
from psimap.data import synthetic_shapes as S

TINY = dict(frames=12, width=80, height=60)
LAYOUT_SEEDS = range(6)


def _top(lay):
    (c, h, yaw), z = G._top(lay.objects[0])
    return c, h, yaw, z


@pytest.fixture(scope="module")
def layouts():
    return {seed: G.make_tabletop(np.random.default_rng(seed)) for seed in LAYOUT_SEEDS}


def _apple(radius=0.035):
    return trimesh.creation.icosphere(subdivisions=3, radius=radius)


def _open_box():
    """A 12 x 8 x 20 cm box whose top face is missing: a scan with a hole, not watertight."""
    m = trimesh.creation.box(extents=[0.12, 0.08, 0.2])
    keep = m.face_normals[:, 2] < 0.5
    return trimesh.Trimesh(m.vertices + [0.3, -0.2, 0.5], m.faces[keep], process=False)


@pytest.fixture(scope="module")
def extra_scene(tmp_path_factory):
    """A tiny tabletop with three extra objects: a new class with a mass, a new class without one,
    and one named after an existing class."""
    out = tmp_path_factory.mktemp("tab") / "scene"
    extra = [("sugar_box", _open_box(), 0.514), ("apple", _apple(), None),
             ("mug", S.solid_mug(), 0.118)]
    summary = G.generate(out, seed=1, layout="tabletop", n_objects=3, extra_objects=extra, **TINY)
    return out, summary, extra


# ------------------------------------------------------------------------------------------ layout
@pytest.mark.parametrize("seed", LAYOUT_SEEDS)
def test_things_rest_on_the_top_inside_it_and_apart(layouts, seed):
    lay = layouts[seed]
    c, h, yaw, z = _top(lay)
    table, things = lay.objects[0], lay.objects[1:]
    assert lay.kind == "tabletop" and table.shape.kind == "table" and 4 <= len(things) <= 8
    assert [o.instance_id for o in lay.objects] == list(range(1, len(lay.objects) + 1))
    # A real table standing on the floor; walls 1.5-3 m from its centre on all four sides.
    tm = S.to_trimesh(table.solid)
    assert abs(tm.bounds[0, 2]) < 1e-6 and 0.68 <= z <= 0.78 and tm.bounds[1, 2] == pytest.approx(z)
    assert 1.0 - 1e-9 <= 2 * h[0] <= 1.8 and 0.7 - 1e-9 <= 2 * h[1] <= 1.0
    walls = np.r_[lay.half_x - c[0], lay.half_x + c[0], lay.half_y - c[1], lay.half_y + c[1]]
    assert np.all((walls >= 1.5 - 1e-9) & (walls <= 3.0))
    for o in things:
        m = G._world_surface(o)
        assert o.support == table.instance_id
        assert abs(m.bounds[0, 2] - z) < 0.002, f"{o.shape.kind} bottom {m.bounds[0, 2]:.4f} vs top {z:.4f}"
        local = (m.vertices[:, :2] - c) @ G._rot2(yaw)        # footprint in the top's frame
        assert np.all(np.abs(local) <= h + 1e-6), f"{o.shape.kind} hangs over the table's edge"
    for i, a in enumerate(lay.objects):
        for b in lay.objects[i + 1:]:
            assert (a.solid ^ b.solid).volume() < 1e-6, (a.shape.kind, b.shape.kind)   # ^: intersection
    # Resting objects only touch the table: nothing between two things' footprints.
    for i, a in enumerate(things):
        for b in things[i + 1:]:
            assert not G.rects_overlap(a.rect, b.rect, gap=G.TOP_GAP * 0.99)
    # No thing stands behind others from most of the way round.
    assert G._seen_share(things, table).min() >= G.MIN_SEEN_SHARE


def test_sizes_range_from_apple_to_large_ball(layouts):
    kinds = {o.shape.kind for lay in layouts.values() for o in lay.objects[1:]}
    assert kinds == {"ball", "box", "bottle", "mug"}
    for lay in layouts.values():      # every tabletop has a large ball and an apple-sized one
        radii = [o.shape.radius for o in lay.objects if o.shape.kind == "ball"]
        assert max(radii) >= 0.1 and min(radii) <= 0.04
    balls = [o.shape.radius for lay in layouts.values() for o in lay.objects if o.shape.kind == "ball"]
    assert max(balls) >= 0.15 and min(balls) <= 0.035
    # Boxes from ~5 cm a side to 25 cm.
    build = G.TABLETOP_KINDS["box"][1]
    sides = np.array([build(np.random.default_rng(k)).half for k in range(40)]) * 2
    assert sides.min() < 0.06 and sides.max() > 0.23 and sides.min() >= 0.05


@pytest.mark.parametrize("seed", range(3))
def test_orbit_keeps_every_thing_in_view(layouts, seed):
    lay = layouts[seed]
    c, h, yaw, z = _top(lay)
    c2w = G.tabletop_trajectory(lay, TINY["frames"], np.random.default_rng(seed + 100))
    eye = c2w[:, :3, 3]
    dist = np.linalg.norm(eye[:, :2] - c, axis=1)
    assert np.all((dist >= 0.7 - 1e-9) & (dist <= 1.5 + 1e-9)) and np.ptp(dist) > 0.05
    assert np.all((eye[:, 2] >= 1.0) & (eye[:, 2] <= 1.6)) and np.ptp(eye[:, 2]) > 0.05
    az = np.unwrap(np.arctan2(eye[:, 1] - c[1], eye[:, 0] - c[0]))
    assert abs(az[-1] - az[0]) > np.radians(300)              # one orbit round the table
    assert np.all(np.abs(eye[:, :2]) < [lay.half_x - 0.25, lay.half_y - 0.25])
    allm = trimesh.util.concatenate([G._world_surface(o) for o in lay.objects])
    assert trimesh.proximity.ProximityQuery(allm).signed_distance(eye).max() < -0.3
    # Every frame looks down at the top ...
    forward = c2w[:, :3, 2]
    assert np.all(forward[:, 2] < -0.2)
    # ... and every thing is in >= 50 % of the frames with >= 4 pixels, even at 80 x 60.
    mesh = G.build_mesh(lay)
    _, prim, _ = G.cast(G._raycaster(mesh), G.camera_rays(G.intrinsics(80, 60), c2w, 80, 60))
    inst, _ = G.label_maps(prim, mesh)
    px = np.stack([(inst == o.instance_id).reshape(len(c2w), -1).sum(1) for o in lay.objects])
    seen = (px >= 4).mean(1)
    assert seen.min() >= 0.5, dict(zip((o.shape.kind for o in lay.objects), seen))
    # Background: walls or floor around the table are in view.
    assert (inst == 0).mean() > 0.2


def test_placement_keeps_small_things_out_of_hiding():
    """The nominal-orbit check: an apple just behind a large ball is hidden from over 30 % of the orbit
    (from the rest the camera sees past or over the ball), one at the table's side from under 20 %."""
    lay = G.make_tabletop(np.random.default_rng(0), n_objects=1)
    table = lay.objects[0]
    c, h, yaw, z = _top(lay)
    ball = S.ball(np.random.default_rng(0), radii=(0.18, 0.18))
    apple = S.ball(np.random.default_rng(0), radii=(0.03, 0.03))
    along = G._rot2(yaw) @ np.array([1.0, 0.0])
    big = G.Placed(10, ball, 0.0, np.r_[c, z], 1)
    hidden = G.Placed(11, apple, 0.0, np.r_[c + 0.22 * along, z], 1)
    apart = G.Placed(11, apple, 0.0, np.r_[c + G._rot2(yaw) @ np.array([0.0, h[1] - 0.06]), z], 1)
    assert G._seen_share([big, hidden], table)[1] < 0.7
    assert G._seen_share([big, apart], table)[1] > 0.8
    assert G._seen_share([big, hidden], table)[0] == 1.0     # the apple hides nothing of the ball


# ---------------------------------------------------------------------------------- extra objects
def test_extra_objects_get_classes_masses_and_complete_meshes(extra_scene):
    from psimap.data import load
    from psimap.data.scene_format import read_gt

    out, summary, extra = extra_scene
    meta = json.loads((out / "transforms.json").read_text())
    cls = {c["name"]: c for c in meta["classes"]}
    n_fixed = len(G.CLASS_NAMES)
    assert len(cls) == n_fixed + 2                               # "mug" already was a class
    assert cls["sugar_box"] == {"id": n_fixed + 1, "name": "sugar_box", "isthing": True}
    assert cls["apple"] == {"id": n_fixed + 2, "name": "apple", "isthing": True}
    gt = read_gt(out)
    by_name = {}
    for r in gt.instances:
        by_name.setdefault(r["name"], []).append(r)
    assert [r["mass_kg"] for r in by_name["sugar_box"]] == [0.514]
    assert "mass_kg" not in by_name["apple"][0]
    assert [r.get("mass_kg") for r in by_name["mug"]].count(0.118) == 1   # the given one, not a generated mug
    assert by_name["table"][0]["id"] == 1 and len(gt.instances) == summary["objects"] == 1 + 3 + 3
    top = summary["table"]["top"]
    seq = load(out)
    gt_inst = np.stack([seq[i].gt_instance for i in range(len(seq))])
    for (name, mesh, _), r in zip(extra, gt.instances[1:4]):
        assert r["name"] == name and r["semantic"] == cls[name]["id"] and r["support"] == 1
        m = trimesh.load(gt.objects[r["id"]], process=False)
        # The complete given surface, upright (z extent kept), resting on the top.
        assert m.area == pytest.approx(mesh.area, rel=1e-5)
        assert m.extents[2] == pytest.approx(mesh.extents[2], abs=1e-6)
        assert abs(m.bounds[0, 2] - top) < 0.002
        assert set(gt.face_semantic[gt.face_instance == r["id"]].tolist()) == {cls[name]["id"]}
        seen = (gt_inst == r["id"]).reshape(len(seq), -1).sum(1)
        assert (seen >= 4).mean() >= 0.5, (name, seen)
    # The open scan stays open (nothing invented), the closed ones closed.
    assert not trimesh.load(gt.objects[gt.instances[1]["id"]], process=False).is_watertight
    assert trimesh.load(gt.objects[gt.instances[2]["id"]], process=False).is_watertight
    # Pseudo-labels cover the new classes too.
    sem = np.stack([seq[i].semantic for i in range(len(seq))])
    assert (sem == cls["apple"]["id"]).sum() > 0


@pytest.mark.parametrize("extra,kw,msg", [
    ([("apple", _apple(), None)], dict(layout="room"), "layout='tabletop'"),
    ([("wall", _apple(), None)], {}, "stuff class"),
    ([("", _apple(), None)], {}, "non-empty"),
    ([("apple", _apple(), -1.0)], {}, "mass_kg"),
    ([("apple", _apple(35.0), None)], {}, "metres"),
    ([("apple", "not a mesh", None)], {}, "expected"),
    ([("slab", trimesh.creation.box(extents=[0.99, 0.99, 0.02]), 3.0)], {}, "no free spot"),
])
def test_bad_extra_objects(tmp_path, extra, kw, msg):
    args = dict(seed=0, layout="tabletop", frames=2, width=16, height=12) | kw
    with pytest.raises(PsimapError, match=msg):
        G.generate(tmp_path / "bad", extra_objects=extra, **args)
    assert not (tmp_path / "bad").exists()


def test_bad_layout(tmp_path):
    with pytest.raises(PsimapError, match="layout must be one of room, tabletop"):
        G.generate(tmp_path / "bad", layout="kitchen", frames=2, width=16, height=12)
    assert not (tmp_path / "bad").exists()


def test_cli_generate_tabletop(tmp_path, capsys):
    out = tmp_path / "tab"
    rc = main(["generate", str(out), "--layout", "tabletop", "--objects", "2", "--frames", "3",
               "--width", "32", "--height", "24"])
    text = capsys.readouterr().out
    assert rc == 0 and "m table (top at 0." in text and "3 objects" in text
    inst = json.loads((out / "gt" / "instances.json").read_text())
    assert [r["name"] for r in inst][0] == "table" and all(r["support"] == 1 for r in inst[1:])
    with pytest.raises(SystemExit):
        main(["generate", str(tmp_path / "x"), "--layout", "kitchen"])
    assert not (tmp_path / "x").exists()
