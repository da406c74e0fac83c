"""Asset steps one by one: physics, repair (degenerate meshes), decimation, collision, texture."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from psimap import PsimapError
from psimap.exporters import collision as C
from psimap.exporters import physics as P
from psimap.exporters import texture as T
from psimap.exporters.decimate import decimate_to_budget, distance_to_surface, surface_distance
from psimap.exporters.repair import repair_mesh
from psimap.transforms import sample_surface


# ---------------------------------------------------------------- physics
def test_box_mass_inertia_analytic_far_from_origin():
    a, b, c = 0.3, 0.2, 0.1
    box = trimesh.creation.box(extents=[a, b, c])
    box.apply_translation([1000.0, -500.0, 20.0])      # float64 must survive large offsets
    ph = P.mass_properties(box, "thing", density=1000.0)
    m = 1000.0 * a * b * c
    assert ph.mass == pytest.approx(m, rel=1e-9)
    np.testing.assert_allclose(ph.com, [1000.0, -500.0, 20.0], atol=1e-9)
    expect = m / 12 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
    np.testing.assert_allclose(np.diag(ph.inertia), expect, rtol=1e-7)
    np.testing.assert_allclose(np.sort(ph.principal_inertia), np.sort(expect), rtol=1e-7)
    assert np.linalg.det(ph.principal_axes) == pytest.approx(1.0)


def test_density_lookup_by_class_words():
    assert P.lookup(P.DENSITY_KG_M3, "mustard_bottle")[1] == "bottle"
    assert P.lookup(P.DENSITY_KG_M3, "Power Drill")[1] == "drill"
    assert P.lookup(P.DENSITY_KG_M3, "books")[1] == "books"
    assert P.lookup(P.DENSITY_KG_M3, "zzz unknown")[1] == "default"
    assert P.lookup(P.FRICTION, "tennis ball")[0] == P.FRICTION["ball"]


def test_density_table_file(tmp_path):
    f = tmp_path / "d.json"
    f.write_text('{"widget": 1234}')
    assert P.load_density_table(f)["widget"] == 1234.0
    f.write_text('{"widget": -1}')
    with pytest.raises(PsimapError, match="positive"):
        P.load_density_table(f)
    f.write_text("[1, 2")
    with pytest.raises(PsimapError, match="density table"):
        P.load_density_table(f)


def test_mass_properties_of_an_asymmetric_solid_match_trimesh():
    # an L (centroid != vertex mean, off-diagonal inertia) turned and moved far from the origin:
    # a box alone cannot tell the centroid from the vertex mean or a wrong parallel-axis sign
    L = trimesh.boolean.union([trimesh.creation.box(extents=[0.3, 0.06, 0.06]),
                               trimesh.creation.box(extents=[0.06, 0.06, 0.3]).apply_translation([0.12, 0, 0.18])],
                              engine="manifold")
    rng = np.random.default_rng(3)
    for _ in range(8):
        m = L.copy().apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
        m.apply_translation(rng.uniform(-50, 50, 3))
        ph = P.mass_properties(m, "thing", density=640.0)
        assert ph.mass == pytest.approx(640.0 * m.volume, rel=1e-9)
        assert np.linalg.norm(ph.com - m.vertices.mean(0)) > 0.01
        np.testing.assert_allclose(ph.com, m.center_mass, atol=1e-9)
        np.testing.assert_allclose(ph.inertia, 640.0 * m.moment_inertia, rtol=1e-6, atol=1e-12)
        # principal frame: a proper rotation that diagonalises the inertia
        R = ph.principal_axes
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(R @ np.diag(ph.principal_inertia) @ R.T, ph.inertia, rtol=1e-9, atol=1e-12)


def test_mass_of_open_mesh_is_an_error():
    plane = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    with pytest.raises(PsimapError, match="no volume"):
        P.mass_properties(plane, "x")


# ---------------------------------------------------------------- repair: degenerate inputs
def _box(**kw):
    return trimesh.creation.box(extents=kw.get("extents", [0.1, 0.1, 0.1]))


def test_repair_rejects_flat_sliver_and_empty():
    g = np.linspace(0, 0.2, 6)
    xy = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    idx = np.arange(36).reshape(6, 6)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    flat = trimesh.Trimesh(np.c_[xy, np.zeros(36)], np.vstack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]))
    r = repair_mesh(flat)
    assert not r.ok and r.mesh is None and "flat" in r.reason
    sliver = _box(extents=[0.2, 0.1, 0.0005])
    r = repair_mesh(sliver)
    assert not r.ok and ("flat" in r.reason or "sliver" in r.reason)
    assert not repair_mesh(trimesh.Trimesh()).ok
    # all vertices NaN -> nothing valid left
    nan = _box()
    nan.vertices[:] = np.nan
    assert not repair_mesh(nan).ok


def test_repair_zero_volume_collapsed_box():
    b = _box()
    b.vertices[:, 2] = 0.0      # every face collapses onto one plane
    r = repair_mesh(b)
    assert not r.ok


def test_repair_fixes_inverted_and_drops_floaters():
    b = _box()
    b.invert()
    assert b.volume < 0
    floater = _box(extents=[0.005, 0.005, 0.005]).apply_translation([1, 1, 1])
    bad = trimesh.util.concatenate([b, floater])
    r = repair_mesh(bad)
    assert r.ok and r.watertight
    assert r.mesh.volume == pytest.approx(1e-3, rel=1e-6)
    assert any("floating" in s for s in r.steps)


def test_repair_closes_open_bottom_and_drops_a_nonmanifold_fin():
    b = _box()
    keep = b.face_normals[:, 2] > -0.5          # remove the bottom: an object scanned on a table
    open_box = trimesh.Trimesh(b.vertices, b.faces[keep])
    r = repair_mesh(open_box)
    assert r.ok and r.watertight
    assert r.mesh.volume == pytest.approx(1e-3, rel=1e-3)
    # non-manifold: a fin (single triangle) glued on an edge of a closed box
    fin_v = np.vstack([b.vertices, [[0.05, 0.05, 0.3]]])
    e = b.edges_unique[0]
    nm = trimesh.Trimesh(fin_v, np.vstack([b.faces, [[e[0], e[1], len(b.vertices)]]]), process=False)
    assert not nm.is_watertight
    r = repair_mesh(nm)
    # the fin is a separate sliver of area: dropped as a floater, the box comes back exactly
    assert r.ok and r.watertight and r.steps == ["removed 1 floating component(s)"]
    assert len(r.mesh.faces) == 12 and r.mesh.volume == pytest.approx(1e-3, rel=1e-9)
    np.testing.assert_allclose(r.mesh.bounds, b.bounds, atol=1e-12)



def test_repair_turns_each_inside_out_body_outward():
    """Two closed bodies, the smaller inside out: the whole has positive volume, so only the
    per-body inversion test (trimesh's fix_inversion, multibody) turns the small one outward."""
    big = _box()
    small = _box(extents=[0.08, 0.08, 0.08]).apply_translation([0.5, 0, 0])
    small.invert()
    r = repair_mesh(trimesh.util.concatenate([big, small]))
    assert r.ok and r.watertight
    assert r.mesh.volume == pytest.approx(1e-3 + 0.08 ** 3, rel=1e-9)
    assert all(body.volume > 0 for body in r.mesh.split(only_watertight=False))


def test_consistent_winding_flips_the_minority_of_each_piece():
    """exporters.repair.consistent_winding: a sphere with a fifth of its faces flipped comes back
    exactly as drawn (each piece keeps the orientation most of its faces have), two pieces each
    keep their own majority (one inside out stays inside out, wound consistently), a Moebius strip
    (no consistent winding) and faces on an edge of three are left as they are; trimesh's walk
    agrees up to each piece's orientation."""
    from psimap.exporters.repair import consistent_winding, fix_winding

    rng = np.random.default_rng(3)
    ball = trimesh.creation.icosphere(4)
    f = ball.faces.copy()
    flip = rng.random(len(f)) < 0.2
    f[flip] = f[flip][:, ::-1]
    np.testing.assert_array_equal(consistent_winding(f), ball.faces)
    theirs = trimesh.Trimesh(ball.vertices, f, process=False)
    trimesh.repair.fix_winding(theirs)
    ours = consistent_winding(f)
    assert np.array_equal(theirs.faces, ours) or np.array_equal(theirs.faces, ours[:, ::-1])

    box = _box()
    inside_out = box.faces[:, ::-1].copy()
    inside_out[:3] = box.faces[:3]                      # 3 of 12 faces outward: the minority
    two = np.vstack([f, inside_out + len(ball.vertices)])
    fixed = trimesh.Trimesh(np.vstack([ball.vertices, box.vertices + 3.0]), consistent_winding(two), process=False)
    assert fixed.is_winding_consistent
    np.testing.assert_array_equal(fixed.faces[:len(f)], ball.faces)
    np.testing.assert_array_equal(fixed.faces[len(f):], box.faces[:, ::-1] + len(ball.vertices))

    # a Moebius strip of 6 quads: no winding is consistent, nothing changes
    t = np.linspace(0, 2 * np.pi, 7)[:-1]
    ring = np.array([[np.cos(a) * (1 + s * np.cos(a / 2)), np.sin(a) * (1 + s * np.cos(a / 2)), s * np.sin(a / 2)]
                     for a in t for s in (-0.3, 0.3)])
    quads = [[2 * i, 2 * i + 1, 2 * ((i + 1) % 6) + 1, 2 * ((i + 1) % 6)] for i in range(5)] + [[10, 11, 0, 1]]
    strip = np.array([[q[0], q[1], q[2]] for q in quads] + [[q[0], q[2], q[3]] for q in quads])
    np.testing.assert_array_equal(consistent_winding(strip), strip)
    # a fin on an edge of a closed box: that edge ties nothing, the box stays as drawn
    fin = np.vstack([box.faces, [[box.edges_unique[0][0], box.edges_unique[0][1], 8]]])
    np.testing.assert_array_equal(consistent_winding(fin)[:12], box.faces)
    m = trimesh.Trimesh(ball.vertices, f, process=False)
    fix_winding(m)
    np.testing.assert_array_equal(m.faces, ball.faces)
    assert consistent_winding(np.zeros((0, 3), int)).shape == (0, 3)

# ---------------------------------------------------------------- decimation
def test_decimation_probe_follows_the_error_power_law_and_its_floor():
    """next_probe: on errors that fall as a power of the face count it lands on the count that meets
    the budget (stepped half the face tolerance away from the end the last probe moved), inside
    the bracket; with no fall it bisects. _floor: a probe the simplifier could not take below N faces
    raises the bracket's low end to N."""
    from psimap.exporters.decimate import _floor, next_probe

    def err(n):
        return 3.0 * n ** -1.5
    tried = [(np.log(100), err(100)), (np.log(400), err(400))]
    lo, hi = np.log(400), np.log(5000)
    assert np.exp(next_probe(lo, hi, tried, err(1000), None, 0.15)) == pytest.approx(1000, rel=1e-9)
    assert np.exp(next_probe(lo, hi, tried, err(1000), "lo", 0.15)) == pytest.approx(1000 * 1.15 ** 0.5, rel=1e-9)
    assert np.exp(next_probe(lo, hi, tried, err(1000), "hi", 0.15)) == pytest.approx(1000 / 1.15 ** 0.5, rel=1e-9)
    far = next_probe(lo, hi, tried, err(10 ** 6), None, 0.15)     # beyond the bracket: a tenth inside it
    assert far == pytest.approx(hi - 0.1 * (hi - lo))
    flat = [(np.log(100), 0.01), (np.log(400), 0.01)]
    assert next_probe(lo, hi, flat, 0.001, None, 0.15) == pytest.approx(0.5 * (lo + hi))
    assert next_probe(lo, hi, tried[:1], err(1000), None, 0.15) == pytest.approx(0.5 * (lo + hi))
    stuck = trimesh.creation.icosphere(subdivisions=3)                             # 1280 faces
    assert _floor(np.log(32), stuck, 0.1) == pytest.approx(np.log(1280))
    assert _floor(np.log(32), stuck, np.inf) == np.log(32)                         # a broken probe says nothing
    assert _floor(np.log(2000), stuck, 0.1) == np.log(2000)


def test_decimation_meets_budget_and_budget_controls_faces():
    s = trimesh.creation.icosphere(subdivisions=4, radius=0.1)       # 5120 faces
    loose = decimate_to_budget(s, 0.004)
    tight = decimate_to_budget(s, 0.0008)
    assert loose.faces_after < tight.faces_after < 5120
    for r in (loose, tight):
        assert r.hausdorff <= r.budget
        h, _ = surface_distance(s, r.mesh)
        assert h <= r.budget * 1.1           # independent re-measurement (other samples)
        assert r.mesh.is_watertight
    # a too-tight budget keeps the input
    same = decimate_to_budget(s, 1e-7)
    assert same.faces_after == 5120
    # the search stops once its bracket is within face_tol: a probe that missed the budget lies
    # within face_tol below the count it returns (face_tol 0 searches to the iteration cap)
    missed = max(f for f, h, _ in tight.curve if h > tight.budget)
    assert missed < tight.faces_after <= 1.15 * missed
    fine = decimate_to_budget(s, 0.0008, face_tol=0.0)
    assert fine.hausdorff <= fine.budget and len(tight.curve) <= 9
    # a face cap: no probe above it; below what the budget needs, the cap's mesh with its error
    capped = decimate_to_budget(s, 0.0008, max_faces=tight.faces_after // 3)
    assert max(f for f, _, _ in capped.curve) <= tight.faces_after // 3
    assert capped.faces_after <= tight.faces_after // 3 and capped.hausdorff > capped.budget
    assert capped.mesh.is_watertight
    h, _ = surface_distance(s, capped.mesh)
    assert h == pytest.approx(capped.hausdorff, rel=0.2)                # the error it reports is its own
    # the budget held by a quantile of the sample distances (the background's): fewer faces, the
    # reported error still the maximum, over the budget where the few worst samples are
    q99 = decimate_to_budget(s, 0.0008, quantile=0.99)
    assert q99.faces_after < 0.8 * tight.faces_after and q99.hausdorff > q99.budget
    d = distance_to_surface(q99.mesh, sample_surface(s, 20000, 5, with_vertices=True))
    assert np.quantile(d, 0.99) <= q99.budget < d.max()
    roomy = decimate_to_budget(s, 0.0008, max_faces=int(1.2 * tight.faces_after))
    assert max(f for f, _, _ in roomy.curve) <= int(1.2 * tight.faces_after)
    assert roomy.hausdorff <= roomy.budget and roomy.faces_after <= 1.15 * fine.faces_after
    missed = max(f for f, h, _ in roomy.curve if h > roomy.budget)      # the cap topped the bracket
    assert missed < roomy.faces_after <= 1.16 * missed          # (the counts asked, not reached, close it)



def test_decimation_probes_start_from_the_last_candidate_that_met_the_budget(monkeypatch):
    # every probe after one that met the budget asks fewer faces: it simplifies that candidate,
    # not the input (a simplification costs by the faces it starts from); the error stays measured
    # against the input, so the budget holds as before
    from psimap.exporters import decimate as D

    s = trimesh.creation.icosphere(subdivisions=5, radius=0.1)       # 20480 faces
    budget, real = 0.0008, D.simplify_to_count
    probes = []                                 # (faces simplified, faces asked, error of the result)

    def recording(mesh, faces, method="auto"):
        out = real(mesh, faces, method)
        probes.append((len(mesh.faces), int(faces), surface_distance(s, out)[0]))
        return out

    monkeypatch.setattr(D, "simplify_to_count", recording)
    for cap in (None, 4000):
        probes.clear()
        r = D.decimate_to_budget(s, budget, max_faces=cap)
        assert r.hausdorff <= r.budget and r.mesh.is_watertight
        assert surface_distance(s, r.mesh)[0] <= budget * 1.1             # against the input itself
        assert len(probes) >= 3 and all(start > asked for start, asked, _ in probes)
        for k, (start, asked, _) in enumerate(probes):
            # an earlier probe clearly within the budget, with more faces than this one asks
            if any(e <= 0.9 * budget and a > asked for _, a, e in probes[:k]):
                assert start < len(s.faces), (k, probes)
        assert any(start < len(s.faces) for start, _, _ in probes)
        if cap is not None:
            assert probes[0][:2] == (len(s.faces), cap)                  # the cap first, from the input

def test_a_simplification_that_opens_a_few_edges_of_a_closed_solid_is_closed_again(monkeypatch):
    # MeshLab's collapse of a room's carved shelf (132k faces, genus 49) left a 5-edge hole at every
    # count tried: no closed candidate, so the unreduced solid was exported (25x its face budget)
    # and its colliders took a mug's place. Holes up to MAX_PATCH_EDGES edges are closed again; a
    # real opening (a sphere's cut-off cap) stays open
    import pymeshlab

    from psimap.exporters import decimate as D

    s = trimesh.creation.icosphere(subdivisions=4, radius=0.1)        # 5120 faces, closed
    real = pymeshlab.MeshSet.meshing_decimation_quadric_edge_collapse

    def opening(ms, **kw):                      # the collapse, then two faces gone: a small hole
        real(ms, **kw)
        ms.compute_selection_by_condition_per_face(condselect="(fi == 0) || (fi == 1)")
        ms.meshing_remove_selected_faces()

    monkeypatch.setattr(pymeshlab.MeshSet, "meshing_decimation_quadric_edge_collapse", opening)
    out = D.simplify_to_count(s, 1000, "meshlab")
    assert out.is_watertight and 995 <= len(out.faces) <= 1005
    assert out.volume == pytest.approx(s.volume, rel=0.03)
    r = D.decimate_to_budget(s, 0.01, max_faces=1000)
    assert r.mesh.is_watertight and r.faces_after <= 1000
    monkeypatch.undo()
    # the helper on its own: two faces' hole closed, a 40-edge cap opening kept
    holed = s.copy()
    holed.update_faces(np.arange(len(s.faces)) >= 2)
    holed.remove_unreferenced_vertices()
    assert not holed.is_watertight and D.close_small_holes(holed).is_watertight
    cap = s.copy()
    cap.update_faces(s.triangles_center[:, 2] < 0.09)
    cap.remove_unreferenced_vertices()
    ring = int((np.unique(np.sort(cap.edges, 1), axis=0, return_counts=True)[1] == 1).sum())
    assert ring > D.MAX_PATCH_EDGES and not D.close_small_holes(cap).is_watertight


def test_a_fast_simplification_that_collapses_at_the_cap_gives_way_to_meshlab(monkeypatch):
    # fast-simplification kept a room's box closed at its 250-face cap and still came out 72 mm
    # off (MeshLab: 2 mm); the cap's result is kept whatever its error, so at the cap the better
    # of the two collapses is taken. Here fast-simplification shrinks every result by 20 %
    import fast_simplification

    from psimap.exporters import decimate as D

    s = trimesh.creation.icosphere(subdivisions=4, radius=0.1)        # 5120 faces, closed
    real = fast_simplification.simplify

    def shrinking(points, triangles, **kw):
        v, f = real(points, triangles, **kw)
        return 0.8 * np.asarray(v), f

    monkeypatch.setattr(fast_simplification, "simplify", shrinking)
    r = D.decimate_to_budget(s, 0.005, max_faces=1000)
    assert r.mesh.is_watertight and r.faces_after <= 1000
    assert r.hausdorff <= 0.005 and surface_distance(s, r.mesh)[0] <= 0.0055
    assert r.mesh.volume == pytest.approx(s.volume, rel=0.05)


# ---------------------------------------------------------------- collision
def test_primitives_are_recognised():
    ball = trimesh.creation.icosphere(3, radius=0.05).apply_translation([1, 2, 3])
    c = C.collision_geometry(ball)
    assert c.kind == "sphere" and c.size[0] == pytest.approx(0.05, rel=0.02)
    np.testing.assert_allclose(c.transform[:3, 3], [1, 2, 3], atol=1e-3)
    R = trimesh.transformations.random_rotation_matrix(np.random.default_rng(0).random(3))
    box = trimesh.creation.box(extents=[0.3, 0.2, 0.1]).apply_transform(R)
    c = C.collision_geometry(box)
    assert c.kind == "box" and c.error < 1e-4
    np.testing.assert_allclose(np.sort(c.size), [0.05, 0.1, 0.15], atol=1e-5)
    cyl = trimesh.creation.cylinder(radius=0.04, height=0.3, sections=64)
    c = C.collision_geometry(cyl)
    assert c.kind == "cylinder"
    assert c.size[0] == pytest.approx(0.04, rel=0.02) and c.size[1] == pytest.approx(0.15, rel=0.01)


def test_concave_shape_decomposes_within_limits():
    L = trimesh.boolean.union([trimesh.creation.box(extents=[0.3, 0.06, 0.06]),
                               trimesh.creation.box(extents=[0.06, 0.06, 0.3]).apply_translation([0.12, 0, 0.18])],
                              engine="manifold")
    c = C.collision_geometry(L, max_hulls=4)
    assert c.kind == "decomposition"
    assert 2 <= c.hull_count <= 4
    assert c.error <= c.tolerance
    assert all(len(p.vertices) <= C.MAX_HULL_VERTICES for p in c.parts)
    # the single hull is far off: that is why it was not chosen
    assert C.collision_geometry(L, max_hulls=1, coacd_thresholds=()).error > 3 * c.tolerance


def test_decomposition_stops_when_the_hull_cap_binds(monkeypatch):
    # a tolerance nothing meets: once a threshold already returns max_hulls parts, finer ones (each
    # ~3-4x slower) cannot add any, so CoACD runs once, not once per threshold
    U = trimesh.boolean.union([trimesh.creation.box(extents=[0.3, 0.06, 0.06]),
                               trimesh.creation.box(extents=[0.06, 0.06, 0.3]).apply_translation([0.12, 0, 0.18]),
                               trimesh.creation.box(extents=[0.06, 0.06, 0.3]).apply_translation([-0.12, 0, 0.18])],
                              engine="manifold")
    calls = []
    real = C._coacd
    monkeypatch.setattr(C, "_coacd", lambda *a, **k: calls.append(a[1]) or real(*a, **k))
    c = C.collision_geometry(U, 1e-3, max_hulls=2, coacd_thresholds=(0.3, 0.15, 0.08), time_budget=60)
    assert calls == [0.3] and c.hull_count == 2 and c.error > c.tolerance


def test_large_objects_get_more_coacd_faces(monkeypatch):
    # a table-sized U is decimated for CoACD to proportionally more faces than a cup-sized one (a
    # 1.6 m table at the small objects' 600 faces lost its top by up to 4 cm)
    seen = []
    real = C._coacd
    monkeypatch.setattr(C, "_coacd", lambda *a, **k: seen.append(k["max_faces"]) or real(*a, **k))
    U = trimesh.boolean.union([trimesh.creation.box(extents=[0.3, 0.06, 0.06]),
                               trimesh.creation.box(extents=[0.06, 0.06, 0.3]).apply_translation([0.12, 0, 0.18]),
                               trimesh.creation.box(extents=[0.06, 0.06, 0.3]).apply_translation([-0.12, 0, 0.18])],
                              engine="manifold")
    C.collision_geometry(U, 1e-3, coacd_thresholds=(0.3,))
    big = U.copy().apply_scale(5.0)                       # 2.3 m across: 4x the faces (the cap)
    C.collision_geometry(big, 5e-3, coacd_thresholds=(0.3,))
    assert seen == [C.COACD_FACES, 4 * C.COACD_FACES]


def test_coacd_budget_counts_only_coacd_time(monkeypatch):
    """The CPU-time budget of the decomposition counts CoACD's own calls: the distances and clipping
    between them take more process CPU time on a busy machine (pool threads waiting for a core), and
    counting them made the same object stop at a coarser threshold under load. A fake clock: each
    CoACD call costs 0.2 s, each distance pass 10 s (a heavily loaded machine); the same thresholds
    run, and the same collider comes out, as with free distance passes."""
    import time

    from psimap.exporters import decimate as D

    U = trimesh.boolean.union([trimesh.creation.box(extents=[0.3, 0.06, 0.06]),
                               trimesh.creation.box(extents=[0.06, 0.06, 0.3]).apply_translation([0.12, 0, 0.18]),
                               trimesh.creation.box(extents=[0.06, 0.06, 0.3]).apply_translation([-0.12, 0, 0.18])],
                              engine="manifold")
    clock = [0.0]
    monkeypatch.setattr(time, "process_time", lambda: clock[0])
    real_coacd, real_dist = C._coacd, D.distance_to_surface

    def run(distance_cost):
        calls = []

        def coacd(*a, **k):
            calls.append(a[1])
            clock[0] += 0.2
            return real_coacd(*a, **k)

        def dist(*a, **k):
            clock[0] += distance_cost
            return real_dist(*a, **k)
        monkeypatch.setattr(C, "_coacd", coacd)
        monkeypatch.setattr(D, "distance_to_surface", dist)
        c = C.collision_geometry(U, 1e-3, max_hulls=16, coacd_thresholds=(0.3, 0.15, 0.08), time_budget=4.0)
        return calls, c
    quiet, c_quiet = run(0.0)
    busy, c_busy = run(10.0)
    assert quiet == busy == [0.3, 0.15, 0.08]
    assert c_busy.hull_count == c_quiet.hull_count and c_busy.error == c_quiet.error


def test_hull_vertex_limit():
    s = trimesh.creation.icosphere(4, radius=0.1)
    h = C.limit_hull_vertices(s, 64)
    assert len(h.vertices) <= 64 and h.is_watertight and h.volume > 0.8 * s.volume


def test_convex_shape_gets_one_capped_hull():
    # an ellipsoid: no primitive fits it, its own hull (642 vertices) does once capped at
    # MAX_HULL_VERTICES (what every simulator's convex collider allows cheaply)
    e = trimesh.creation.icosphere(3, radius=1.0).apply_scale([0.06, 0.04, 0.025])
    assert len(e.convex_hull.vertices) > 10 * C.MAX_HULL_VERTICES
    c = C.collision_geometry(e)
    assert c.kind == "hull" and c.hull_count == 1 and c.error <= c.tolerance
    hull = c.parts[0]
    assert len(hull.vertices) <= C.MAX_HULL_VERTICES and hull.is_watertight and hull.is_convex
    assert 0.9 * e.volume < hull.volume < 1.1 * e.volume


def test_collider_stays_out_of_neighbour_colliders():
    # a box whose neighbour's collider reaches 6 mm into it (two colliders, each within tolerance
    # of meshes that touch): without obstacles the box primitive fits; with them it is not a
    # candidate and the hull is cut back to clear the neighbour, still within tolerance
    mesh = trimesh.creation.box(extents=[0.2, 0.2, 0.1])
    mesh.apply_translation([0.1, 0.1, 0.05])
    neighbour = trimesh.creation.box(extents=[0.2, 0.2, 0.2])
    neighbour.apply_translation([0.3 - 0.006, 0.1, 0.1])
    depth, axis = C.convex_overlap(mesh, neighbour)
    assert depth == pytest.approx(0.006) and np.allclose(axis, [-1, 0, 0])
    free = C.collision_geometry(mesh, 0.02)
    assert free.kind == "box" and C.penetrates(free.parts, [neighbour])
    c = C.collision_geometry(mesh, 0.02, obstacles=[neighbour])
    assert c.kind == "hull" and not C.penetrates(c.parts, [neighbour])
    assert c.parts[0].bounds[1, 0] == pytest.approx(0.194 - 5e-4, abs=1e-6)
    assert c.error == pytest.approx(0.0065, abs=1e-3) and len(c.parts[0].vertices) <= C.MAX_HULL_VERTICES
    # separated shapes: a negative depth, nothing cut
    far = neighbour.copy()
    far.apply_translation([0.1, 0, 0])
    assert C.convex_overlap(mesh, far)[0] < 0 and C.clip_convex(mesh, [far]) is mesh
    # a part entirely inside an obstacle has nothing left
    assert C.clip_convex(mesh, [trimesh.creation.box(extents=[1, 1, 1])]) is None


def test_a_part_that_carries_a_thing_is_cut_under_it_not_beside_it():
    """A thin board part (3 cm deep in y) and a thing standing 4 cm deep in a notch of it and wider
    than it in y: the least overlap is sideways, and that cut leaves nothing of the board (the
    thing falls through); marked as standing on it (SceneObject.keep_clear's hulls), the board is
    cut under the thing and still carries it."""
    from psimap.exporters.objects import standing_hull

    board = trimesh.creation.box(bounds=[[-0.15, -0.015, 0.0], [0.15, 0.015, 0.1]])
    thing = trimesh.creation.box(bounds=[[-0.04, -0.02, 0.06], [0.04, 0.02, 0.11]])
    assert C.clip_convex(board, [thing]) is None                 # cut beside it: nothing left
    cut = C.clip_convex(board, [standing_hull(thing)])
    assert cut is not None and cut.bounds[1, 2] == pytest.approx(0.06 - 5e-4, abs=1e-6)
    assert C._inside_convex(cut, np.array([[0.0, 0.0, 0.058]]))[0] and C.convex_overlap(cut, thing)[0] <= 0
    # a thing beside the part, not on it, is cleared the short way as before
    side = trimesh.creation.box(bounds=[[0.14, -0.03, 0.02], [0.2, 0.03, 0.08]])
    beside = C.clip_convex(board, [standing_hull(side)])
    assert beside.bounds[1, 0] == pytest.approx(0.14 - 5e-4, abs=1e-6) and beside.bounds[1, 2] == pytest.approx(0.1)


# ---------------------------------------------------------------- texture
def _cam_looking_down(height=1.0, w=64, h=64, f=60.0):
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    c2w = np.eye(4)
    c2w[:3, :3] = np.diag([1.0, -1.0, -1.0])      # z forward = world -z
    c2w[2, 3] = height
    return K, c2w


def test_bake_from_views_colours_seen_texels_only():
    box = trimesh.creation.box(extents=[0.2, 0.2, 0.2])
    v, f, uv, _ = T.unwrap(box)
    K, c2w = _cam_looking_down()
    w = h = 64
    depth = np.zeros((h, w), np.float32)
    # depth of the top face (z = 0.1) as seen from height 1: 0.9 m where the box projects
    ys, xs = np.mgrid[0:h, 0:w]
    xw = (xs - K[0, 2]) / K[0, 0] * 0.9
    yw = -(ys - K[1, 2]) / K[1, 1] * 0.9
    inside = (np.abs(xw) < 0.1) & (np.abs(yw) < 0.1)
    depth[inside] = 0.9
    rgb = np.zeros((h, w, 3), np.float32)
    rgb[..., 0] = 1.0
    img, cov = T.bake_from_views(v, f, uv, [T.View(rgb, depth, K, c2w)], 64,
                                 fallback_vertex_rgb=np.zeros((len(v), 3)))
    # only the top face (1 of 6) is seen: coverage ~ 1/6, the rest stays the black fallback
    assert 0.08 < cov < 0.3
    rows, cols, fid, _ = T.rasterize_uv(f, uv, 64)
    top = np.asarray(trimesh.Trimesh(v, f, process=False).face_normals)[fid, 2] > 0.9
    assert img[rows[top], cols[top], 0].mean() > 200
    assert img[rows[~top], cols[~top], 0].mean() < 30
    # an occluder closer to the camera (depth test): nothing on the box is coloured
    img2, cov2 = T.bake_from_views(v, f, uv, [T.View(rgb, np.where(inside, 0.5, 0).astype(np.float32), K, c2w)],
                                   64, fallback_vertex_rgb=np.zeros((len(v), 3)))
    assert cov2 == 0.0 and img2.max() == 0



def test_rasterize_uv_covers_each_triangle_once_whatever_the_chunk():
    """Two triangles sharing a diagonal tile a 1 x 0.5 rectangle of the atlas: each of its 32 x 16
    texel centres is covered once (none lies on the diagonal), barycentrics give back the texel
    centre; testing 7 candidates at a time gives the same texels in the same order as all at once."""
    uv = np.array([[0, 0], [1, 0], [1, 0.5], [0, 0.5]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    rows, cols, fid, bary = T.rasterize_uv(faces, uv, 32)
    assert len(rows) == len(set(zip(rows.tolist(), cols.tolist()))) == 32 * 16
    assert rows.min() == 16 and rows.max() == 31 and cols.min() == 0 and cols.max() == 31
    np.testing.assert_allclose(bary.sum(1), 1.0, atol=1e-12)
    centre = np.stack([(cols + 0.5) / 32, 1 - (rows + 0.5) / 32], 1)
    np.testing.assert_allclose(np.einsum("pk,pkd->pd", bary, uv[faces[fid]]), centre, atol=1e-12)
    for got, want in zip(T.rasterize_uv(faces, uv, 32, chunk=7), (rows, cols, fid, bary)):
        np.testing.assert_array_equal(got, want)


def test_bake_from_views_weighs_nearer_views_more():
    """Two views straight above a box's top face, 0.9 m and 1.9 m from it, one red, one blue: a
    texel's colour is their mix weighted by cos^4 / z^2, red (1.9 / 0.9)^2 = 4.46 times the blue."""
    box = trimesh.creation.box(extents=[0.2, 0.2, 0.2])
    v, f, uv, _ = T.unwrap(box)
    views = []
    for height, channel in ((1.0, 0), (2.0, 2)):
        K, c2w = _cam_looking_down(height=height)
        ys, xs = np.mgrid[0:64, 0:64]
        d = height - 0.1
        inside = (np.abs((xs - K[0, 2]) / K[0, 0] * d) < 0.1) & (np.abs((ys - K[1, 2]) / K[1, 1] * d) < 0.1)
        rgb = np.zeros((64, 64, 3), np.float32)
        rgb[..., channel] = 1.0
        views.append(T.View(rgb, np.where(inside, d, 0).astype(np.float32), K, c2w))
    img, _ = T.bake_from_views(v, f, uv, views, 64, fallback_vertex_rgb=np.zeros((len(v), 3)))
    rows, cols, fid, bary = T.rasterize_uv(f, uv, 64)
    pos = np.einsum("pk,pkd->pd", bary, v[f[fid]])
    top = np.asarray(trimesh.Trimesh(v, f, process=False).face_normals)[fid, 2] > 0.9
    # texels off the optical axis see both cameras at slightly different angles: the centre ones
    centre = top & (np.abs(pos[:, :2]).max(1) < 0.02)
    red = 1.9 ** 2 / (1.9 ** 2 + 0.9 ** 2)
    assert centre.sum() > 10
    np.testing.assert_allclose(img[rows[centre], cols[centre], 0], 255 * red, atol=3)
    np.testing.assert_allclose(img[rows[centre], cols[centre], 2], 255 * (1 - red), atol=3)


def test_vertex_colors_from_views_depth_tests_each_vertex():
    K, c2w = _cam_looking_down()            # camera 1 m above the origin, looking down -z
    h = w = 64
    rgb = np.zeros((h, w, 3), np.float32)
    rgb[..., 1] = 1.0
    depth = np.full((h, w), 0.9, np.float32)   # a surface at z = 0.1 fills the view
    verts = np.array([[0.0, 0.0, 0.1],        # on the seen surface: green
                      [0.0, 0.0, -0.3],       # 40 cm behind it (occluded): default
                      [0.0, 0.0, 1.5],        # behind the camera: default
                      [5.0, 0.0, 0.1]])       # outside the image: default
    out = T.vertex_colors_from_views(verts, [T.View(rgb, depth, K, c2w)], default=(0.5, 0.5, 0.5))
    np.testing.assert_allclose(out[0], [0.0, 1.0, 0.0])
    np.testing.assert_allclose(out[1:], 0.5)
    # two views that both see the vertex: the mean colour
    rgb2 = np.zeros_like(rgb)
    rgb2[..., 0] = 1.0
    out2 = T.vertex_colors_from_views(verts[:1], [T.View(rgb, depth, K, c2w), T.View(rgb2, depth, K, c2w)])
    np.testing.assert_allclose(out2[0], [0.5, 0.5, 0.0])


def test_texture_size_follows_area():
    small = trimesh.creation.box(extents=[0.05] * 3)
    big = trimesh.creation.box(extents=[0.5] * 3)
    assert T.texture_size(small) < T.texture_size(big) <= 1024


def test_clip_to_support_cuts_and_caps_watertight():
    from psimap.exporters.instance_meshes import clip_to_support

    # a box that hangs 2 cm below its support at z = 0 (overhanging discs): cut flat and closed there
    box = trimesh.creation.box(extents=[0.1, 0.08, 0.12]).apply_translation([0.3, -0.2, 0.04])
    out = clip_to_support(box, 0.0)
    assert out.is_watertight and out.is_winding_consistent
    assert out.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)
    assert out.volume == pytest.approx(0.1 * 0.08 * 0.1, rel=1e-6)
    # already above its support: untouched
    assert clip_to_support(box, -0.5) is box


def test_project_to_surfels_pulls_a_fat_box_onto_its_faces():
    from psimap.exporters.instance_meshes import project_to_surfels

    # oriented points on the faces of a 10 cm cube; the fused mesh is 1 cm too large on every side
    rng = np.random.default_rng(0)
    cube = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    pts, fid = trimesh.sample.sample_surface_even(cube, 3000, seed=0)
    fat = trimesh.creation.box(extents=[0.12, 0.12, 0.12]).subdivide().subdivide()
    fat.vertices += rng.normal(0, 1e-4, fat.vertices.shape)
    out = project_to_surfels(fat, pts, cube.face_normals[fid])
    d_in = np.abs(trimesh.proximity.signed_distance(cube, fat.vertices))
    d_out = np.abs(trimesh.proximity.signed_distance(cube, out.vertices))
    assert np.median(d_in) > 0.009
    assert np.median(d_out) < 0.002          # face interiors land on the faces
    assert len(out.faces) == len(fat.faces) and np.isfinite(out.vertices).all()


def test_support_height_reads_the_floor_under_the_object():
    from psimap.exporters.instance_meshes import support_height

    floor = np.column_stack([np.random.default_rng(1).uniform(-1, 1, (500, 2)), np.full(500, 0.02)])
    table = np.column_stack([np.random.default_rng(2).uniform(2, 3, (200, 2)), np.full(200, 0.7)])
    pts = np.concatenate([floor, table])
    obj = trimesh.creation.box(extents=[0.1, 0.1, 0.1]).apply_translation([0.2, 0.2, 0.07])
    assert support_height(obj, pts) == pytest.approx(0.02)
    assert support_height(obj.copy().apply_translation([2.3, 2.3, 0.7]), pts) == pytest.approx(0.7)
    assert support_height(obj, np.zeros((0, 3))) is None


def test_rest_on_support_gives_a_resting_ball_a_base_under_its_com():
    from psimap.exporters.objects import rest_on_support

    ball = trimesh.creation.icosphere(3, radius=0.05).apply_translation([0.2, 0.1, 0.05])
    out, grew = rest_on_support(ball, 0.0)
    assert grew and out.is_watertight
    base = out.vertices[out.vertices[:, 2] < 1e-3]
    assert np.ptp(base[:, 0]) > 0.03 and np.ptp(base[:, 1]) > 0.03       # a real footprint now
    assert np.abs(base[:, :2].mean(0) - [0.2, 0.1]).max() < 0.01           # under the centre of mass
    assert ball.volume < out.volume < 1.2 * ball.volume                     # only the unseen cap was added
    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1]).apply_translation([0, 0, 0.05])
    assert rest_on_support(box, 0.0) == (box, False)                         # already stands
    assert rest_on_support(ball.copy().apply_translation([0, 0, 0.2]), 0.0)[1] is False   # not resting


def test_rest_on_support_of_a_piece_with_no_volume_is_quiet():
    # a flat fused piece (both sides of a sheet: volume 0) leaning on the support: trimesh's centre
    # of mass is 0 / 0 there (NaN and a RuntimeWarning printed in a real capture's export)
    import warnings

    from psimap.exporters.objects import rest_on_support

    sheet = trimesh.Trimesh([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0.05], [0.1, 0.1, 0.05]],
                            [[0, 1, 2], [1, 3, 2], [0, 2, 1], [1, 2, 3]], process=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out, grew = rest_on_support(sheet, 0.0)
    assert out is sheet and grew is False          # an edge on the support: no footprint to extrude


def test_fused_instance_voxel_is_bounded_by_size_and_renders():
    """Issue #17: a 37 cm ball of 1 mm surfels fused at 0.75 mm voxels gave ~800k faces (minutes,
    or no surface when the voxel hash map gave up). The voxel stays at or above the instance's
    diagonal / MAX_VOXELS_PER_DIAGONAL and what the supersampled renders resolve."""
    import torch

    from psimap.camera import look_at
    from psimap.exporters.instance_meshes import MAX_VOXELS_PER_DIAGONAL, fuse_instance
    from psimap.exporters.texture import View
    from psimap.transforms import rotmat_to_quat

    r = 0.185
    sphere = trimesh.creation.icosphere(4, radius=r).apply_translation([0, 0, r])
    pts, fi = trimesh.sample.sample_surface_even(sphere, 20000, seed=0)
    n = sphere.face_normals[fi]
    # discs tangent to the sphere: any frame whose third axis is the normal
    a = np.cross(n, np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    R = np.stack([a, np.cross(n, a), n], axis=2)
    sizes = {"tiny": 0.001, "coarse": 0.006}
    K = np.array([[280.0, 0, 160], [0, 280.0, 120], [0, 0, 1]])
    views = [View(np.zeros((240, 320, 3), np.float32), np.zeros((240, 320), np.float32), K,
                  look_at(np.array([1.1 * np.cos(t), 1.1 * np.sin(t), 1.0]), np.array([0, 0, r])))
             for t in np.linspace(0, 2 * np.pi, 6, endpoint=False)]
    voxels, faces = {}, {}
    for name, radius in sizes.items():
        surfels = {"means": torch.as_tensor(pts, dtype=torch.float32),
                   "quats": torch.as_tensor(rotmat_to_quat(R), dtype=torch.float32),
                   "scales": torch.full((len(pts), 2), radius), "opacities": torch.full((len(pts),), 0.95),
                   "colors": torch.full((len(pts), 3), 0.5)}
        mesh = fuse_instance(surfels, views, depth_max=5.0)
        voxels[name], faces[name] = mesh.voxel_size, len(mesh.faces)
    diag = np.linalg.norm(np.ptp(pts, axis=0))
    assert voxels["tiny"] >= diag / MAX_VOXELS_PER_DIAGONAL - 1e-9
    # render-limited: 640 px across at ~1.2 m with f = 560 px -> ~2 mm pixels, voxel 1.5 px
    assert voxels["tiny"] > 2.5e-3, voxels
    assert voxels["coarse"] == pytest.approx(0.75 * 0.006, rel=1e-4)       # the surfel rule when coarser
    assert faces["tiny"] < 150_000, faces


def test_an_instance_with_no_surface_says_why():
    """Issue #17: "no surface fused for this instance" named no cause. A thing hidden inside
    another one wins no pixel: the report says so, with its surfel and pixel counts."""
    from psimap.camera import camera_rig, look_at
    from psimap.data.frames import ClassInfo
    from psimap.exporters.instance_meshes import instance_meshes
    from psimap.scene import scene_from_meshes

    big = trimesh.creation.box(extents=[0.4, 0.4, 0.4]).apply_translation([0, 0, 0.2])
    hidden = trimesh.creation.icosphere(2, radius=0.05).apply_translation([0, 0, 0.2])
    floor = trimesh.creation.box(extents=[2, 2, 0.02]).apply_translation([0, 0, -0.01])
    c2ws = [look_at(np.array([1.2 * np.cos(a), 1.2 * np.sin(a), 0.9]), np.array([0, 0, 0.2]))
            for a in np.linspace(0, 2 * np.pi, 4, endpoint=False)]
    classes = [ClassInfo(1, "floor", False), ClassInfo(2, "box", True), ClassInfo(3, "ball", True)]
    scene = scene_from_meshes([floor, big, hidden], [0, 5, 6], [1, 2, 3], classes, camera_rig(c2ws, 64, 48, 60.0))
    inst = instance_meshes(scene)
    by_id = {t.instance_id: t for t in inst.things}
    assert by_id[5].mesh is not None and len(by_id[5].mesh.faces) and by_id[5].why_empty == ""
    assert by_id[6].mesh is None and "hidden behind other labels" in by_id[6].why_empty
    import re

    m = re.match(r"its (\d+) surfels win at most (\d+) pixels", by_id[6].why_empty)
    assert m and int(m.group(1)) > 0 and int(m.group(2)) < 16


def test_an_instance_is_fused_from_at_most_max_fusion_views_evenly_spaced(monkeypatch):
    """A thing seen in every frame of a long capture is fused from MAX_FUSION_VIEWS of the views
    that see it (first to last, evenly spaced), not all of them; one seen in fewer keeps all."""
    import psimap.exporters.instance_meshes as im
    from psimap.camera import camera_rig, look_at
    from psimap.data.frames import ClassInfo
    from psimap.scene import scene_from_meshes

    box = trimesh.creation.box(extents=[0.3, 0.3, 0.3]).apply_translation([0, 0, 0.15])
    floor = trimesh.creation.box(extents=[2, 2, 0.02]).apply_translation([0, 0, -0.01])
    c2ws = [look_at(np.array([1.2 * np.cos(a), 1.2 * np.sin(a), 0.9]), np.array([0, 0, 0.15]))
            for a in np.linspace(0, 2 * np.pi, 7, endpoint=False)]
    classes = [ClassInfo(1, "floor", False), ClassInfo(2, "box", True)]
    scene = scene_from_meshes([floor, box], [0, 5], [1, 2], classes, camera_rig(c2ws, 48, 36, 60.0))
    fused = []
    real = im.fuse_instance

    def spy(surfels, views, **kw):
        fused.append([v.c2w for v in views])
        return real(surfels, views, **kw)
    monkeypatch.setattr(im, "fuse_instance", spy)
    monkeypatch.setattr(im, "MAX_FUSION_VIEWS", 3)
    inst = im.instance_meshes(scene)
    assert len(inst.views) == 7 and len(fused) == 1
    assert len(fused[0]) == 3 and all(np.allclose(a, c2ws[k]) for a, k in zip(fused[0], (0, 3, 6)))
    assert inst.things[0].mesh is not None and len(inst.things[0].mesh.faces)
    monkeypatch.setattr(im, "MAX_FUSION_VIEWS", 7)
    im.instance_meshes(scene)
    assert len(fused[1]) == 7


def test_a_resting_object_gets_no_cylinder_lying_on_its_side():
    """Issue #17: a reconstructed apple (a 3.5 cm ball cut flat where it rests, 6.4 cm tall)
    fits a lying cylinder within tolerance; its centre of mass off the axis, it rolled 10 cm in the
    settle check and was pinned. Resting, a lying cylinder is no candidate; upright ones still are."""
    ball = trimesh.creation.icosphere(4, radius=0.035).apply_translation([0, 0, 0.029])
    apple = trimesh.boolean.intersection([ball, trimesh.creation.box(extents=[0.2, 0.2, 0.2]).apply_translation(
        [0, 0, 0.1])], engine="manifold")
    lying = trimesh.creation.cylinder(radius=0.03, height=0.07, sections=48)
    lying.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    lying.apply_translation([0, 0, 0.03])
    standing = trimesh.creation.cylinder(radius=0.03, height=0.12, sections=48).apply_translation([0, 0, 0.06])
    tol = 0.012
    free = C.collision_geometry(lying, tol)
    assert free.kind == "cylinder" and abs(free.transform[2, 2]) < 0.2        # not resting: it is a cylinder
    for mesh in (apple, lying):
        c = C.collision_geometry(mesh, tol, resting=True)
        assert not (c.kind == "cylinder" and abs(c.transform[2, 2]) < C.UPRIGHT_COS), (c.kind, c.transform)
        assert c.error <= tol
    assert C.collision_geometry(standing, tol, resting=True).kind == "cylinder"


def test_flat_collider_parts_are_dropped():
    """A shelf part clipped flat at a board (coplanar vertices) made MuJoCo refuse the whole scene
    ("cannot compute convex hull") and `psimap demo` stop; slivers are no collider parts."""
    box = trimesh.creation.box(extents=[0.2, 0.1, 0.05]).apply_translation([0, 0, 0.025])
    assert C.clip_halfspace(box, np.array([0.0, 0.0, 1.0]), 0.05 - 2e-4) is None        # 0.2 mm left
    kept = C.clip_halfspace(box, np.array([0.0, 0.0, 1.0]), 0.04)
    assert kept is not None and kept.extents[2] == pytest.approx(0.01)
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 1e-5]], [[0, 1, 2], [1, 3, 2], [0, 2, 3], [0, 3, 1]])
    assert C.solid_parts([box, flat, None]) == [box]
