"""Training: loss and depth error decrease, no NaN, determinism, resume, skipped frames, NaN guard,
density control, losses, and the `psimap train` / `psimap mesh` commands on a tiny scene."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from psimap import PsimapError
from psimap.camera import look_at
from psimap.data.frames import ClassInfo, Frame, FrameSequence
from psimap.nonfinite import Diverged
from psimap.train import losses as L
from psimap.train.config import TrainConfig
from psimap.train.trainer import train

W, H = 64, 48
K = np.array([[52.0, 0, 31.5], [0, 52.0, 23.5], [0, 0, 1]])


def tiny_scene(n_frames=8):
    """Floor (2 x 2 m) with a 0.4 m box, checker-textured, seen from a ring of cameras."""
    import open3d as o3d
    import trimesh

    floor = trimesh.creation.box((2.0, 2.0, 0.02))
    floor.apply_translation((0, 0, -0.01))
    box = trimesh.creation.box((0.4, 0.4, 0.4))
    box.apply_translation((0.1, 0, 0.2))
    mesh = trimesh.util.concatenate([floor, box])
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                     o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], -1).reshape(-1, 3)
    frames = []
    for i, a in enumerate(np.linspace(0, 2 * np.pi, n_frames, endpoint=False)):
        c2w = look_at(np.array([1.6 * np.cos(a), 1.6 * np.sin(a), 1.1]), (0, 0, 0.15))
        dirs = d @ c2w[:3, :3].T
        rays = np.concatenate([np.repeat(c2w[None, :3, 3], len(dirs), 0), dirs], 1).astype(np.float32)
        t = rc.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        ok = np.isfinite(t)
        p = c2w[:3, 3] + np.where(ok, t, 0)[:, None] * dirs
        checker = ((np.floor(p[:, 0] / 0.25) + np.floor(p[:, 1] / 0.25) + np.floor(p[:, 2] / 0.25)) % 2)
        rgb = np.stack([0.2 + 0.6 * checker, 0.5 + 0.2 * (p[:, 2] > 0.01), 0.7 - 0.5 * checker], 1)
        rgb = np.where(ok[:, None], rgb, 0.0).reshape(H, W, 3).astype(np.float32)
        depth = np.where(ok, t * (dirs @ c2w[:3, 2]), 0).reshape(H, W).astype(np.float32)
        frames.append(Frame(rgb=rgb, depth=depth, K=K.copy(), c2w=c2w, name=f"f{i:03d}"))
    return frames, mesh


def sequence(frames):
    return FrameSequence(loader=lambda i: frames[i], count=len(frames),
                         classes=[ClassInfo(1, "floor", False), ClassInfo(2, "box", True)])


def cfg(**kw):
    base = dict(iters=60, log_every=10, densify_every=20, densify_from=0.2, densify_until=0.8)
    base.update(kw)
    return TrainConfig(**base)


@pytest.fixture(scope="module")
def scene_frames():
    return tiny_scene()


@pytest.fixture(scope="module")
def trained(scene_frames):
    frames, _ = scene_frames
    return train(sequence(frames), cfg(), log=lambda m: None)


def test_loss_and_depth_error_decrease(trained):
    m = trained.metrics
    assert m["loss_end"]["total"] < 0.8 * m["loss_start"]["total"], (m["loss_start"], m["loss_end"])
    assert m["loss_end"]["rgb"] < m["loss_start"]["rgb"]
    assert m["depth_l1_end"] < m["depth_l1_start"], (m["depth_l1_start"], m["depth_l1_end"])
    assert m["depth_l1_end"] < 0.02                          # 2 cm on exact depth
    for k, t in trained.surfels.items():
        if t.is_floating_point():
            assert torch.isfinite(t).all(), k
    assert bool((trained.surfels["scales"] > 0).all())
    assert m["sogmm_K"] > 0 and 0 < m["surfels"] <= m["budget"]
    assert trained.cameras["names"] == [f"f{i:03d}" for i in range(8)]


def test_deterministic_for_a_seed(scene_frames):
    frames, _ = scene_frames
    a = train(sequence(frames), cfg(iters=25), log=lambda m: None)
    b = train(sequence(frames), cfg(iters=25), log=lambda m: None)
    for k in ("means", "quats", "scales", "opacities", "colors"):
        assert torch.equal(a.surfels[k], b.surfels[k]), k
    c = train(sequence(frames), cfg(iters=25, seed=1), log=lambda m: None)
    assert len(c) != len(a) or not torch.equal(a.surfels["means"], c.surfels["means"])


def test_renderer_uses_the_cores_and_gives_them_back(scene_frames):
    """Training renders on every core this process may use (or cfg.threads), the same bits as one
    thread, and leaves the caller's native thread count as it was."""
    from psimap.render import native
    from psimap.train.trainer import available_cores

    frames, _ = scene_frames
    seen = []
    native.set_num_threads(1)
    a = train(sequence(frames), cfg(iters=12), log=lambda m: None,
              callback=lambda step, params, t: seen.append(native.get_num_threads()))
    assert set(seen) == {available_cores()}
    assert native.get_num_threads() == 1
    b = train(sequence(frames), cfg(iters=12, threads=3), log=lambda m: None,
              callback=lambda step, params, t: seen.append(native.get_num_threads()))
    assert seen[-1] == 3
    assert _surfel_digest(a) == _surfel_digest(b)


def _surfel_digest(scene) -> str:
    import hashlib

    h = hashlib.sha1()
    for k in ("means", "quats", "scales", "opacities", "colors"):
        h.update(scene.surfels[k].numpy().tobytes())
    return h.hexdigest()


_DIGEST_IN_SUBPROCESS = """
import sys, torch
sys.path.insert(0, {tests!r})
torch.set_num_threads(2)                     # the trainer must not depend on the caller's threads
import test_train as T
from psimap.train.trainer import train
frames, _ = T.tiny_scene()
print("DIGEST", T._surfel_digest(train(T.sequence(frames), T.cfg(iters=40), log=lambda m: None)))
"""


def test_deterministic_across_processes_and_thread_settings(scene_frames):
    """Same seed, bit-identical surfels in a fresh process whose torch / OpenMP / BLAS thread
    counts differ (40 steps, one density-control round in between)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    frames, _ = scene_frames
    here = _surfel_digest(train(sequence(frames), cfg(iters=40), log=lambda m: None))
    env = dict(os.environ, OMP_NUM_THREADS="2", OPENBLAS_NUM_THREADS="2", MKL_NUM_THREADS="2")
    code = _DIGEST_IN_SUBPROCESS.format(tests=str(Path(__file__).resolve().parent))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    there = [ln.split()[1] for ln in out.stdout.splitlines() if ln.startswith("DIGEST")]
    assert there == [here]


def test_resume_continues(trained, scene_frames, tmp_path):
    frames, _ = scene_frames
    ckpt = tmp_path / "scene.ckpt"
    trained.save(ckpt)
    # full resolution from the first step: the comparison below is on the frames trained last
    resumed = train(sequence(frames), cfg(iters=20, lowres_until=0.0), resume=ckpt, log=lambda m: None)
    assert resumed.metrics["steps"] == trained.metrics["steps"] + 20
    # starts where the first run ended, far below a fresh start
    assert resumed.metrics["depth_l1_start"] == pytest.approx(trained.metrics["depth_l1_end"], rel=1e-4)
    # (the same first step from a fresh start: same seed, so the same frame at the same resolution)
    fresh = train(sequence(frames), cfg(iters=20, lowres_until=0.0), log=lambda m: None)
    assert resumed.metrics["loss_start"]["total"] < 0.8 * fresh.metrics["loss_start"]["total"]


def test_frames_without_depth_are_skipped(scene_frames):
    frames, _ = scene_frames
    frames = list(frames)
    bad = Frame(rgb=frames[0].rgb, depth=np.zeros((H, W), np.float32), K=K, c2w=frames[0].c2w,
                name="nodepth")
    s = train(sequence(frames[:4] + [bad] + frames[4:]), cfg(iters=10), log=lambda m: None)
    assert s.metrics["skipped_frames"] == ["nodepth"]
    assert "nodepth" not in s.cameras["names"] and len(s.cameras["names"]) == 8
    with pytest.raises(PsimapError, match="no frame has valid depth"):
        train(sequence([bad, bad]), cfg(iters=5), log=lambda m: None)


def test_nan_guard(scene_frames, monkeypatch):
    frames, _ = scene_frames
    real = L.rgb_loss
    calls = {"n": 0}

    def flaky(*a, **k):                  # NaN on the first 3 steps, then fine
        calls["n"] += 1
        v = real(*a, **k)
        return v * float("nan") if calls["n"] <= 3 else v

    monkeypatch.setattr(L, "rgb_loss", flaky)
    s = train(sequence(frames), cfg(iters=12), log=lambda m: None)
    assert s.metrics["skipped_steps"] == 3
    assert all(torch.isfinite(t).all() for t in s.surfels.values() if t.is_floating_point())

    monkeypatch.setattr(L, "rgb_loss", lambda *a, **k: real(*a, **k) * float("nan"))
    with pytest.raises(Diverged, match="'rgb'"):
        train(sequence(frames), cfg(iters=30), log=lambda m: None)


def test_density_control_clone_split_prune_budget():
    from psimap.train.density import GradStats, densify_and_prune
    from psimap.train.trainer import PARAM_NAMES, make_optimizer, make_params

    n = 6
    means = np.zeros((n, 3)); means[:, 0] = np.arange(n)
    scales = np.full((n, 2), 0.01); scales[1] = 0.2           # surfel 1 is large
    opac = np.full(n, 0.8); opac[2] = 0.01                    # surfel 2 is transparent
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    params = make_params(means, q, scales, opac, np.full((n, 3), 0.5))
    opt, _ = make_optimizer(params, TrainConfig(), 1.0)
    sum((p**2).sum() for p in params.values()).backward()
    opt.step()
    parent_scale = params["log_scales"].exp()[1].detach().clone()
    stats = GradStats(torch.tensor([1.0, 1.0, 1.0, 0.0, 1.0, 0.0]), torch.ones(n))
    g = torch.Generator().manual_seed(0)
    r = densify_and_prune(params, opt, stats, grad_threshold=0.5, large_scale=0.05, prune_opacity=0.05,
                          max_scale=10.0, budget=100, generator=g)
    assert r == {"cloned": 2, "split": 1, "pruned": 1, "surfels": 6 - 1 - 1 + 2 + 2}
    for group in opt.param_groups:                            # optimiser follows the new tensors
        p = group["params"][0]
        assert p is params[group["name"]] and opt.state[p]["exp_avg"].shape == p.shape
    # split children sit in the parent's tangent plane (z = 0) with scales / 1.6
    kids = params["log_scales"].exp()[-2:]
    assert torch.allclose(kids, (parent_scale / 1.6).expand(2, 2))
    assert torch.allclose(params["means"][-2:, 2], torch.zeros(2), atol=1e-6)
    # budget: growth stops, and above it the least opaque go
    stats = GradStats(torch.ones(r["surfels"]), torch.ones(r["surfels"]))
    r2 = densify_and_prune(params, opt, stats, grad_threshold=0.5, large_scale=0.05, prune_opacity=0.0,
                           max_scale=10.0, budget=5, generator=g)
    assert r2["surfels"] == 5 and params["means"].shape[0] == 5 and r2["cloned"] == 0
    assert set(PARAM_NAMES) == set(params)


def test_geo_weight_schedule(scene_frames):
    """L_geo's weight is lambda_geo x geo_scale: half at 0.5, gone at 0 (the default schedule ends
    there, so the depth has the last word on fine geometry)."""
    from psimap.train.trainer import init_from_prior, loss_terms, prepare_frames, target_spacing

    frames, _ = scene_frames
    c = cfg()
    tf, _, _, _ = prepare_frames(sequence(frames), c, log=lambda m: None)
    spacing = target_spacing(tf, c.spacing_pixels)
    params, index, _ = init_from_prior(tf, c, spacing, log=lambda m: None)
    with torch.no_grad():                      # move surfels off the prior so L_geo is not ~0
        params["means"] += 0.01 * torch.randn(params["means"].shape, generator=torch.Generator().manual_seed(0))
    full = loss_terms(params, tf[0], c, index, spacing, False, geo_scale=1.0)[0]["geo"]
    half = loss_terms(params, tf[0], c, index, spacing, False, geo_scale=0.5)[0]["geo"]
    assert full.item() > 1e-3 and half.item() == pytest.approx(0.5 * full.item(), rel=1e-6)
    assert "geo" not in loss_terms(params, tf[0], c, index, spacing, False, geo_scale=0.0)[0]
    assert TrainConfig().geo_final == 0.0


def _ssim_written_out(a, b, window=11, sigma=1.5):
    """SSIM as Wang et al. write it: each local mean one 2D convolution with the 11x11 Gaussian."""
    import torch.nn.functional as F

    C = a.shape[-1]
    x, y = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
    r = torch.arange(window, dtype=a.dtype) - (window - 1) / 2
    g = torch.exp(-r**2 / (2 * sigma**2))
    w = (g[:, None] * g[None, :] / g.sum() ** 2).expand(C, 1, window, window)

    def blur(t):
        return F.conv2d(F.pad(t, (window // 2,) * 4, mode="replicate"), w, groups=C)

    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    return (((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))).mean()


@pytest.mark.parametrize("shape", [(20, 24, 3), (37, 16, 1)])
def test_separable_ssim_is_the_written_out_one(shape):
    """ssim (two 1D passes, the five means in two calls) gives the 2D-window SSIM's value and
    gradient in the prediction, on images that are neither square nor alike."""
    g = torch.Generator().manual_seed(1)
    target = torch.rand(*shape, generator=g)
    pred = (0.6 * target + 0.4 * torch.rand(*shape, generator=g)).requires_grad_(True)
    fast = L.ssim(pred, target)
    (v_fast,) = torch.autograd.grad(fast, pred)
    ref = _ssim_written_out(pred, target)
    (v_ref,) = torch.autograd.grad(ref, pred)
    assert 0.2 < float(ref.detach()) < 0.95
    assert float(fast.detach()) == pytest.approx(float(ref.detach()), rel=1e-5)
    torch.testing.assert_close(v_fast, v_ref, rtol=1e-4, atol=1e-7)


def test_losses():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(20, 24, 3, generator=g)
    assert float(L.ssim(a, a)) == pytest.approx(1.0, abs=1e-6)
    assert float(L.ssim(a, torch.rand(20, 24, 3, generator=g))) < 0.3
    assert float(L.rgb_loss(a, a)) == pytest.approx(0.0, abs=1e-6)
    # tilted plane z = 2 + 0.5 x (camera frame): normal from depth is the plane normal, facing camera
    Kt = torch.tensor(K, dtype=torch.float32)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32),
                            indexing="ij")
    rx = (xs - Kt[0, 2]) / Kt[0, 0]
    depth = 2.0 / (1 - 0.5 * rx)                             # z = 2 + 0.5 x with x = rx z
    n = L.depth_to_normal(depth, Kt)
    expect = torch.tensor([0.5, 0.0, -1.0]) / np.sqrt(1.25)
    inner = n[2:-2, 2:-2].reshape(-1, 3)
    assert torch.allclose(inner, expect.expand_as(inner), atol=1e-4)
    assert float(n[0].abs().sum()) == 0.0                    # borders excluded
    alpha = torch.ones(H, W)
    assert float(L.normal_consistency(n * 0.7, alpha, depth, Kt)) < 1e-4
    assert float(L.normal_consistency(-n, alpha, depth, Kt)) == pytest.approx(2.0, abs=1e-3)
    assert float(L.iso_loss(torch.tensor([[0.02, 0.01]]), 0.01)) == pytest.approx(1.0)
    v = torch.ones(3, 3, dtype=torch.bool)
    assert float(L.depth_l1(torch.zeros(3, 3), torch.ones(3, 3), v & False)) == 0.0


def test_cli_train_mesh_and_errors(scene_frames, tmp_path, capsys):
    import trimesh

    from psimap.cli import main
    from psimap.data.scene_format import write_scene

    frames, mesh = scene_frames
    data = write_scene(tmp_path / "data", frames, [ClassInfo(1, "floor", False)])
    ckpt = tmp_path / "scene.ckpt"
    assert main(["train", str(data), "--out", str(ckpt), "--iters", "40"]) == 0
    out = tmp_path / "mesh.ply"
    assert main(["mesh", str(ckpt), "--out", str(out)]) == 0
    m = trimesh.load(out)
    assert len(m.faces) > 100 and m.visual.vertex_colors is not None
    # the mesh lies on the true surface (quantised mm depth, 40 steps): median distance < 2 cm
    from scipy.spatial import cKDTree

    truth = trimesh.sample.sample_surface(mesh, 20000, seed=0)[0]
    d = cKDTree(truth).query(m.vertices)[0]
    assert np.median(d) < 0.02, np.median(d)
    capsys.readouterr()
    assert main(["train", str(tmp_path / "missing"), "--out", str(tmp_path / "x.ckpt")]) == 1
    assert capsys.readouterr().err.strip() == f"psimap train: error: no such data folder: {tmp_path / 'missing'}"
    (tmp_path / "bad.ckpt").write_bytes(ckpt.read_bytes()[:1000])
    assert main(["mesh", str(tmp_path / "bad.ckpt"), "--out", str(tmp_path / "y.ply")]) == 1
    # a clean error naming the file, not a crash ("internal error: RuntimeError: PytorchStreamReader...")
    err = capsys.readouterr().err.strip()
    assert err.startswith("psimap mesh: error: ") and len(err.splitlines()) == 1, err
    assert "internal error" not in err and f"{tmp_path / 'bad.ckpt'}: truncated or corrupt checkpoint" in err
    assert not (tmp_path / "x.ckpt").exists() and not (tmp_path / "y.ply").exists()


def _plane_grid(step=0.08, half=0.8):
    """Surfels on the z = 0 plane (grid `step`), checker colours: means [N,3], quats, colours."""
    g = np.arange(-half, half + 1e-9, step)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    means = np.concatenate([xy, np.zeros((len(xy), 1))], 1)
    checker = ((np.floor(xy[:, 0] / 0.24) + np.floor(xy[:, 1] / 0.24)) % 2)[:, None] > 0
    colors = np.where(checker, [0.8, 0.3, 0.2], [0.2, 0.4, 0.9])
    return means, np.tile([1.0, 0, 0, 0], (len(xy), 1)), colors


def test_accumulate_is_in_ndc_units():
    """One surfel 2 m in front of the camera, world gradient 1e-3 along camera x: the screen-space
    gradient is 1e-3 * z / fx pixels^-1 * W / 2 = 1e-3 * 2 / 52 * 32 in NDC (3DGS units)."""
    from psimap.train.density import GradStats, accumulate

    viewmat = torch.eye(4)
    Kt = torch.tensor(K, dtype=torch.float32)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.0], [0.0, 0.0, -1.0]])
    grad = torch.tensor([[1e-3, 0.0, 0.0], [0.0, 1e-3, 5.0], [1e-3, 0.0, 0.0]])
    st = GradStats.zeros(3)
    accumulate(st, grad, means, viewmat, Kt, W, H)
    accumulate(st, torch.zeros(3, 3), means, viewmat, Kt, W, H)    # unseen view: not counted
    g = st.mean()
    assert float(g[0]) == pytest.approx(1e-3 * 2 / 52 * W / 2, rel=1e-5)
    assert float(g[1]) == pytest.approx(1e-3 * 2 / 52 * H / 2, rel=1e-5)   # depth gradient ignored
    assert float(g[2]) == 0.0 and float(st.count[2]) == 0.0                # behind the camera
    assert st.count.tolist()[:2] == [1.0, 1.0]


def test_density_control_densifies_where_the_map_is_missing():
    """A plane with a hole in its surfels, supervised by renders of the full plane: the default
    threshold (NDC units) clones the surfels around the hole and leaves the fitted ones alone.
    In pixel units the same threshold cloned only a few (it was W / 2 = 32 times stricter)."""
    from psimap.camera import look_at
    from psimap.train.density import GradStats, accumulate, densify_and_prune
    from psimap.train.trainer import loss_terms, make_optimizer, make_params, render, to_train_frame

    means, q, colors = _plane_grid()
    n = len(means)
    full = make_params(means, q, np.full((n, 2), 0.05), np.full(n, 0.9), colors)
    centre = np.array([0.3, 0.2])
    keep = np.linalg.norm(means[:, :2] - centre, axis=1) >= 0.2
    views = []
    for eye in ([0, 0, 2.0], [0.3, -0.2, 1.9], [-0.2, 0.3, 2.1]):
        c2w = look_at(np.array(eye), (0.0, 0.0, 0.0))
        blank = to_train_frame("v", np.zeros((H, W, 3)), np.zeros((H, W)), K, c2w)
        with torch.no_grad():
            out = render(full, blank)
        views.append(to_train_frame("v", out.rgb.numpy(), np.where(out.alpha.numpy() > 0.5,
                                                                  out.depth.numpy(), 0), K, c2w))
    cfg_ = TrainConfig(use_prior=False)
    m = int(keep.sum())
    params = make_params(means[keep], q[keep], np.full((m, 2), 0.05), np.full(m, 0.9), colors[keep])
    opt, _ = make_optimizer(params, cfg_, 1.0)
    stats = GradStats.zeros(m)
    for fr in views:
        terms, _ = loss_terms(params, fr, cfg_, None, 0.08, False)
        sum(terms.values()).backward()
        accumulate(stats, params["means"].grad, params["means"].detach(), fr.viewmat, fr.K, W, H)
        opt.zero_grad(set_to_none=True)
    dist = np.linalg.norm(means[keep][:, :2] - centre, axis=1)
    near, far = dist < 0.35, dist > 0.6
    r = densify_and_prune(params, opt, stats, grad_threshold=cfg_.grad_threshold, large_scale=1.0,
                          prune_opacity=0.05, max_scale=10.0, budget=10 * m,
                          generator=torch.Generator().manual_seed(0))
    cloned = (stats.mean() > cfg_.grad_threshold).numpy()
    assert r["cloned"] == int(cloned.sum()) and r["split"] == 0
    assert cloned[near].mean() > 0.9, cloned[near].mean()          # the hole's rim densifies
    assert cloned[far].mean() < 0.1, cloned[far].mean()            # fitted surfels do not
    assert r["surfels"] == m + r["cloned"]
    # the pixel-unit statistic (the old behaviour) misses most of the rim
    assert ((stats.mean() / (W / 2)).numpy()[near] > cfg_.grad_threshold).mean() < 0.5


def test_median_depth_loss_moves_the_front_surfel():
    """Two layers: the front surfel (the median, what the mesh fuses) sits 10 cm before the target;
    the median-depth term pulls that front surfel, not the one behind it, to the target."""
    from psimap.train.trainer import loss_terms, make_params, to_train_frame

    means = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -0.2]])         # camera looks down from z = 2
    params = make_params(means, np.tile([1.0, 0, 0, 0], (2, 1)), np.full((2, 2), 2.0),
                         np.array([0.9, 0.9]), np.full((2, 3), 0.5))
    from psimap.camera import look_at

    c2w = look_at(np.array([0.0, 0.0, 2.0]), (0.0, 0.0, 0.0))
    fr = to_train_frame("v", np.full((H, W, 3), 0.5), np.full((H, W), 2.1), K, c2w)
    cfg_ = TrainConfig(use_prior=False, lambda_rgb=0.0, lambda_iso=0.0, lambda_depth=0.0,
                       lambda_depth_median=1.0)
    terms, out = loss_terms(params, fr, cfg_, None, 0.1, False)
    assert "depth_median" in terms and float(terms["rgb"].detach()) == 0.0
    assert float(out.median_depth.detach()[H // 2, W // 2]) == pytest.approx(2.0, abs=1e-3)
    assert float(terms["depth_median"].detach()) == pytest.approx(0.1, abs=2e-3)
    terms["depth_median"].backward()
    g = params["means"].grad
    assert float(g[0, 2]) > 0 and float(g[1].abs().sum()) == 0.0   # only the front surfel, pushed down


def test_prior_fit_uses_the_measured_depth_noise(scene_frames):
    """With noise growing with range, the noise-aware SOGMM (prior_noise) keeps noisy patches whole:
    fewer components than the noise-blind fit of the same frames; training stays finite."""
    from psimap.data.frames import Frame

    frames, _ = scene_frames
    rng = np.random.default_rng(0)
    noisy = []
    for f in frames:
        d = f.depth.astype(np.float64)
        sigma = 0.003 + 0.02 * np.clip(d - 1.0, 0, None) ** 2        # grows with range
        nd = np.where(d > 0, d + rng.standard_normal(d.shape) * sigma, 0).astype(np.float32)
        noisy.append(Frame(rgb=f.rgb, depth=nd, K=f.K, c2w=f.c2w, name=f.name))
    aware = train(sequence(noisy), cfg(iters=4), log=lambda m: None)
    blind = train(sequence(noisy), cfg(iters=4, prior_noise=False), log=lambda m: None)
    assert aware.metrics["sogmm_K"] < 0.8 * blind.metrics["sogmm_K"], (aware.metrics["sogmm_K"], blind.metrics["sogmm_K"])
    assert torch.isfinite(aware.surfels["means"]).all()


def test_prior_noise_with_non_finite_depth(scene_frames):
    """+inf and NaN depth pixels are invalid for the prior's points and for their noise alike (one
    noise value per point, or the fit gets arrays of different lengths)."""
    from psimap.data.frames import Frame

    frames, _ = scene_frames
    bad = []
    for k, f in enumerate(frames):
        d = f.depth.astype(np.float32).copy()
        d[k % 5::7, ::3] = np.inf
        d[::11, k % 4::5] = np.nan
        bad.append(Frame(rgb=f.rgb, depth=d, K=f.K, c2w=f.c2w, name=f.name))
    scene = train(sequence(bad), cfg(iters=4), log=lambda m: None)
    assert scene.metrics["sogmm_K"] > 0 and torch.isfinite(scene.surfels["means"]).all()


def test_openmp_threads_wait_passively_unless_the_user_says():
    """`import psimap` before torch makes OpenMP's idle threads sleep (spinning ones took a core
    from the other thread on a busy 2-core machine); a policy the user set is kept."""
    import os
    import subprocess
    import sys

    code = "import psimap, os, torch; print(os.environ['OMP_WAIT_POLICY'])"
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.stdout.split() == ["PASSIVE"], out.stderr[-500:]
    out = subprocess.run([sys.executable, "-c", code], env={**env, "OMP_WAIT_POLICY": "active"},
                         capture_output=True, text=True, timeout=120)
    assert out.stdout.split() == ["active"], out.stderr[-500:]
