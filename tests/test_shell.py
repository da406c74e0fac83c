"""The shell model weighs open and hollow objects (issue #16 §5): a mug is a wall around air."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from psimap.exporters.shell import AREAL_DENSITY, UNKNOWN_OPEN, open_cavity, shell_class, shell_mass


def cup(r=0.04, h=0.09, wall=0.005, sections=48):
    outer = trimesh.creation.cylinder(radius=r, height=h, sections=sections).apply_translation([0, 0, h / 2])
    inner = trimesh.creation.cylinder(radius=r - wall, height=h, sections=sections).apply_translation(
        [0, 0, h / 2 + wall])
    return trimesh.boolean.difference([outer, inner], engine="manifold")


def test_classes():
    assert shell_class("coffee mug") == "mug" and shell_class("mugs") == "mug"
    assert shell_class("Pitcher_base") == "pitcher" and shell_class("water pitcher") == "pitcher"
    assert shell_class("glasses") == "glass" and shell_class("cracker box") is None


def test_open_cup_cavity_and_mass():
    m = cup()
    cav = open_cavity(m)
    assert 0.5 < cav.fraction < 0.8          # 0.72 exactly; the voxel walls are a cell thicker
    np.testing.assert_array_equal(cav.axis, [0, 0, 1])
    s = shell_mass(m, "mug", cavity=cav)
    side, bottom = 2 * np.pi * 0.04 * 0.09, np.pi * 0.04**2
    assert abs(s.area - (side + bottom)) / (side + bottom) < 0.01        # the rim's opening left out
    rho = np.sqrt(np.prod(AREAL_DENSITY["mug"]))
    assert abs(s.mass - rho * s.area) < 1e-12 and 0.12 < s.mass < 0.19
    lo, hi = s.mass_range
    assert lo < s.mass < hi and hi / lo == pytest.approx(11.5 / 2.7)
    # no opening mass at the top: the centre of mass is below mid-height
    assert s.com[2] < 0.9 * 0.045 and np.allclose(s.com[:2], 0, atol=1e-3)
    # the solid model would weigh the envelope: the shell is several times lighter
    assert s.mass < 0.25 * m.convex_hull.volume * 2300


def test_shell_inertia_matches_a_sampled_shell():
    m = cup()
    s = shell_mass(m, "mug")
    hull = m.convex_hull
    wall = hull.face_normals[:, 2] < np.cos(np.radians(25))
    pts, _ = trimesh.sample.sample_surface(hull.submesh([np.flatnonzero(wall)], append=True), 200_000, seed=0)
    d = pts - pts.mean(0)
    I = s.mass * (np.eye(3) * (d * d).sum(1).mean() - d.T @ d / len(d))
    np.testing.assert_allclose(s.inertia, I, rtol=0.02, atol=0.01 * np.trace(I) / 3)
    np.testing.assert_allclose(s.com, pts.mean(0), atol=5e-4)


def test_filled_mug_is_still_a_shell_by_its_class():
    """A reconstruction closed the mug's inside: no cavity to measure, the class says shell."""
    solid = trimesh.creation.cylinder(radius=0.04, height=0.09, sections=48).apply_translation([0, 0, 0.045])
    cav = open_cavity(solid)
    assert cav.fraction < 0.02
    s = shell_mass(solid, "coffee mug", cavity=cav)
    assert s is not None and s.key == "mug" and 0.12 < s.mass < 0.19
    assert shell_mass(solid, "can", cavity=cav) is None          # a can of food is no shell


def test_lying_cup_of_unknown_class_opens_sideways():
    m = cup().apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    cav = open_cavity(m)
    assert cav.fraction > 0.5 and abs(cav.axis[1]) == 1.0
    s = shell_mass(m, "object", cavity=cav)
    assert s.key == "open cavity" and s.areal_density == pytest.approx(np.sqrt(np.prod(UNKNOWN_OPEN)))


@pytest.mark.parametrize("name", ["banana", "drill", "closed box with a void"])
def test_concave_or_closed_solids_are_not_shells(name):
    if name == "banana":       # a bent solid: its concave side is not walled in
        m = trimesh.creation.torus(major_radius=0.08, minor_radius=0.018)
        m = trimesh.boolean.intersection([m, trimesh.creation.box(extents=[0.3, 0.3, 0.3]).apply_translation(
            [0, 0.15, 0])], engine="manifold")
    elif name == "drill":      # a body and a handle, lying flat: the gap between them is open below
        body = trimesh.creation.box(extents=[0.18, 0.05, 0.05]).apply_translation([0, 0.06, 0.025])
        grip = trimesh.creation.box(extents=[0.04, 0.12, 0.05]).apply_translation([0.07, 0, 0.025])
        m = trimesh.boolean.union([body, grip], engine="manifold")
    else:                      # a sealed box with an empty inside: closed on all sides, filled
        outer = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
        m = trimesh.boolean.difference([outer, trimesh.creation.box(extents=[0.08, 0.08, 0.08])], engine="manifold")
    cav = open_cavity(m)
    assert cav.fraction < 0.1, cav
    assert shell_mass(m, "object", cavity=cav) is None
