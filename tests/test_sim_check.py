"""psimap.sim.check_mjcf: load failure, penetration nudge, settle drift, ball primitive vs hull."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from psimap import PsimapError
from psimap.sim.check import check_mjcf

BOX = """<mujoco><compiler angle="radian"/><option timestep="0.002"/><worldbody>
<geom name="floor" type="plane" size="0 0 0.05"/>
<body name="box" pos="0 0 {z}"><freejoint/>
<geom type="box" size="0.1 0.1 0.05" mass="1"/></body>
{extra}</worldbody></mujoco>"""


def _write(tmp_path, text, name="scene.xml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_resting_box_passes(tmp_path):
    r = check_mjcf(_write(tmp_path, BOX.format(z=0.05, extra="")))
    assert r["passed"], r["failures"]
    assert r["bodies"] == 1 and r["nudges"] == {}
    assert r["min_contact_dist"] >= -1e-3
    assert r["drift"]["box"] < 1e-3
    assert r["sim_seconds_per_wall_second"] > 0


def test_penetration_is_nudged_and_reported(tmp_path):
    p = _write(tmp_path, BOX.format(z=0.04, extra=""))      # 1 cm into the floor
    r = check_mjcf(p)
    assert r["passed"], r["failures"]
    assert r["nudges"]["box"] == pytest.approx([0, 0, 0.01], abs=1.5e-3)
    assert r["min_contact_dist"] >= -1e-3
    assert 'pos="0 0 0.05' in p.read_text()                # the file itself was fixed
    r2 = check_mjcf(_write(tmp_path, BOX.format(z=0.04, extra=""), "b.xml"), resolve=False)
    assert not r2["passed"] and "penetration" in r2["failures"][0]


def test_penetration_into_a_wall_is_resolved_sideways(tmp_path):
    """A box resting on the floor sunk 4 mm into a static wall (a reconstruction that fused an
    object touching the wall a few mm deep, as on a 7-Scenes capture): it leaves the wall along the
    contact normal, stays on the floor and passes. Lifting it (the old rule) never clears a vertical
    face: the box went up in 4 mm steps, the penetration stayed and the check failed."""
    wall = '<body name="wall" pos="0.246 0 0.5"><geom type="box" size="0.15 0.5 0.5"/></body>\n'
    p = _write(tmp_path, BOX.format(z=0.05, extra=wall))
    r = check_mjcf(p)
    assert r["passed"], r["failures"]
    dx, dy, dz = r["nudges"]["box"]
    assert dx == pytest.approx(-0.004 - 2e-4, abs=3e-4) and abs(dy) < 1e-4 and abs(dz) < 1e-4
    assert r["min_contact_dist"] >= -1e-3 and r["drift"]["box"] < 1e-3
    assert r["static_bodies"] == ["wall"]


def test_penetration_into_a_tilted_support_is_resolved_straight_up(tmp_path):
    """A box sunk 3 mm into a static ramp tilted 20 degrees (an object on a sloped hull face): it
    goes straight up until the contact plane is cleared (3 mm / cos 20), never sideways along the
    normal, which slides an object near a support's edge off it."""
    import mujoco

    from psimap.sim.check import resolve_penetration

    tilt = np.radians(20.0)
    ramp = (f'<body name="ramp" pos="0 0 0.1" euler="0 {tilt:.6f} 0"><geom type="box" size="0.5 0.5 0.1"/>'
            '</body>\n')
    box = ('<body name="box" pos="0 0 0" euler="0 {t:.6f} 0"><freejoint/>'
           '<geom type="box" size="0.05 0.05 0.05" mass="0.2"/></body>\n').format(t=tilt)
    # the box's bottom face 3 mm below the ramp's top face, along the ramp's normal, over its centre
    n = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    centre = np.array([0, 0, 0.1]) + n * (0.1 + 0.05 - 0.003)
    box = box.replace('pos="0 0 0"', 'pos="{:.6f} {:.6f} {:.6f}"'.format(*centre))
    text = """<mujoco><compiler angle="radian"/><option timestep="0.002"/><worldbody>
<geom name="floor" type="plane" size="0 0 0.05"/>{}{}</worldbody></mujoco>""".format(ramp, box)
    p = _write(tmp_path, text)
    nudges = resolve_penetration(p, max_gap=0.0)
    dx, dy, dz = nudges["box"]
    assert abs(dx) < 1e-6 and abs(dy) < 1e-6
    assert dz == pytest.approx((0.003 + 2e-4) / np.cos(tilt), abs=2e-4)
    model = mujoco.MjModel.from_xml_path(str(p))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    assert min((data.contact[i].dist for i in range(data.ncon)), default=0.0) >= -1e-3


def test_free_bodies_side_by_side_the_lighter_one_leaves(tmp_path):
    # two boxes on the floor, 4 mm into each other sideways: the 0.2 kg one leaves the 1 kg one
    light = ('<body name="light" pos="0.146 0 0.05"><freejoint/>'
             '<geom type="box" size="0.05 0.05 0.05" mass="0.2"/></body>\n')
    r = check_mjcf(_write(tmp_path, BOX.format(z=0.05, extra=light)))
    assert r["passed"], r["failures"]
    assert list(r["nudges"]) == ["light"]
    assert r["nudges"]["light"] == pytest.approx([0.004 + 2e-4, 0, 0], abs=3e-4)


def test_floating_object_falls_and_fails(tmp_path):
    # 45 cm above the floor: not resting, and a scene where it falls is not what was scanned
    r = check_mjcf(_write(tmp_path, BOX.format(z=0.5, extra="")))
    assert r["unsupported"] == ["box"] and "box" not in r["drift"]
    assert r["fell"]["box"] == pytest.approx(0.45, abs=0.01)
    assert not r["passed"] and any("unsupported object(s) fell" in f for f in r["failures"])
    # 3 mm above it: lowered onto the floor (reported as a negative nudge) and passes
    r2 = check_mjcf(_write(tmp_path, BOX.format(z=0.053, extra=""), "low.xml"))
    assert r2["passed"] and r2["unsupported"] == [] and r2["fell"] == {}
    assert r2["nudges"]["box"] == pytest.approx([0, 0, -0.003], abs=3e-4)


def test_hovering_stack_is_lowered_bottom_first(tmp_path):
    # a box 15 mm above a static table's top, a second box 8 mm above the first: both come down
    # (a reconstruction's underside a voxel above its support would drop in the settle)
    table = '<body name="table" pos="0 0 0.2"><geom type="box" size="0.4 0.3 0.2"/></body>\n'
    top = ('<body name="top" pos="0 0 {z}"><freejoint/>'
           '<geom type="box" size="0.05 0.05 0.05" mass="0.2"/></body>\n').format(z=0.4 + 0.015 + 0.1 + 0.008 + 0.05)
    text = BOX.format(z=0.4 + 0.015 + 0.05, extra=table + top).replace(
        'size="0.1 0.1 0.05" mass="1"', 'size="0.1 0.1 0.05" mass="1"')
    p = _write(tmp_path, text)
    r = check_mjcf(p)
    assert r["passed"], r["failures"]
    assert r["nudges"]["box"] == pytest.approx([0, 0, -0.015], abs=5e-4)
    assert r["nudges"]["top"] == pytest.approx([0, 0, -0.023], abs=5e-4)     # its own gap + the box's
    assert r["max_drift"] < 1e-3 and r["unsupported"] == []
    # without resolving, the same scene drops more than a centimetre: the check would fail
    r2 = check_mjcf(_write(tmp_path, text, "raw.xml"), resolve=False)
    assert not r2["passed"]
    # beyond max_gap nothing is lowered: floating is a broken scene, not a reconstruction gap
    r3 = check_mjcf(_write(tmp_path, text, "far.xml"), max_gap=0.005)
    assert "box" not in r3["nudges"] and not r3["passed"]


def test_toppling_object_fails_drift(tmp_path):
    # a thin pole standing on one edge, tilted 0.2 rad: it falls over
    pole = BOX.format(z="0.2960", extra="").replace('size="0.1 0.1 0.05"', 'size="0.01 0.01 0.3"')
    pole = pole.replace('pos="0 0 0.2960"', 'pos="0 0 0.2960" euler="0.2 0 0"')
    r = check_mjcf(_write(tmp_path, pole))
    assert "box" in r["drift"] and r["drift"]["box"] > 0.05
    assert not r["passed"] and any("moved more than" in f for f in r["failures"])


def test_load_failure_is_an_error(tmp_path):
    with pytest.raises(PsimapError, match="MuJoCo could not load"):
        check_mjcf(_write(tmp_path, "<mujoco><worldbody><geom type='mesh' mesh='nope'/></worldbody></mujoco>"))
    with pytest.raises(PsimapError, match="not found"):
        check_mjcf(tmp_path / "missing.xml")


def test_ball_sphere_primitive_stays_put_hull_rolls(tmp_path):
    """The issue's measurement: a ball's faceted convex hull rolls, a sphere primitive stays."""
    from psimap.exporters.objects import build_object
    from psimap.exporters.pipeline import export_scene

    ball = trimesh.creation.icosphere(1, radius=0.05)          # coarse facets, like a scan
    ball.apply_transform(trimesh.transformations.rotation_matrix(0.3, [1, 1, 0]))
    ball.apply_translation(-ball.bounds[0] * [0, 0, 1])
    obj = build_object(ball, "ball", 1, completion="none", decimation_budget=0.0)
    assert obj.collision.kind == "sphere"
    r = export_scene([obj], tmp_path / "prim", "mjcf")
    assert r["check"]["passed"] and r["check"]["drift"]["ball_1"] < 2e-3
    obj_hull = build_object(ball, "ball", 1, completion="none", decimation_budget=0.0)
    from psimap.exporters.collision import Collision, limit_hull_vertices

    obj_hull.collision = Collision("hull", 0.0, 0.0, parts=[limit_hull_vertices(obj_hull.mesh)])
    obj_hull.physics.com = np.asarray(obj_hull.mesh.center_mass)
    r2 = export_scene([obj_hull], tmp_path / "hull", "mjcf")
    assert r2["check"]["drift"]["ball_1"] > r["check"]["drift"]["ball_1"]


def test_static_body_is_support_not_mover(tmp_path):
    # a static table (no joint) with a box 3 mm inside its top: the box is lifted out, the table is
    # never nudged nor counted as a mover, and the box rests on it
    table = ('<body name="table" pos="0.5 0 0.2"><geom type="box" size="0.4 0.3 0.2"/></body>\n')
    text = BOX.format(z=0.447, extra=table).replace('pos="0 0 0.447"', 'pos="0.5 0 0.447"')
    p = _write(tmp_path, text)
    r = check_mjcf(p)
    assert r["passed"], r["failures"]
    assert r["static_bodies"] == ["table"] and r["bodies"] == 1
    assert list(r["nudges"]) == ["box"] and r["nudges"]["box"] == pytest.approx([0, 0, 0.003], abs=1e-3)
    assert list(r["drift"]) == ["box"] and r["drift"]["box"] < 1e-3 and r["unsupported"] == []
    assert 'name="table" pos="0.5 0 0.2"' in p.read_text()


def test_multi_part_body_hovering_is_found_and_lowered(tmp_path):
    # a "can" made of six stacked slabs (what a convex decomposition gives), its lowest 6 mm above
    # the floor: MuJoCo's mid-phase tree ignores a runtime margin, the gap must still be read
    slabs = "".join(f'<geom type="box" size="0.05 0.05 0.015" pos="0 0 {-0.075 + 0.03 * k:.3f}" mass="0.2"/>'
                    for k in range(6))
    text = BOX.replace('<geom type="box" size="0.1 0.1 0.05" mass="1"/>', slabs).format(z=0.09 + 0.006, extra="")
    r = check_mjcf(_write(tmp_path, text))
    assert r["nudges"]["box"] == pytest.approx([0, 0, -0.006], abs=3e-4)
    assert r["passed"] and r["unsupported"] == [] and r["max_drift"] < 1e-3


def test_gap_between_convex_meshes_is_read_exactly(tmp_path):
    # a box-shaped convex mesh 12 mm above a static slab mesh, off-centre: the gap comes from rays
    # cast down, not from MuJoCo's approximate contact distance at an enlarged margin
    corners = " ".join(f"{x} {y} {z}" for x in (-0.05, 0.05) for y in (-0.04, 0.04) for z in (-0.03, 0.03))
    slab = " ".join(f"{x} {y} {z}" for x in (-0.3, 0.3) for y in (-0.2, 0.2) for z in (-0.02, 0.02))
    text = f"""<mujoco><option timestep="0.002"/><asset><mesh name="cube" vertex="{corners}"/>
<mesh name="slab" vertex="{slab}"/></asset><worldbody>
<geom name="floor" type="plane" size="0 0 0.05"/>
<body name="table" pos="0 0 0.5"><geom type="mesh" mesh="slab"/></body>
<body name="box" pos="0.2 0.1 {0.52 + 0.012 + 0.03}"><freejoint/><geom type="mesh" mesh="cube" mass="0.3"/></body>
</worldbody></mujoco>"""
    r = check_mjcf(_write(tmp_path, text))
    assert r["nudges"]["box"] == pytest.approx([0, 0, -0.012], abs=3e-4)
    assert r["passed"] and r["max_drift"] < 1e-3


def test_lowering_onto_a_ridge_does_not_leave_the_body_inside_it(tmp_path):
    """A box hovers 5 mm over a static ridge whose crest runs under its bottom face between the
    points the downward rays start from: the rays read a 15 mm gap, lowering by it puts the crest
    1 cm into the box, and the check must lift it out again rather than fail on the penetration."""
    import mujoco

    from psimap.sim.check import resolve_penetration

    ridge = ('<body name="ridge" pos="0.01 0 0.1"><geom type="box" size="0.05 0.3 0.05" '
             'euler="0 0.785398 0"/></body>\n')
    crest = 0.1 + 0.05 * np.sqrt(2)
    z = crest + 0.005 + 0.05                          # box centre: its bottom 5 mm over the crest
    p = _write(tmp_path, BOX.format(z=f"{z:.6f}", extra=ridge).replace('size="0.1 0.1 0.05"',
                                                                        'size="0.05 0.05 0.05"'))
    nudges = resolve_penetration(p, max_gap=0.02)
    model = mujoco.MjModel.from_xml_path(str(p))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    worst = min((data.contact[i].dist for i in range(data.ncon)), default=0.0)
    assert worst >= -1.5e-3, worst                    # not left inside the ridge
    dx, dy, dz = nudges.get("box", (0.0, 0.0, 0.0))
    assert -0.006 < dz < 0.0 and abs(dx) < 1e-3 and abs(dy) < 1e-3      # came down onto it, by about its real gap
