"""Things rest flat on what they stand on, and small things keep small meshes (issue #16 §3, §6)."""
from __future__ import annotations

import numpy as np
import trimesh

from psimap.exporters.objects import cut_at_support, with_flat_base


def test_a_sunk_bottom_is_cut_flat_at_the_support():
    """A fused bottle whose bottom sank 2.5 cm (and tilted) into the table it stands on."""
    bottle = trimesh.creation.cylinder(radius=0.04, height=0.22, sections=24)
    bottle.apply_transform(trimesh.transformations.rotation_matrix(np.radians(4), [1, 0, 0]))
    bottle.apply_translation([0, 0, 0.11 + 0.683 - 0.025])
    cut = cut_at_support(bottle, 0.683)
    assert cut is not bottle and cut.is_watertight
    lo = cut.bounds[0, 2]
    assert abs(lo - 0.683) < 1e-6          # manifold3d rounds to float32
    base = cut.vertices[np.abs(cut.vertices[:, 2] - 0.683) < 1e-6]
    assert np.ptp(base[:, 0]) > 0.07 and np.ptp(base[:, 1]) > 0.07      # a whole flat disc, not an edge
    # nothing below the support: no change; a support under a mere sliver: not its support
    assert cut_at_support(cut, 0.683) is cut
    assert cut_at_support(bottle, bottle.bounds[1, 2] - 0.01) is bottle


def test_collider_parts_get_a_flat_base_on_the_support():
    """A hull simplified to a tolerance: one bottom corner 6 mm up. Stood on the plane it rests on an
    edge; with the flat base, on its whole footprint, and no wider than before."""
    pts = np.array([[0, 0, 0], [0.04, 0, 0], [0.04, 0.04, 0.006], [0, 0.04, 0],
                    [0, 0, 0.2], [0.04, 0, 0.2], [0.04, 0.04, 0.2], [0, 0.04, 0.2]], float)
    part = trimesh.convex.convex_hull(pts)
    high = trimesh.convex.convex_hull(pts + [0, 0, 0.05])                  # not at the base: kept
    flat, kept = with_flat_base([part, high], 0.0)
    assert kept is high
    v = np.asarray(flat.vertices)
    base = v[np.abs(v[:, 2]) < 1e-12]
    assert len(base) >= 4 and np.ptp(base[:, 0]) > 0.039 and np.ptp(base[:, 1]) > 0.039
    np.testing.assert_allclose(flat.bounds, part.bounds, atol=1e-12)          # footprint unchanged
    assert flat.is_convex and flat.volume > part.volume


def test_small_objects_keep_small_visual_meshes():
    """A 7 cm box closed into 49k faces (a voxel staircase, a subdivided closing): its visual mesh
    comes back at the face budget for its size, never above the mesh it was fused from."""
    from psimap.exporters.decimate import visual_face_budget
    from psimap.exporters.objects import SceneObject, finish_object

    box = trimesh.creation.box(extents=[0.07, 0.05, 0.04]).apply_translation([0, 0, 0.02])
    dense = box.subdivide().subdivide().subdivide().subdivide().subdivide().subdivide()
    assert len(dense.faces) > 40_000
    cap = visual_face_budget(dense, 0.0025, source_faces=10_919)
    assert 200 <= cap <= 3000
    assert visual_face_budget(dense, 0.0025, source_faces=150) == 200        # never under the floor
    table = trimesh.creation.box(extents=[1.6, 0.8, 0.04])
    assert visual_face_budget(table, 0.01) > cap                           # bigger things get more

    # a fused surface is rough: no coarser mesh stays within a 1 mm budget of every bump, and the
    # error budget alone would keep all 20 k faces of this 7 cm ball
    rng = np.random.default_rng(0)
    rough = trimesh.creation.icosphere(subdivisions=5, radius=0.035)
    rough.vertices += rng.normal(0, 0.0015, rough.vertices.shape)
    obj = SceneObject(1, "ball", rough)
    obj.source = rough
    obj.measured.faces_before = 10_919
    finish_object(obj, decimation_budget=0.001, collision_tolerance=0.005)
    assert obj.measured.face_budget == visual_face_budget(rough, 0.001, 10_919) < 3000
    assert len(obj.mesh.faces) <= obj.measured.face_budget and obj.mesh.is_watertight
    assert obj.measured.decimation_error < 0.006


def test_a_reconstructed_ball_gets_a_sphere_not_a_lying_cylinder():
    """A fused ball is a little out of round (6.7 x 6.9 x 7.3 cm): a cylinder on its side fits it
    within the tolerance too, and rolls off the cabinet it rests on; the sphere follows it best."""
    from psimap.exporters.collision import collision_geometry

    ball = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    ball.apply_scale([0.0335, 0.0345, 0.0365])
    ball.apply_transform(trimesh.transformations.rotation_matrix(np.radians(30), [1, 1, 0]))
    c = collision_geometry(ball, 0.012)
    assert c.kind == "sphere", (c.kind, c.error)
    can = trimesh.creation.cylinder(radius=0.033, height=0.12, sections=32)
    assert collision_geometry(can, 0.006).kind == "cylinder"
    box = trimesh.creation.box(extents=[0.1, 0.06, 0.04])
    assert collision_geometry(box, 0.004).kind == "box"
