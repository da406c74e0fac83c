"""Geometry work proportional to the scene (issue #20): surfel spacing from each point's viewing
distance (far walls coarse, near things fine), large planar stuff coarser, a total cap, and geometry
steps that end at a loss plateau."""

import numpy as np
import pytest

from psimap.data import load
from psimap.train.config import TrainConfig
from psimap.train.trainer import Plateau, init_from_prior, prepare_frames, target_spacing
from scripts import load_script

B = load_script("benchmarks/budget.py", "bench_budget")

BEFORE = B.BEFORE


@pytest.fixture(scope="module")
def far_wall(tmp_path_factory):
    """benchmarks/budget.py's far-wall capture, small: a table filmed from 0.5-0.8 m, walls 2.5-4 m away."""
    return B.far_wall_capture(tmp_path_factory.mktemp("far") / "scene", 0, frames=8, width=160, height=120,
                              n_objects=3)


def _init(data, **kw):
    """The prior's surfels with TrainConfig's defaults (spacing by viewing distance) and kw."""
    seq = load(data)
    cfg = TrainConfig(**kw)
    fr, _, _, _ = prepare_frames(seq, cfg, log=lambda m: None)
    spacing = target_spacing(fr, cfg.spacing_pixels)
    logs = []
    params, index, info = init_from_prior(fr, cfg, spacing, list(seq.classes), log=logs.append)
    return params, info, fr, logs


def _on_things(means, data):
    """[N] bool: surfels within 2 cm of a GT thing surface (gt/mesh.ply instance > 0)."""
    from surfels import gt_surface_labels

    from psimap.metrics.geometry import raycasting_scene
    import open3d as o3d

    mesh, inst, _, _ = gt_surface_labels(data)
    rs = raycasting_scene(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    hit = rs.compute_closest_points(o3d.core.Tensor(np.asarray(means, np.float32)))
    d = np.linalg.norm(hit["points"].numpy() - means, axis=1)
    return (d < 0.02) & (inst[hit["primitive_ids"].numpy().astype(np.int64)] > 0)


def test_far_walls_get_coarse_surfels_and_things_keep_theirs(far_wall):
    old, info_old, fr, _ = _init(far_wall, **BEFORE)
    new, info_new, _, logs = _init(far_wall)
    m_old, m_new = old["means"].detach().numpy(), new["means"].detach().numpy()
    # the median depth is the table's, so the old rule spaced the far walls like the table
    assert info_new["n_init"] < 0.3 * info_old["n_init"], (info_old["n_init"], info_new["n_init"])
    t_old, t_new = _on_things(m_old, far_wall).sum(), _on_things(m_new, far_wall).sum()
    assert t_new >= t_old, (t_old, t_new)                   # things keep (at least) their surfels
    # things take thing_spacing_pixels (2.5 px), not the scene's 3 px: (3 / 2.5)^2 = 1.44x the surfels
    coarse, _, _, _ = _init(far_wall, thing_spacing_pixels=3.0)
    t_coarse = _on_things(coarse["means"].detach().numpy(), far_wall).sum()
    assert t_new > 1.25 * t_coarse, (t_coarse, t_new)
    # a surfel's size follows its distance: 2.5 m from every camera it is > 2x the old rule's
    cams = np.stack([f.c2w[:3, 3] for f in fr])
    far = lambda m: np.linalg.norm(m[:, None] - cams[None], axis=2).min(1) > 2.5  # noqa: E731
    s_old = np.exp(old["log_scales"].detach().numpy()).max(1)[far(m_old)]
    s_new = np.exp(new["log_scales"].detach().numpy()).max(1)[far(m_new)]
    assert np.median(s_new) > 2.0 * np.median(s_old), (np.median(s_old), np.median(s_new))
    assert info_new["planar_area"] > 0 and any("large planar stuff" in m for m in logs)
    # the large planar stuff (walls, floor) is spaced coarser: without that factor more surfels
    _, info_flat, _, _ = _init(far_wall, stuff_spacing_factor=1.0)
    assert info_flat["n_init"] > info_new["n_init"], (info_flat["n_init"], info_new["n_init"])


def test_the_surfel_cap_holds_and_is_logged(far_wall):
    _, info, _, logs = _init(far_wall, max_surfels=1500)
    assert info["n_init"] <= 1500 / TrainConfig().budget_factor + 1
    assert info["n_needed"] > info["n_init"] and info["spacing_scale"] > 1.0
    assert any(m.startswith("surfel cap:") for m in logs)


def test_footprint_is_the_mean_of_each_components_points():
    from psimap.geometry.sogmm import fit_sogmm

    rng = np.random.default_rng(0)
    # two 1 m squares, one seen from 1 m (footprint 0.004), one from 3 m (0.012)
    a = np.c_[rng.random((4000, 2)), np.zeros(4000)]
    b = np.c_[rng.random((4000, 2)) + [3.0, 0.0], np.zeros(4000)]
    pts = np.concatenate([a, b])
    fp = np.r_[np.full(4000, 0.004), np.full(4000, 0.012)]
    g = fit_sogmm(pts, voxel=0.02, footprint=fp)
    near = g.means[:, 0] < 2.0
    assert np.allclose(g.footprint[near], 0.004) and np.allclose(g.footprint[~near], 0.012)
    plain = fit_sogmm(pts, voxel=0.02)
    assert plain.footprint is None and np.array_equal(plain.means, g.means)


def test_plateau_pairs_windows_by_frame():
    rng = np.random.default_rng(0)
    level = np.array([0.05, 0.06, 0.5, 0.6])   # two frames with little loss and two with much

    def feed(p, gain_per_window, windows, share_high):
        for w in range(windows):
            for _ in range(p.window):
                f = 2 * int(rng.random() < share_high[w]) + int(rng.integers(2))
                p.add(f, level[f] * (1 - gain_per_window) ** w)

    # every frame's loss flat, but the second window drew mostly the low-loss frame: a plain mean
    # would read a 60 % gain; paired by frame it is none
    p = Plateau(50, 0.02)
    feed(p, 0.0, 2, [0.7, 0.1])
    assert p.stalled(100) and abs(p.gain) < 1e-9
    # 10 % better per window on every frame: not a plateau, whatever frames were drawn
    p = Plateau(50, 0.02)
    feed(p, 0.10, 2, [0.1, 0.7])
    assert not p.stalled(100) and p.gain == pytest.approx(0.10, abs=1e-9)
    # only at whole windows, two at least after the schedule settled; window 0 never stops
    assert not p.stalled(99) and not p.stalled(50)
    assert not Plateau(0, 0.02).stalled(100)


def _mesh_f1(scene, gt_mesh):
    from psimap.metrics.geometry import geometry_metrics

    return geometry_metrics(scene.mesh(), gt_mesh, threshold=0.05, max_samples=20_000, seed=0)["f1"]


def test_geometry_steps_stop_at_a_plateau_on_an_easy_scene_only(far_wall):
    from test_train import cfg, sequence, tiny_scene

    from psimap.train.trainer import train

    frames, gt_mesh = tiny_scene()
    run = dict(iters=300, densify_every=50, densify_from=0.1, densify_until=0.7, plateau_window=25, plateau_tol=0.03)
    # easy: 8 noise-free views of a box on a floor, fitted within ~150 steps
    easy = train(sequence(frames), cfg(**run), log=lambda m: None)
    m = easy.metrics
    assert m["geometry_stop"] == "plateau" and m["geometry_steps"] < 250, m["plateau_checks"]
    assert m["steps"] == m["geometry_steps"] and m["plateau_gain"] < 0.03
    assert m["history"][-1]["step"] == m["geometry_steps"]      # it stopped there
    # the density schedule ran before the stop: at least one round, and it settled
    assert m["densify"] and m["density_settled"] <= m["geometry_steps"] - 2 * 25
    full = train(sequence(frames), cfg(**{**run, "plateau_window": 0}), log=lambda m: None)
    assert full.metrics["geometry_stop"] == "cap" and full.metrics["steps"] == 300
    f_easy, f_full = _mesh_f1(easy, gt_mesh), _mesh_f1(full, gt_mesh)
    assert f_easy > f_full - 0.02 and f_full > 0.9, (f_easy, f_full)
    # hard: the far-wall capture (noisy depth, textured walls, things): at 250 steps its loss still
    # falls more than 3 % per window, and every step runs
    hard = train(str(far_wall), cfg(**{**run, "iters": 250}, panoptic=False), log=lambda m: None)
    assert hard.metrics["geometry_stop"] == "cap" and hard.metrics["steps"] == 250, hard.metrics["plateau_checks"]
    # it was checked, and kept going (how many windows remain after density control settles moves
    # with the renderer's rounding: 3 on the torch projection, 2 on the native one)
    assert len(hard.metrics["plateau_checks"]) >= 1
    assert all(g >= 0.03 for _, g in hard.metrics["plateau_checks"]), hard.metrics["plateau_checks"]
