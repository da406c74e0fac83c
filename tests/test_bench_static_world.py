"""benchmarks/static_world.py: its scene builders (no export), so the benchmark does not rot."""

import numpy as np
import pytest
from scripts import load_script

B = load_script("benchmarks/static_world.py", "bench_static_world")
SMALL = dict(width=64, height=48, views=6)


def _ids(scene):
    return scene.surfels["instance_id"].numpy(), scene.surfels["semantic_id"].numpy()


def test_hollow_mug_is_a_watertight_container():
    mug = B.hollow_mug(radius=0.042, height=0.1, wall=0.005)
    assert mug.is_watertight and mug.is_winding_consistent
    # wall and floor of 5 mm around air, plus a handle: far less than the solid cylinder's 554 cm3
    solid = np.pi * 0.042**2 * 0.1
    assert 0.15 * solid < mug.volume < 0.3 * solid, mug.volume * 1e6
    np.testing.assert_allclose(mug.bounds[0, 2], 0.0, atol=1e-9)
    assert mug.bounds[1, 0] > 0.042 + 0.02                # the handle sticks out on +x


def test_arc_cameras_look_at_the_target_from_hand_height():
    cams = B.arc_cameras([0.0, 0.3, 0.74], 0.9, np.linspace(-1.2, 1.2, 10), 96, 72)
    c2w = cams["c2w"]
    assert c2w.shape == (10, 4, 4) and cams["K"].shape == (10, 3, 3)
    z = c2w[:, 2, 3]
    assert z.min() >= 1.2 - 1e-9 and z.max() <= 1.6 + 1e-9 and z.max() - z.min() > 0.3
    towards = np.array([0.0, 0.3, 0.74]) - c2w[:, :3, 3]
    towards /= np.linalg.norm(towards, axis=1, keepdims=True)
    np.testing.assert_allclose(np.einsum("ij,ij->i", c2w[:, :3, 2], towards), 1.0, atol=1e-9)
    horizontal = np.linalg.norm(c2w[:, :2, 3] - [0.0, 0.3], axis=1)
    np.testing.assert_allclose(horizontal, 0.9, atol=1e-9)


def test_desk_scenes_labelled_and_unlabelled(tmp_path):
    cache = {}
    desk = B.build("stuff-desk", tmp_path, cache=cache, **SMALL)
    void = B.build("unlabelled-desk", tmp_path, cache=cache, **SMALL)
    assert desk.things == void.things == 4
    iid, sid = _ids(desk.scene)
    assert sorted(set(iid.tolist())) == [0, 11, 12, 13, 14]
    classes = {c["id"]: c for c in desk.scene.classes}
    assert classes[3]["name"] == "table" and not classes[3]["isthing"]
    assert set(sid[iid == 12].tolist()) == {5}                        # the mug
    # the desk is stuff (instance 0) in one and void (semantic 0) in the other, the same surfels
    viid, vsid = _ids(void.scene)
    np.testing.assert_array_equal(iid, viid)
    assert (sid == 3).sum() > 1000 and (vsid == 3).sum() == 0
    assert (vsid == 0).sum() == (sid == 3).sum()
    # every thing stands on the desk top
    means = desk.scene.surfels["means"].numpy()
    for k in (11, 12, 13, 14):
        assert abs(means[iid == k, 2].min() - B.DESK_TOP) < 0.01, k


@pytest.mark.parametrize("name", ["y-up", "z-down", "colmap"])
def test_turned_desks_turn_stuff_desk(tmp_path, name):
    cache = {}
    turned = B.build(name, tmp_path, cache=cache, **SMALL)
    ref = cache["stuff-desk"]
    R = turned.rotation
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(R) - 1) < 1e-12 and not np.allclose(R, np.eye(3))
    np.testing.assert_allclose(turned.scene.surfels["means"].numpy(),
                               ref.scene.surfels["means"].numpy() @ R.T.astype(np.float32), atol=1e-5)
    up = R @ [0, 0, 1]
    np.testing.assert_allclose(turned.scene.cameras["c2w"].numpy()[:, :3, 3],
                               ref.scene.cameras["c2w"].numpy()[:, :3, 3] @ R.T, atol=1e-5)
    assert np.degrees(np.arccos(up[2])) > 45                          # really another up


def test_compare_sees_a_yaw_as_the_same_export():
    """compare(): the same objects, turned about z, match; a moved object shows as an offset."""
    c = np.cos(0.5), np.sin(0.5)
    yaw = np.array([[c[0], -c[1], 0], [c[1], c[0], 0], [0, 0, 1]])

    def rep(bounds, rotation):
        return {"gravity": {"rotation": rotation.tolist()}, "outcome": {"dynamic": 1},
                "objects": [{"name": "box_1", "static": False, "bounds": bounds, "physics": {"mass_kg": 0.2}}]}

    a = rep([[0.1, 0.2, 0.7], [0.2, 0.3, 0.8]], np.eye(3))
    centre = yaw @ [0.15, 0.25, 0.75]
    b = rep([centre - 0.05, centre + 0.05], np.eye(3))
    out = B.compare(a, b, yaw)
    assert out["same_roles"] and out["same_outcome"] and out["tilt_deg"] < 1e-6
    assert out["max_offset_mm"] < 1e-6
    b["objects"][0]["bounds"] = [centre - 0.05 + [0.02, 0, 0], centre + 0.05 + [0.02, 0, 0]]
    assert abs(B.compare(a, b, yaw)["max_offset_mm"] - 20) < 1e-6


@pytest.mark.skipif(not B.YCB.is_dir(), reason="../shared/data/ycb not available")
def test_ycb_scans_stand_apart_on_the_table(tmp_path):
    built = B.build("ycb-table", tmp_path, **SMALL)
    assert built.things == 6
    assert built.real_mass == {"banana": 0.066, "bowl": 0.147, "cracker_box": 0.411, "mug": 0.118,
                               "mustard_bottle": 0.603, "power_drill": 0.895}
    names = {c["id"]: c["name"] for c in built.scene.classes}
    iid, sid = _ids(built.scene)
    means = built.scene.surfels["means"].numpy()
    boxes = []
    for k in range(21, 27):
        assert names[int(sid[iid == k][0])] == B.YCB_NAMES[k - 21]
        pts = means[iid == k]
        assert abs(pts[:, 2].min() - B.TABLE_TOP) < 0.01
        boxes.append((pts[:, :2].min(0), pts[:, :2].max(0)))
    for i in range(6):
        for j in range(i + 1, 6):
            (la, ha), (lb, hb) = boxes[i], boxes[j]
            assert not (np.all(la < hb) and np.all(lb < ha)), (B.YCB_NAMES[i], B.YCB_NAMES[j])


def test_ycb_placements_refuse_overlaps():
    import trimesh

    big = [trimesh.creation.box(extents=[0.5, 0.5, 0.1]) for _ in range(2)]
    with pytest.raises(ValueError, match="overlap"):
        B.ycb_placements(big, 0.74)


def test_room_from_the_generator(tmp_path):
    from psimap.data.scene_format import read_gt
    from psimap.data.synthetic import CLASS_ID

    built = B.build("room", tmp_path, width=48, height=36, views=3)
    gt = read_gt(tmp_path / "room-capture")
    iid, sid = _ids(built.scene)
    assert built.things == len(gt.objects) > 3
    assert set(iid.tolist()) == {0, *gt.objects}
    # stuff is floor / wall (/ ceiling) with instance 0; every thing keeps its class
    assert set(sid[iid == 0].tolist()) <= {CLASS_ID["floor"], CLASS_ID["wall"], CLASS_ID["ceiling"]}
    assert CLASS_ID["floor"] in set(sid[iid == 0].tolist())
    for row in gt.instances:
        assert set(sid[iid == row["id"]].tolist()) == {row["semantic"]}
    assert len(built.scene.cameras["names"]) == 3
