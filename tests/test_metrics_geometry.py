"""Geometry metrics on hand-built meshes with known answers."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from psimap import PsimapError
from psimap.metrics.geometry import (camera_rays, geometry_metrics, plot_geometry, sample_surface,
                                     surface_distances, visible_faces)


def quad(z: float, half: float = 0.5, cx: float = 0.0, cy: float = 0.0) -> trimesh.Trimesh:
    """An axis-aligned square at height z (normal +z), 2*half wide."""
    v = np.array([[cx - half, cy - half, z], [cx + half, cy - half, z],
                  [cx + half, cy + half, z], [cx - half, cy + half, z]])
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)


def camera(width=64, height=48, f=40.0, c2w=None):
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    return (K, np.eye(4) if c2w is None else c2w, width, height)


def test_identical_meshes_are_perfect():
    box = trimesh.creation.box((2.0, 1.0, 0.5)).subdivide()
    m = geometry_metrics(box, box)
    assert m["f1"] == 1.0 and m["precision"] == 1.0 and m["recall"] == 1.0
    assert m["chamfer_l1"] < 1e-3 and m["accuracy"] < 1e-5 and m["completeness"] < 1e-5


def test_plane_shifted_along_normal_gives_the_analytic_distance():
    gt = quad(0.0)
    pred = quad(0.02)
    at5 = geometry_metrics(pred, gt, threshold=0.05)
    assert at5["accuracy"] == pytest.approx(0.02, rel=0.01)
    assert at5["completeness"] == pytest.approx(0.02, rel=0.01)
    assert at5["chamfer_l1"] == pytest.approx(0.02, rel=0.01)
    assert at5["f1"] == 1.0
    at1 = geometry_metrics(pred, gt, threshold=0.01)
    assert at1["f1"] == 0.0 and at1["precision"] == 0.0 and at1["recall"] == 0.0


def test_shifted_box_matches_closed_form_and_sample_count_follows_the_budget():
    # 2 m cube shifted 2 cm up. Top/bottom (8 of 24 m^2) are 2 cm off; on the sides only the 2 cm
    # strip above the GT top is off, by a distance uniform in [0, 2 cm] (mean 1 cm).
    gt = trimesh.creation.box((2.0, 2.0, 2.0))
    pred = gt.copy()
    pred.apply_translation([0, 0, 0.02])
    m = geometry_metrics(pred, gt, threshold=0.01)
    expected_acc = (8 * 0.02 + 16 * 0.01 * 0.01) / 24
    assert m["accuracy"] == pytest.approx(expected_acc, rel=0.03)
    # Precision at 1 cm: sides except the upper half of the strip; p ~ 2/3 needs more samples than
    # the 10k start for a 0.25% standard error, so the adaptive count must have grown.
    expected_p = 16 * (1 - 0.005) / 24
    assert m["precision"] == pytest.approx(expected_p, abs=0.0075)
    assert m["n_pred_points"] > 10_000
    se = np.sqrt(m["precision"] * (1 - m["precision"]) / m["n_pred_points"])
    assert se <= 0.0025
    # A cap on the count is honoured.
    capped = geometry_metrics(pred, gt, threshold=0.01, max_samples=5000)
    assert capped["n_pred_points"] == 5000 and capped["n_gt_points"] == 5000


def test_same_seed_same_numbers_and_seed_changes_samples():
    gt = trimesh.creation.icosphere(2)
    pred = trimesh.creation.icosphere(1)
    a = geometry_metrics(pred, gt, seed=3)
    b = geometry_metrics(pred, gt, seed=3)
    c = geometry_metrics(pred, gt, seed=4)
    assert a == b
    assert a["accuracy"] != c["accuracy"]
    assert a["accuracy"] == pytest.approx(c["accuracy"], rel=0.05)


def test_visible_faces_respects_occlusion_frustum_and_range():
    front = quad(2.0)                 # in front of the camera, fills much of the view
    hidden = quad(3.0, half=0.3)      # right behind `front`: occluded
    behind = quad(-2.0)               # behind the camera
    aside = quad(2.0, cx=10.0)        # outside the frustum
    mesh = trimesh.util.concatenate([front, hidden, behind, aside])
    seen = visible_faces(mesh, [camera()])
    assert seen.tolist() == [True, True, False, False, False, False, False, False]
    assert not visible_faces(mesh, [camera()], max_depth=1.5).any()
    # OpenCV convention: a camera 2 m above the floor looking down (z forward = world -z).
    down = np.eye(4)
    down[:3, :3] = np.diag([1.0, -1.0, -1.0])
    down[:3, 3] = [0, 0, 2.0]
    floor_and_ceiling = trimesh.util.concatenate([quad(0.0), quad(4.0)])
    assert visible_faces(floor_and_ceiling, [camera(c2w=down)]).tolist() == [True, True, False, False]


def test_camera_rays_hit_at_z_depth():
    K, c2w, w, h = camera(8, 6)
    rays = camera_rays(K, c2w, w, h)
    assert rays.shape == (48, 6)
    # direction z component is 1: the ray parameter of a hit is its depth.
    np.testing.assert_allclose(rays[:, 5], 1.0)
    np.testing.assert_allclose(rays[0, 3:5], [(0.5 - 4) / 40, (0.5 - 3) / 40], rtol=1e-6)


def test_unseen_gt_surface_is_left_out_of_completeness_and_recall():
    front = quad(2.0)
    hidden = quad(3.0, half=0.3)
    gt = trimesh.util.concatenate([front, hidden])
    pred = front  # a reconstruction that got exactly what the camera saw
    culled = geometry_metrics(pred, gt, cameras=[camera()])
    assert culled["completeness"] < 1e-5 and culled["recall"] == 1.0 and culled["f1"] == 1.0
    assert culled["gt_seen_fraction"] == pytest.approx(1.0 / 1.36, rel=1e-6)
    unculled = geometry_metrics(pred, gt)
    # 0.36 / 1.36 of GT area lies 1 m away from the prediction.
    assert unculled["completeness"] == pytest.approx(0.36 / 1.36 * 1.0, rel=0.05)
    assert unculled["recall"] == pytest.approx(1.0 / 1.36, abs=0.01)
    # Accuracy and precision use the whole GT mesh either way.
    assert culled["accuracy"] == unculled["accuracy"] == pytest.approx(0.0, abs=1e-5)


def test_partly_seen_faces_are_culled_point_by_point():
    # One 6 x 6 m quad (2 faces, both hit) of which the camera sees only a 3.2 x 2.4 m window, and
    # a 0.8 m occluder at half the distance hiding a 1.6 m square of that window.
    K, c2w, w, h = camera()           # f 40 px, 64 x 48: at z = 2 the view is 3.2 x 2.4 m
    window = quad(2.0, half=1.0)
    window.vertices[:, 0] *= 1.6
    window.vertices[:, 1] *= 1.2
    big = quad(2.0, half=3.0)
    assert visible_faces(big, [camera()]).all()
    m = geometry_metrics(window, big, cameras=[camera()])
    # A reconstruction of exactly the seen window is complete, though both GT faces are "hit".
    assert m["completeness"] < 1e-4 and m["recall"] == 1.0
    assert m["gt_seen_fraction"] == pytest.approx(7.68 / 36, rel=0.03)
    occluded = trimesh.util.concatenate([big, quad(1.0, half=0.4)])
    m = geometry_metrics(window, occluded, cameras=[camera()])
    seen_far, seen_occ = 7.68 - 1.6 ** 2, 0.64
    assert m["gt_seen_fraction"] == pytest.approx((seen_far + seen_occ) / 36.64, rel=0.03)
    # The occluder (1 m from the window) is the only seen GT surface the prediction lacks.
    assert m["completeness"] == pytest.approx(seen_occ / (seen_far + seen_occ) * 1.0, rel=0.05)
    assert m["recall"] == pytest.approx(seen_far / (seen_far + seen_occ), abs=0.01)


def test_degenerate_inputs():
    gt = quad(0.0)
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int), process=False)
    with pytest.raises(PsimapError, match="no faces"):
        geometry_metrics(empty, gt)
    nan = quad(0.0)
    nan.vertices[0, 0] = np.nan
    with pytest.raises(PsimapError, match="not finite"):
        geometry_metrics(nan, gt)
    flat = trimesh.Trimesh(np.zeros((3, 3)), [[0, 1, 2]], process=False)
    with pytest.raises(PsimapError, match="zero area"):
        geometry_metrics(flat, gt)
    with pytest.raises(PsimapError, match="seen by any camera"):
        # 5 m below the quad, looking further down: sees nothing
        geometry_metrics(gt, gt, cameras=[camera(c2w=_translate(0, 0, -5) @ _flip())])
    with pytest.raises(PsimapError, match="not finite"):
        visible_faces(gt, [(np.full((3, 3), np.nan), np.eye(4), 8, 6)])
    with pytest.raises(PsimapError, match="threshold"):
        geometry_metrics(gt, gt, threshold=0.0)
    # Zero-area (degenerate) triangles mixed into a valid mesh change nothing.
    v = np.vstack([quad(0.02).vertices, [[5, 5, 5]]])
    f = np.vstack([quad(0.02).faces, [[4, 4, 4], [0, 0, 1]]])
    with_degenerate = trimesh.Trimesh(v, f, process=False)
    a = geometry_metrics(with_degenerate, gt)
    b = geometry_metrics(quad(0.02), gt)
    assert a["accuracy"] == pytest.approx(b["accuracy"], rel=1e-6)
    assert a["completeness"] == pytest.approx(0.02, rel=0.01)


def _translate(x, y, z):
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


def _flip():
    # camera looking along world -z
    return np.diag([1.0, -1.0, -1.0, 1.0])


def test_sampling_is_area_weighted():
    big, small = quad(0.0, half=1.0), quad(5.0, half=0.5)
    mesh = trimesh.util.concatenate([big, small])
    pts = sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.faces), 40_000, np.random.default_rng(0))
    assert (pts[:, 2] > 1).mean() == pytest.approx(1 / 5, abs=0.01)
    # Uniform inside a face: x of the big square is uniform in [-1, 1].
    xb = pts[pts[:, 2] < 1, 0]
    assert xb.mean() == pytest.approx(0.0, abs=0.02) and xb.var() == pytest.approx(1 / 3, rel=0.03)


def plotted_figures(monkeypatch) -> list:
    """Figures handed to plt.close (what a plot function drew), kept for inspection."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figs, real = [], plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: figs.append(fig) or real(fig))
    return figs


def test_plot_geometry_draws_the_metrics_curves(tmp_path, monkeypatch):
    from PIL import Image

    from psimap.metrics.geometry import summarize

    # a prediction covering a quarter of the GT square, 2 cm above it: precision 1, recall ~0.28
    d = surface_distances(quad(0.02, half=0.5), quad(0.0, half=1.0), max_samples=4000)
    m = summarize(d, 0.05)
    assert m["precision"] == 1.0 and 0.2 < m["recall"] < 0.35
    figs = plotted_figures(monkeypatch)
    out = tmp_path / "geom.png"
    plot_geometry(d, out, 0.05)
    img = np.asarray(Image.open(out).convert("RGB"))
    assert img.shape == (400, 1000, 3) and img.std() > 20            # 10 x 4 in at 100 dpi, not blank
    (fig,) = figs
    curves = {ln.get_label(): ln for ln in fig.axes[0].get_lines() if not ln.get_label().startswith("_")}
    assert sorted(curves) == ["F1", "precision", "recall"]
    for key, name in (("precision", "precision"), ("recall", "recall"), ("f1", "F1")):
        x, y = curves[name].get_data()                                # x in cm
        assert np.interp(5.0, x, y) == pytest.approx(m[key], abs=0.02), name
        assert np.all(np.diff(y) >= -1e-12) or name == "F1"          # P and R grow with the threshold
    # the histograms count every sample once (values beyond the axis go to the last bin)
    bars = fig.axes[1].patches
    assert sum(b.get_height() for b in bars) == len(d.pred_to_gt) + len(d.gt_to_pred)
