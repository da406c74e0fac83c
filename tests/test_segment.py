"""`psimap segment`: model-free pseudo-labels, scored against exact ground truth.

Two kinds of scenes: a tiny generated tabletop (the CLI end to end, per-frame things PQ against its
gt/), and hand-built ray-cast scenes for the edge cases (a bowl, a tiny cube, a box against a wall, no
plane at all, invalid depth, a world that is not Z-up).
"""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from psimap.segment.frame import CEILING, FLOOR, OBJECT, SUPPORT, WALL, Capture, segment_frame

W, H = 160, 120
K = np.array([[125.0, 0, 79.5], [0, 125.0, 59.5], [0, 0, 1]])
Z_UP = Capture(up=np.array([0.0, 0.0, 1.0]), floor=0.0)


def look_at(eye, target) -> np.ndarray:
    """OpenCV camera-to-world [4, 4] at `eye` looking at `target`, image up towards +z."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    c2w = np.eye(4)
    c2w[:3, :3] = np.column_stack([right, down, fwd])
    c2w[:3, 3] = eye
    return c2w


def cast(parts, c2w):
    """(depth [H, W], gt instance [H, W]) of meshes `parts` [(trimesh, instance id)] (0 = stuff)."""
    import open3d as o3d

    from tests.raycast import labelled_depth

    import trimesh

    mesh = trimesh.util.concatenate([m for m, _ in parts])          # one geometry: one face index
    face_inst = np.concatenate([np.full(len(m.faces), iid) for m, iid in parts])
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                     o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    depth, inst, _ = labelled_depth(rc, K, c2w, W, H, face_inst, np.zeros(len(face_inst)))
    return depth.astype(np.float64), inst


def room(*things, wall=True):
    """A 4 x 4 m floor at z = 0 and a wall at y = 1.5, plus `things` [(trimesh, id)]."""
    import trimesh

    parts = [(trimesh.creation.box((4, 4, 0.02), trimesh.transformations.translation_matrix([0, 0, -0.01])), 0)]
    if wall:
        parts.append((trimesh.creation.box((4, 0.02, 2.5), trimesh.transformations.translation_matrix([0, 1.51, 1.25])), 0))
    return parts + list(things)


def box(size, centre, iid):
    import trimesh

    return trimesh.creation.box(size, trimesh.transformations.translation_matrix(centre)), iid


def bowl(centre, iid, r=0.09, h=0.07, wall=0.008):
    """An open bowl: a tube with a bottom (its inside seen from above is a second surface)."""
    import trimesh

    tube = trimesh.creation.annulus(r - wall, r, h)
    tube.apply_translation([0, 0, h / 2])
    base = trimesh.creation.cylinder(r, wall)
    base.apply_translation([0, 0, wall / 2])
    mesh = trimesh.util.concatenate([tube, base])
    mesh.apply_translation(centre)
    return mesh, iid


def best_iou(inst, gt, iid) -> float:
    m = gt == iid
    ids, n = np.unique(inst[m], return_counts=True)
    best = 0.0
    for p, c in zip(ids, n):
        if p:
            best = max(best, c / (m.sum() + (inst == p).sum() - c))
    return best


EYE = look_at([0, -0.6, 1.0], [0, 0.6, 0.0])


def test_floor_wall_and_objects_including_a_bowl_a_tiny_cube_and_a_box_against_the_wall():
    things = [box((0.2, 0.2, 0.25), (-0.35, 0.5, 0.125), 1),
              bowl((0.25, 0.45, 0.0), 2),
              box((0.03, 0.03, 0.03), (0.0, 0.3, 0.015), 3),         # tiny: 3 cm at ~1 m, ~25 pixels
              box((0.3, 0.2, 0.4), (0.1, 1.4, 0.2), 4)]              # touching the wall
    depth, gt = cast(room(*things), look_at([0, -0.5, 1.1], [0, 0.9, 0.1]))
    sem, inst, info = segment_frame(depth, None, K, look_at([0, -0.5, 1.1], [0, 0.9, 0.1]), Z_UP)
    floor_gt = (gt == 0) & (depth > 0)
    # every object is one cluster of its own (the bowl's inside and outside are one)
    for iid in (1, 2, 3, 4):
        assert best_iou(inst, gt, iid) > 0.7, iid
    assert info["objects"] == 4
    # the stuff: floor below, wall behind (each a plane classified by gravity and height)
    assert np.mean(np.isin(sem[floor_gt], (FLOOR, WALL))) > 0.97
    assert {p["class"] for p in info["planes"]} == {"floor", "wall"}
    assert not np.any(sem == CEILING) and not np.any(sem == SUPPORT)


def test_hollow_bowl_is_one_object_seen_from_above():
    c2w = look_at([0, -0.25, 0.75], [0, 0.2, 0.0])
    depth, gt = cast(room(bowl((0.0, 0.2, 0.0), 1), wall=False), c2w)
    sem, inst, info = segment_frame(depth, None, K, c2w, Z_UP)
    assert best_iou(inst, gt, 1) > 0.85
    assert info["objects"] == 1


def test_a_floor_patch_off_the_level_by_centimetres_is_floor_but_a_small_cube_is_not():
    """A real floor bends by centimetres far from the camera: a flat patch 3 cm over the floor level
    that the frame's plane misses is still floor; a 4 cm cube beside it stays an object."""
    things = [box((1.2, 0.8, 0.03), (0.0, 2.2, 0.015), 1), box((0.04, 0.04, 0.04), (0.3, 0.6, 0.02), 2)]
    c2w = look_at([0, -0.5, 1.2], [0, 1.5, 0.0])
    depth, gt = cast(room(*things, wall=False), c2w)
    sem, inst, info = segment_frame(depth, None, K, c2w, Z_UP)
    assert np.mean(sem[gt == 1] == FLOOR) > 0.9
    assert best_iou(inst, gt, 2) > 0.5 and info["objects"] == 1


def test_a_thing_in_front_of_another_is_cut_from_it_by_the_depth_step():
    """Overlapping in the image, 40 cm apart in depth, on one floor: only the depth step parts them."""
    things = [box((0.12, 0.12, 0.2), (0.0, 0.2, 0.1), 1), box((0.5, 0.3, 0.6), (0.0, 0.6, 0.3), 2)]
    c2w = look_at([0, -0.5, 0.5], [0, 0.6, 0.2])
    depth, gt = cast(room(*things, wall=False), c2w)
    sem, inst, info = segment_frame(depth, None, K, c2w, Z_UP)
    assert best_iou(inst, gt, 1) > 0.8 and best_iou(inst, gt, 2) > 0.8
    assert info["objects"] == 2


def test_a_table_top_is_support_and_its_legs_join_it_while_a_thing_on_it_stays_a_thing():
    legs = [box((0.05, 0.05, 0.7), (x, y, 0.35), 1) for x in (-0.45, 0.45) for y in (0.2, 0.8)]
    top = box((1.0, 0.7, 0.04), (0, 0.5, 0.72), 1)
    mug = box((0.08, 0.08, 0.1), (0.1, 0.45, 0.79), 2)
    c2w = look_at([0, -0.7, 1.5], [0, 0.5, 0.5])
    depth, gt = cast(room(*legs, top, mug), c2w)
    sem, inst, info = segment_frame(depth, None, K, c2w, Z_UP)
    table = gt == 1
    assert np.mean(sem[table] == SUPPORT) > 0.9          # top, edges and legs
    assert best_iou(inst, gt, 2) > 0.7
    assert info["objects"] == 1


def test_a_frame_with_no_plane_and_a_frame_with_no_depth():
    import trimesh

    ball = trimesh.creation.icosphere(3, 0.3)
    ball.apply_translation([0, 1.0, 1.0])
    c2w = look_at([0, 0, 1.0], [0, 1.0, 1.0])
    depth, gt = cast([(ball, 1)], c2w)
    sem, inst, info = segment_frame(depth, None, K, c2w, Z_UP)
    assert info["planes"] == [] and info["objects"] == 1
    assert best_iou(inst, gt, 1) > 0.9
    for empty in (np.zeros((H, W)), np.full((H, W), np.nan)):
        sem, inst, info = segment_frame(empty, None, K, c2w, Z_UP)
        assert not sem.any() and not inst.any() and info["objects"] == 0


def test_nan_and_zero_depth_pixels_are_left_unlabelled_and_do_not_split_the_rest():
    things = [box((0.2, 0.2, 0.25), (-0.2, 0.5, 0.125), 1), box((0.15, 0.15, 0.15), (0.25, 0.45, 0.075), 2)]
    depth, gt = cast(room(*things), EYE)
    holes = depth.copy()
    holes[:, 20:26] = np.nan                            # a band of NaN
    holes[80:84, :] = 0.0                               # and a band of zeros
    sem, inst, info = segment_frame(holes, None, K, EYE, Z_UP)
    bad = ~np.isfinite(holes) | (holes <= 0)
    assert not sem[bad].any() and not inst[bad].any()
    for iid in (1, 2):
        assert best_iou(np.where(bad, 0, inst), np.where(bad, 0, gt), iid) > 0.7
    assert np.mean(sem[(gt == 0) & ~bad & (depth > 0)] == FLOOR) > 0.5


def _cabinet_scene():
    """A 0.9 m cabinet with a box and a bottle on its top (set back from its front) and a 1.3 m post
    on the floor beside it; the cabinet top's own up-facing samples (a grid, gaps where the box and
    the bottle stand)."""
    parts = [box((0.6, 0.4, 0.9), (0.0, 0.8, 0.45), 1), box((0.15, 0.15, 0.15), (0.05, 0.75, 0.975), 2),
             box((0.08, 0.08, 0.2), (-0.18, 0.7, 1.0), 3), box((0.1, 0.1, 1.3), (0.55, 0.75, 0.65), 4)]
    xs, ys = np.meshgrid(np.arange(-0.29, 0.3, 0.015), np.arange(0.61, 1.0, 0.015))
    free = ~((np.abs(xs - 0.05) < 0.08) & (np.abs(ys - 0.75) < 0.08))
    free &= ~((np.abs(xs + 0.18) < 0.05) & (np.abs(ys - 0.7) < 0.05))
    top = np.stack([xs[free], ys[free], np.full(free.sum(), 0.9)], 1)
    return parts, top


def test_supports_the_capture_saw_from_above_are_levels_with_filled_footprints():
    """support_levels: the cabinet top (0.24 m^2, two holes where things hide it) and a table top
    around a crate are levels whose footprints cover what stands on them; a small box top and the
    floor are none."""
    from psimap.segment.capture import support_levels
    from psimap.segment.frame import SegmentParams, horizontal_basis

    _, top = _cabinet_scene()
    small = np.stack(np.meshgrid(np.arange(1.0, 1.2, 0.015), np.arange(0.0, 0.2, 0.015)), -1).reshape(-1, 2)
    small = np.column_stack([small, np.full(len(small), 0.3)])                   # a 0.04 m^2 box top
    floor = np.column_stack([np.random.default_rng(0).uniform(-2, 2, (2000, 2)), np.zeros(2000)])
    # a 1.2 x 0.8 m table top at 0.5 m with a 0.4 m crate on its middle: a hole no closing fills
    tx, ty = np.meshgrid(np.arange(-2.0, -0.8, 0.015), np.arange(-1.0, -0.2, 0.015))
    ring = (np.abs(tx + 1.4) > 0.2) | (np.abs(ty + 0.6) > 0.2)
    table = np.column_stack([tx[ring], ty[ring], np.full(ring.sum(), 0.5)])
    P = np.concatenate([top, small, floor, table])
    N = np.tile([0.0, 0.0, 1.0], (len(P), 1))
    up = np.array([0.0, 0.0, 1.0])
    levels = sorted(support_levels(P, N, up, 0.0, SegmentParams()), key=lambda s: s.height)
    assert len(levels) == 2 and abs(levels[0].height - 0.5) < 1e-9 and abs(levels[1].height - 0.9) < 1e-9
    g = lambda x, y: np.array([x, y, 0.0]) @ horizontal_basis(up)                 # noqa: E731
    assert levels[0].footprint(g(-1.4, -0.6)) == 2 and levels[0].footprint(g(-0.5, -0.6)) == 0
    s = levels[1]
    assert s.footprint(g(0.05, 0.75)) == 2 and s.footprint(g(-0.18, 0.7)) == 2   # under the box, the bottle
    assert s.footprint(g(0.0, 0.6)) >= 1 and s.footprint(g(-0.3, 0.99)) >= 1    # the front face, a corner
    assert s.footprint(g(0.0, 0.57)) == 1                                       # the rim, 3 cm out
    assert s.footprint(g(0.0, 0.5)) == 0 and s.footprint(g(0.55, 0.75)) == 0    # the floor in front, the post
    assert s.footprint(g(1.1, 0.1)) == 0                                        # the box top
    assert 0.18 <= (s.cells == 2).sum() * s.cell ** 2 <= 0.24                    # inside the 0.24 m^2 top
    assert 0.28 <= (s.cells >= 1).sum() * s.cell ** 2 <= 0.36                    # and a 4 cm rim
    # without the floor level known, the floor is a support too (a tabletop close-up has none)
    assert len(support_levels(P, N, up, None, SegmentParams())) == 3


@pytest.mark.parametrize("eye", [[0.0, -1.2, 1.0], [0.0, -1.5, 0.95]])
def test_what_stands_on_a_top_seen_edge_on_is_cut_from_its_front_at_the_level_the_capture_saw(eye):
    """A camera a few centimetres over a cabinet sees its top as a sliver: no support plane, and the
    box and the bottle on it run into its front as one cluster. With the level the survey saw from
    above (Capture.supports) each is a cluster of its own; the post beside it, taller than the level
    but outside the footprint, is not cut."""
    from psimap.segment.capture import support_levels
    from psimap.segment.frame import SegmentParams

    parts, top = _cabinet_scene()
    c2w = look_at(eye, [0, 0.8, 0.8])
    depth, gt = cast(room(*parts), c2w)
    _, inst, info = segment_frame(depth, None, K, c2w, Z_UP)
    assert best_iou(inst, gt, 2) < 0.1 and best_iou(inst, gt, 3) < 0.1 and info["objects"] == 2
    up = np.array([0.0, 0.0, 1.0])
    capture = Capture(up=up, floor=0.0,
                      supports=support_levels(top, np.tile(up, (len(top), 1)), up, 0.0, SegmentParams()))
    sem, inst, info = segment_frame(depth, None, K, c2w, capture)
    for iid in (1, 2, 3, 4):
        assert best_iou(inst, gt, iid) > 0.9, iid
    assert info["objects"] == 4
    assert np.all(sem[gt == 2] == OBJECT)


@pytest.mark.parametrize("eye", [[0.0, -0.6, 0.55], [0.3, -0.9, 0.52]])
def test_a_bookcase_is_not_cut_at_its_boards_but_what_stands_on_a_board_is(eye):
    """A camera at the height of a bookcase's lower board: the crate on it runs into the case as one
    cluster. With both boards' levels known, the crate is cut from the case, and the case is not cut
    at either board (its sides rise past them beside the boards; its top board stands on nothing)."""
    from psimap.segment.capture import support_levels
    from psimap.segment.frame import SegmentParams

    sides = [box((0.03, 0.35, 1.6), (x, 0.9, 0.8), 1) for x in (-0.465, 0.465)]
    boards = [box((0.9, 0.35, 0.03), (0.0, 0.9, z - 0.015), 1) for z in (0.5, 1.0, 1.6)]
    crate = box((0.2, 0.2, 0.2), (0.0, 0.9, 0.6), 2)
    xs, ys = np.meshgrid(np.arange(-0.44, 0.45, 0.015), np.arange(0.735, 1.07, 0.015))
    up = np.array([0.0, 0.0, 1.0])
    top = np.concatenate([np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)], 1) for z in (0.5, 1.0)])
    capture = Capture(up=up, floor=0.0,
                      supports=support_levels(top, np.tile(up, (len(top), 1)), up, 0.0, SegmentParams()))
    assert sorted(round(s.height, 3) for s in capture.supports) == [0.5, 1.0]
    c2w = look_at(eye, [0, 0.9, 0.5])
    depth, gt = cast(room(*sides, *boards, crate), c2w)
    _, ref, _ = segment_frame(depth, None, K, c2w, Z_UP)
    _, inst, _ = segment_frame(depth, None, K, c2w, capture)
    assert best_iou(inst, gt, 2) > 0.9
    assert best_iou(inst, gt, 1) >= best_iou(ref, gt, 1) - 0.01
    assert len(np.unique(inst[(gt == 1) & (inst > 0)])) == 1


def test_labels_do_not_depend_on_the_world_frame():
    """The same frame in a Y-up world (a phone capture's) with up given: the same labels."""
    things = [box((0.2, 0.2, 0.25), (-0.2, 0.5, 0.125), 1), bowl((0.25, 0.45, 0.0), 2)]
    depth, gt = cast(room(*things), EYE)
    R = np.eye(4)
    R[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]                  # z-up -> y-up
    ref = segment_frame(depth, None, K, EYE, Z_UP)
    y_up = Capture(up=np.array([0.0, 1.0, 0.0]), floor=0.0)
    turned = segment_frame(depth, None, K, R @ EYE, y_up)
    assert np.mean(ref[0] == turned[0]) > 0.99
    assert ref[2]["objects"] == turned[2]["objects"] == 2
    # and with the wrong up, the floor is a wall and the wall a floor (what a broken gravity would do)
    wrong = segment_frame(depth, None, K, R @ EYE, Z_UP)
    assert np.mean(wrong[0] == ref[0]) < 0.5


# ---- the command, on a tiny generated tabletop ----------------------------------------------------

@pytest.fixture(scope="module")
def tabletop(tmp_path_factory):
    from psimap.data.synthetic import generate

    path = tmp_path_factory.mktemp("segment") / "tabletop"
    generate(path, seed=0, frames=6, width=W, height=H, layout="tabletop", progress=False)
    return path


def things_pq_per_frame(seq, gt_classes, labels) -> float:
    from psimap.metrics.panoptic import panoptic_metrics

    thing = {c.id for c in gt_classes if c.isthing}
    vals = []
    for i, (sem, inst) in enumerate(labels):
        f = seq[i]
        gs = np.where(np.isin(f.gt_semantic, list(thing)), 1, np.where(f.gt_semantic > 0, 2, 0))
        ps = np.where(sem == OBJECT, 1, np.where(sem > 0, 2, 0))
        r = panoptic_metrics([(ps, np.where(ps == 1, inst, 0), gs, np.where(gs == 1, f.gt_instance, 0))], [1])
        vals.append(r["per_class"][1]["pq"])
    return float(np.mean(vals))


def test_cli_labels_a_capture_refuses_to_replace_them_and_train_sees_them(tabletop, tmp_path):
    from psimap.cli import main
    from psimap.data import load

    data = tmp_path / "copy"
    shutil.copytree(tabletop, data)
    before = (data / "semantic" / "frame_00000.png").read_bytes()
    assert main(["segment", str(data)]) == 1                     # the generator's labels are there
    assert (data / "semantic" / "frame_00000.png").read_bytes() == before
    assert not (data / "labels.json").exists() and not (data / "segment_preview.png").exists()
    (data / "mine.png").write_bytes(b"not psimap's")
    assert main(["segment", str(data), "--force", "--preview", str(data / "mine.png")]) == 1
    assert (data / "mine.png").read_bytes() == b"not psimap's"
    assert main(["segment", str(data), "--force"]) == 0
    assert (data / "segment_preview.png").stat().st_size > 10_000
    meta = json.loads((data / "labels.json").read_text())
    assert [c["name"] for c in meta["classes"]] == ["floor", "wall", "ceiling", "support", "object", "furniture"]
    assert len(meta["frames"]) == 6
    seq = load(data)                                             # what `psimap train` reads
    assert [c.name for c in seq.classes if c.isthing] == ["object", "furniture"]
    labels = [(seq[i].semantic, seq[i].instance) for i in range(len(seq))]
    # numbers against ground truth: the things on the table are found one by one, the table is support
    gt_classes = load(tabletop).classes
    pq = things_pq_per_frame(seq, gt_classes, labels)
    assert pq > 0.5, pq
    ids = {c.name: c.id for c in gt_classes}
    f0 = seq[0]
    assert np.mean(labels[0][0][f0.gt_semantic == ids["table"]] == SUPPORT) > 0.6
    assert np.mean(labels[0][0][f0.gt_semantic == ids["floor"]] == FLOOR) > 0.8
    # every other frame: the rest stay unlabelled
    again = tmp_path / "every"
    shutil.copytree(tabletop, again)
    assert main(["segment", str(again), "--force", "--every", "2", "--no-preview"]) == 0
    seq = load(again)
    assert seq[0].semantic is not None and seq[1].semantic is None
    assert not (again / "segment_preview.png").exists()


def test_by_default_the_frames_training_reads_are_labelled(tabletop, tmp_path, monkeypatch):
    """A capture longer than training's frame cap (TRAIN_FRAMES, 300; 4 here) gets labels on the
    frames `psimap train` reads, no more: every one of them labelled, the others not."""
    import psimap.segment.capture as capture
    from psimap.cli import main
    from psimap.data import load
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import prepare_frames

    data = tmp_path / "long"
    shutil.copytree(tabletop, data)
    monkeypatch.setattr(capture, "TRAIN_FRAMES", 4)
    # --force: the overlay replaces the generator's labels; the frames it leaves out have none
    assert main(["segment", str(data), "--force", "--no-preview"]) == 0
    seq = load(data)
    assert [i for i in range(len(seq)) if seq[i].semantic is not None] == [0, 2, 3, 5]     # of 6
    frames = prepare_frames(seq, TrainConfig(max_frames=4), log=lambda m: None)[0]
    assert len(frames) == 4 and all(f.semantic is not None for f in frames)
    # a short capture: all of it
    monkeypatch.setattr(capture, "TRAIN_FRAMES", 6)
    assert main(["segment", str(data), "--force", "--no-preview"]) == 0
    assert all(f.semantic is not None for f in load(data))


def test_frames_labelled_on_threads_get_the_labels_of_one_thread(tabletop, tmp_path):
    """segment_capture labels frames on a thread per core; each frame's RANSAC draws come from its own
    seeded generator (geometry.planes, not Open3D's process-wide one, whose OpenMP team made the
    labels differ run to run: CI once), so one thread and three, twice, give the same labels bit for
    bit."""
    from psimap.data import load
    from psimap.segment.capture import segment_capture

    runs = []
    for run, workers in enumerate((1, 3, 3)):
        data = tmp_path / f"run{run}"
        shutil.copytree(tabletop, data)
        s = segment_capture(data, force=True, preview=None, progress=False, workers=workers)
        assert s["frames"] == 6
        seq = load(data)
        runs.append([(seq[i].semantic, seq[i].instance) for i in range(len(seq))])
    for other in runs[1:]:
        assert all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) for a, b in zip(runs[0], other))
    assert sum(int(inst.max()) for _, inst in runs[0]) > 6            # objects were found


def test_bad_input_is_one_error(tmp_path, capsys):
    from psimap.cli import main

    assert main(["segment", str(tmp_path / "missing")]) == 1
    assert "no such" in capsys.readouterr().err
    assert main(["segment", str(tmp_path), "--every", "-1"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "error" in err


def test_a_cluster_over_furniture_size_is_furniture_and_a_small_one_an_object():
    """Size classes: a 0.9 m tall narrow cabinet (its top too small for a support) is `furniture`
    (exported static, weighed like furniture); a 20 cm box beside it stays an `object`."""
    from psimap.segment.frame import FURNITURE

    things = [box((0.3, 0.3, 0.9), (-0.4, 0.7, 0.45), 1), box((0.2, 0.2, 0.2), (0.3, 0.5, 0.1), 2)]
    c2w = look_at([0, -0.9, 1.3], [0, 0.7, 0.2])
    depth, gt = cast(room(*things), c2w)
    sem, inst, _ = segment_frame(depth, None, K, c2w, Z_UP)
    assert best_iou(inst, gt, 1) > 0.7 and best_iou(inst, gt, 2) > 0.7
    assert np.mean(sem[gt == 1] == FURNITURE) > 0.9
    assert np.mean(sem[gt == 2] == OBJECT) > 0.9
