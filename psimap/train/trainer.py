"""Joint optimisation of the surfel map (geometry + appearance) against posed RGB-D frames.

Flow: frames -> (SOGMM prior -> initial surfels, colour from the images) -> Adam over surfel
parameters, one random frame per step, with L_rgb + depth L1 + L_geo + L_iso + 2DGS normal
consistency / distortion -> adaptive density control within a surfel budget -> the panoptic
field on the frozen surfel set (`panoptic_phase`, psimap.panoptic.fit's loop) -> Scene.
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from psimap import PsimapError
from psimap.data.frames import evenly_spaced
from psimap.cores import available_cores
from psimap.nonfinite import Diverged, NonFiniteGuard, backward_if_finite
from psimap.panoptic.fit import View
from psimap.train.config import TrainConfig
from psimap.train import losses as L
from psimap.train.density import GradStats, accumulate, densify_and_prune
from psimap.transforms import depth_to_world, quat_to_rotmat_torch

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logit", "color_logit")

# Fewest surfels an initialisation or a budget gives, however small the observed area.
MIN_SURFELS = 16
# Initial opacity of every surfel (then learned): below 1, so surfels behind an overlapping one
# still get some blending weight, and gradients, from the first step.
INIT_OPACITY = 0.7
# Depth pixels the target spacing's median depth is taken over: every 7th valid pixel is plenty
# for a median and keeps the concatenation small.
SPACING_DEPTH_STEP = 7
# About this many back-projected points from the whole sequence feed the prior and the init (the
# SOGMM fit's time grows with the point count; point_stride picks the pixel step).
PRIOR_POINTS = 400_000
# Scene extent (sets the position learning rate and the prune size): the 1st-99th percentile box of
# every 4th pixel of ~20 frames spread over the sequence; percentiles ignore stray depth returns.
EXTENT_FRAMES = 20
EXTENT_PIXEL_STEP = 4
EXTENT_PERCENTILE = 1
# A thing's SOGMM patches are at most this many thing spacings wide (so each holds ~this^2 surfels
# and the patch planes follow the object's curvature at the scale its surfels resolve).
THING_PATCH_SPACINGS = 4
# A stuff component whose shorter side spans this many of its own surfel spacings is large planar
# stuff (walls, floor, ceiling), spaced TrainConfig.stuff_spacing_factor coarser.
LARGE_PLANE_SPACINGS = 6
# Smallest footprint (m per pixel) a component is given: guards a degenerate zero-depth average.
MIN_FOOTPRINT = 1e-5
# Things take at most this share of the initial surfels, however much of the view they fill: the
# rest of the scene keeps enough to be covered.
THING_SHARE_MAX = 0.5
# Depth error before / after training is measured on this many frames spread over the sequence.
EVAL_FRAMES = 6
# The position step decays exponentially to this fraction of lr_means (coarse moves first).
MEANS_LR_END = 0.01
# loss_end is the mean over the last 1/LOSS_END_PART of the steps (one step's loss is one frame's).
LOSS_END_PART = 10
# The plateau rule watches the frames' fit: the data terms, whose weights the schedule never changes
# (L_geo's decays, the regularisers switch on, the LiDAR term comes every other step).
DATA_TERMS = ("rgb", "depth", "depth_median")
# A density-control round that changes at most this share of the surfels settles the set (with
# the plateau rule on): no later round, and the plateau rule may start counting.
DENSITY_SETTLED = 0.02
# The plateau rule pairs a window's steps with the window before by frame when at least this many
# frames appear in both (else it compares the two windows' plain means).
PLATEAU_MIN_PAIRED = 3
# Weight of the newest step in the smoothed loss shown on the progress bar and in `history`.
LOSS_EMA = 0.1


@dataclass
class Plateau:
    """When to end the geometry steps: every `window` steps, the frames' loss (DATA_TERMS) of the
    last window is compared with the window before, frame by frame (a step's loss is one random
    frame's, and frames differ far more from each other than one frame does between windows); the
    steps end when the relative gain is below `tol`. window 0: never (the cap, cfg.iters, ends them).
    """

    window: int
    tol: float
    frames: list = field(default_factory=list)
    losses: list = field(default_factory=list)
    gain: float = float("nan")
    checks: list = field(default_factory=list)        # [step, gain] of every comparison made

    def add(self, frame: int, loss: float) -> None:
        self.frames.append(int(frame))
        self.losses.append(float(loss))

    def stalled(self, steps_settled: int) -> bool:
        """True when, `steps_settled` steps after the schedule settled (a multiple of the window, two
        windows at least), the last window improved on the one before by less than tol."""
        w = self.window
        if w <= 0 or steps_settled < 2 * w or steps_settled % w or len(self.losses) < 2 * w:
            return False
        fa, la = np.array(self.frames[-2 * w:-w]), np.array(self.losses[-2 * w:-w])
        fb, lb = np.array(self.frames[-w:]), np.array(self.losses[-w:])
        common = np.intersect1d(fa, fb)
        if len(common) >= PLATEAU_MIN_PAIRED:
            before = sum(float(la[fa == f].mean()) for f in common)
            after = sum(float(lb[fb == f].mean()) for f in common)
        else:
            before, after = float(la.mean()), float(lb.mean())
        self.gain = (before - after) / max(before, 1e-12)
        self.checks.append([len(self.losses), self.gain])
        return self.gain < self.tol


@dataclass
class TrainFrame(View):
    """One training frame at training resolution: a View (depth, K, poses, pseudo-labels) with its
    colour image rgb [H,W,3] float32 in [0, 1]."""

    rgb: torch.Tensor = field(kw_only=True)

    @property
    def valid(self) -> torch.Tensor:
        return self.depth > 0


# ------------------------------------------------------------------------------------------------
# frames


def downscale(rgb, depth, K, factor: int):
    """Block-average by an integer factor. rgb [H,W,3], depth [H,W] (0 = invalid), K [3,3] numpy.

    A block's depth is kept only when all its pixels are valid and agree within 5 % (no mixing
    across depth edges). Pixel centres: new pixel j covers old pixels f j .. f j + f - 1, so
    c' = (c - (f - 1) / 2) / f and f' = f / factor.
    """
    if factor == 1:
        return rgb, depth, K
    H, W = depth.shape
    h, w = H // factor, W // factor
    r = rgb[: h * factor, : w * factor].reshape(h, factor, w, factor, 3).mean((1, 3))
    d = depth[: h * factor, : w * factor].reshape(h, factor, w, factor)
    dmin, dmax = d.min((1, 3)), d.max((1, 3))
    ok = (dmin > 0) & (dmax - dmin <= 0.05 * dmax)
    dd = np.where(ok, d.mean((1, 3)), 0.0)
    K2 = np.array(K, dtype=np.float64)
    K2[0, 0] /= factor
    K2[1, 1] /= factor
    K2[0, 2] = (K2[0, 2] - (factor - 1) / 2) / factor
    K2[1, 2] = (K2[1, 2] - (factor - 1) / 2) / factor
    return r.astype(np.float32), dd.astype(np.float32), K2


def downscale_labels(label, factor: int, shape):
    """Nearest-neighbour label map [H,W] at 1/factor (the block's centre pixel), cropped to `shape`."""
    if label is None:
        return None
    lab = np.asarray(label).astype(np.int64)
    if factor > 1:
        lab = lab[factor // 2::factor, factor // 2::factor]
    return torch.from_numpy(np.ascontiguousarray(lab[: shape[0], : shape[1]]))


def to_train_frame(name, rgb, depth, K, c2w, semantic=None, instance=None) -> TrainFrame:
    """TrainFrame of numpy arrays: rgb [H,W,3], depth [H,W], K [3,3], c2w [4,4] (OpenCV)."""
    return TrainFrame(name=name, rgb=torch.from_numpy(np.ascontiguousarray(rgb, np.float32)),
                      depth=torch.from_numpy(np.ascontiguousarray(depth, np.float32)),
                      K=torch.as_tensor(K, dtype=torch.float32), c2w=np.asarray(c2w, np.float64),
                      viewmat=torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32),
                      semantic=semantic, instance=instance)


def prepare_frames(seq, cfg: TrainConfig, log=print):
    """Frames at training resolution (width <= cfg.max_width) plus half-resolution copies, and the
    LiDAR sweeps the frames carry (psimap.train.lidar.Sweep).

    Frames without any valid depth are skipped (reported by name), unless the capture has LiDAR:
    then their colour still trains the map and the sweeps supply the geometry. Returns
    (frames, low, skipped, sweeps).
    """
    from psimap.train.lidar import sweep_of

    n = len(seq)
    if n == 0:
        raise PsimapError("the data folder has no frames")
    idx = evenly_spaced(n, cfg.max_frames)
    kept, skipped, sweeps = [], [], []
    for i in idx:
        f = seq[int(i)]
        depth = np.asarray(f.depth, np.float32)
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
        if cfg.max_depth > 0:
            depth = np.where(depth <= cfg.max_depth, depth, 0.0)
        rgb = np.asarray(f.rgb, np.float32)
        if not np.isfinite(rgb).all() or not np.isfinite(f.c2w).all():
            skipped.append(f.name or str(i))       # non-finite colour or pose
            continue
        sweep = sweep_of(f, f.name or str(i)) if cfg.lidar else None
        if sweep is not None:
            sweeps.append(sweep)
        kept.append((f, rgb, depth, i))
    frames, low = [], []
    for f, rgb, depth, i in kept:
        if not np.any(depth > 0) and not sweeps:
            skipped.append(f.name or str(i))
            continue
        factor = max(1, int(math.ceil(f.width / cfg.max_width)))
        r, d, K = downscale(rgb, depth, f.K, factor)
        frames.append(to_train_frame(f.name or str(i), r, d, K, f.c2w,
                                     downscale_labels(f.semantic, factor, d.shape),
                                     downscale_labels(f.instance, factor, d.shape)))
        r2, d2, K2 = downscale(r, d, K, 2)
        low.append(to_train_frame(f.name or str(i), r2, d2, K2, f.c2w))
    if skipped:
        log(f"skipping {len(skipped)} frame(s) without valid depth (or with NaN colour / pose): {', '.join(skipped[:5])}"
            f"{' ...' if len(skipped) > 5 else ''}")
    if not frames:
        raise PsimapError("no frame has valid depth: nothing to train on")
    sizes = {(fr.width, fr.height) for fr in frames}
    if len(sizes) > 1:
        raise PsimapError(f"frames differ in size {sorted(sizes)}: one camera resolution expected")
    return frames, low, skipped, sweeps


def backprojected(frames, stride: int):
    """World points [P,3] float64 and their colours [P,3] of every `stride`-th valid pixel of each frame."""
    pts, cols = [], []
    for fr in frames:
        p, v, u = depth_to_world(fr.depth.numpy(), fr.K.numpy(), fr.c2w, stride=stride)
        pts.append(p)
        cols.append(fr.rgb.numpy()[v, u])
    return np.concatenate(pts), np.concatenate(cols)


def observed_points(frames, stride: int, sweeps=()):
    """backprojected() and, with LiDAR, every return with its colour (psimap.train.lidar.colour_returns)."""
    p, c = backprojected(frames, stride)
    if sweeps:
        from psimap.train.lidar import colour_returns

        lp, lc = colour_returns(sweeps, frames)
        p, c = np.concatenate([p, lp]), np.concatenate([c, lc])
    return p, c


def target_spacing(frames, pixels: float, sweeps=()) -> float:
    """`pixels` pixel footprints at the median observed depth (what the views can resolve), metres.
    Without depth images, the median depth of the LiDAR returns the frames see."""
    z = np.concatenate([fr.depth[fr.valid].numpy()[::SPACING_DEPTH_STEP] for fr in frames])
    if len(z) == 0 and sweeps:
        from psimap.train.lidar import depths_in_frames

        z = depths_in_frames(sweeps, frames)
    if len(z) == 0:
        raise PsimapError("no frame has valid depth and no LiDAR return is in view: nothing to train on")
    med = float(np.median(z))
    focal = float(np.median([0.5 * (fr.K[0, 0] + fr.K[1, 1]) for fr in frames]))
    return pixels * med / focal


def point_stride(frames) -> int:
    """Pixel step that back-projects about PRIOR_POINTS points from the whole sequence (prior and init)."""
    return max(1, int(round(math.sqrt(frames[0].width * frames[0].height * len(frames) / PRIOR_POINTS))))


def prior_points(frames, cfg: TrainConfig, log=print, sweeps=()):
    """4D points (x, y, z, grey) [P, 4] of every stride-th valid pixel for the SOGMM fit, then the
    LiDAR returns (psimap.train.lidar.prior_returns); the noise std [P] of each (depth pixels:
    sigma(z) estimated from the frames' own depth, psimap.geometry.depth_noise; returns: the
    sweeps' own range noise), or None when cfg.prior_noise is off or no noise is measurable; the
    pixel step; and each point's footprint [P], metres per pixel at its own viewing distance (a
    pixel's depth / its frame's focal length; a return's distance to the nearest training camera /
    the median focal length). Returns (pts4, noise, stride, footprint)."""
    from psimap.geometry.points import backproject_frame

    stride = point_stride(frames)
    per_frame = [backproject_frame(fr.rgb.numpy(), fr.depth.numpy(), fr.K.numpy(), fr.c2w, stride=stride)
                 for fr in frames]
    pts4 = np.concatenate(per_frame)
    # each point's camera depth: its offset from the camera centre along the optical axis
    z = np.concatenate([(p[:, :3] - np.asarray(fr.c2w, np.float64)[:3, 3]) @ np.asarray(fr.c2w, np.float64)[:3, 2]
                        for p, fr in zip(per_frame, frames)])
    focals = np.array([0.5 * float(fr.K[0, 0] + fr.K[1, 1]) for fr in frames])
    footprint = z / np.repeat(focals, [len(p) for p in per_frame])
    lidar4 = np.zeros((0, 4), np.float32)
    if sweeps:
        from scipy.spatial import cKDTree

        from psimap.train.lidar import prior_returns

        lidar4 = prior_returns(sweeps, frames, PRIOR_POINTS)
        centres = np.stack([np.asarray(fr.c2w, np.float64)[:3, 3] for fr in frames])
        dist, _ = cKDTree(centres).query(lidar4[:, :3].astype(np.float64), k=1)
        footprint = np.concatenate([footprint, dist / float(np.median(focals))])
    all4 = np.concatenate([pts4, lidar4])
    if not cfg.prior_noise:
        return all4, None, stride, footprint
    from psimap.geometry.depth_noise import estimate_depth_noise, noise_at

    model = estimate_depth_noise([fr.depth.numpy() for fr in frames])
    noise = None
    if len(model[0]):
        zc, sc = model
        log(f"depth noise from the images: sigma {sc[0] * 1000:.1f} mm at {zc[0]:.1f} m .. "
            f"{sc[-1] * 1000:.1f} mm at {zc[-1]:.1f} m")
        noise = noise_at(z, model)
    if len(lidar4):
        from psimap.train.lidar import range_noise

        # pixels without a noise model count as noiseless (the fit's behaviour without noise)
        noise = np.concatenate([np.zeros(len(pts4)) if noise is None else noise,
                                np.full(len(lidar4), range_noise(sweeps))])
    return all4, noise, stride, footprint


def thing_points(frames, classes, stride: int) -> np.ndarray | None:
    """Which back-projected points (prior_points' order) lie in a thing mask: [P] bool, or None when
    no frame carries masks. A pixel is on a thing when its semantic class is a thing class, or,
    without semantic maps or a class table, when it has an instance id. Frames without masks give
    False (the coarse rule)."""
    thing_ids = [int(c["id"] if isinstance(c, dict) else c.id) for c in classes or []
                 if (c["isthing"] if isinstance(c, dict) else c.isthing)]
    if not any(fr.semantic is not None or fr.instance is not None for fr in frames):
        return None
    out = []
    for fr in frames:
        d = fr.depth.numpy()[::stride, ::stride]
        valid = np.isfinite(d) & (d > 0)            # backproject_frame's pixels, in its order
        if fr.semantic is not None and thing_ids:
            on = np.isin(fr.semantic.numpy()[::stride, ::stride], thing_ids)
        elif fr.instance is not None:
            on = fr.instance.numpy()[::stride, ::stride] > 0
        else:
            on = np.zeros(d.shape, bool)
        out.append(on[valid])
    return np.concatenate(out)


def _pad_to(mask: np.ndarray | None, n: int) -> np.ndarray | None:
    """thing_points' mask [P] extended with False to n points (the LiDAR returns after the pixels)."""
    return None if mask is None else np.concatenate([mask, np.zeros(n - len(mask), bool)])


def fit_prior(frames, cfg: TrainConfig, spacing: float, classes=None, log=print, sweeps=()):
    """The SOGMM prior of the frames' back-projected points (prior_points). With cfg.thing_detail and
    masked frames, points in thing masks are fitted finer (patches at most THING_PATCH_SPACINGS thing
    spacings wide; sogmm.detail says which components are on things). With cfg.distance_spacing
    each component also knows its points' mean footprint (sogmm.footprint, metres per pixel).
    Returns (sogmm, pts4, stride)."""
    from psimap.geometry.sogmm import fit_sogmm

    pts4, noise, stride, footprint = prior_points(frames, cfg, log, sweeps)
    kw = {"noise": noise, "footprint": footprint if cfg.distance_spacing else None}
    thing = _pad_to(thing_points(frames, classes, stride), len(pts4)) if cfg.thing_detail else None
    if thing is None or not thing.any():
        return fit_sogmm(pts4, **kw), pts4, stride
    return (fit_sogmm(pts4, detail=thing, detail_extent=THING_PATCH_SPACINGS * thing_spacing(spacing, cfg), **kw),
            pts4, stride)


def thing_spacing(spacing: float, cfg: TrainConfig) -> float:
    """Target surfel spacing on things (m): the scene's spacing scaled by thing / scene pixels."""
    return spacing * cfg.thing_spacing_pixels / cfg.spacing_pixels


def relative_density(sogmm, spacing: float, cfg: TrainConfig, n_total: int) -> np.ndarray | None:
    """Surfels per m^2 of each component relative to the others [K], or None (uniform) when the
    prior knows no things. Thing components get the thing spacing; the rest of the scene shares
    what is left of the same n_total (so it gets coarser), and things never take more than
    THING_SHARE_MAX of it."""
    if sogmm.detail is None:
        return None
    side = sogmm.extents()
    areas = side[:, 0] * side[:, 1]
    on = sogmm.detail > 0.5
    a_thing, a_stuff = float(areas[on].sum()), float(areas[~on].sum())
    if a_thing <= 0 or a_stuff <= 0:
        return None
    n_thing = min(a_thing / thing_spacing(spacing, cfg) ** 2, THING_SHARE_MAX * n_total)
    ratio = (n_thing / a_thing) / ((n_total - n_thing) / a_stuff)
    return np.where(on, max(ratio, 1.0), 1.0)


def component_spacing(sogmm, spacing: float, cfg: TrainConfig) -> tuple[np.ndarray, np.ndarray]:
    """Target surfel spacing of each prior component (m) [K] from what the views resolve there, and
    which components are large planar stuff [K] bool.

    A component's spacing is cfg.spacing_pixels pixel footprints at its own points' viewing distance
    (sogmm.footprint): a far wall gets coarser surfels than a near table. Thing components (the
    masks' detail) keep the thing spacing of the rule before (thing_spacing: thing_spacing_pixels
    at the median depth); finer near things (thing_spacing_pixels footprints) measured no better
    geometry and a lower thing PQ on the demo scene (0.66 vs 0.82). A component that is not on a thing and whose
    shorter side spans LARGE_PLANE_SPACINGS of its spacings is large planar stuff (a wall, the floor,
    a ceiling: the fit left it that large because it is flat within the noise), spaced
    cfg.stuff_spacing_factor times coarser: a 2D surfel represents a plane at any size.
    """
    fp = sogmm.footprint
    if fp is None:
        fp = np.full(sogmm.K, spacing / cfg.spacing_pixels)
    fp = np.maximum(np.asarray(fp, np.float64), MIN_FOOTPRINT)
    s = cfg.spacing_pixels * fp
    thing = np.zeros(sogmm.K, bool) if sogmm.detail is None else sogmm.detail > 0.5
    s[thing] = thing_spacing(spacing, cfg)
    planar = ~thing & (sogmm.extents().min(1) >= LARGE_PLANE_SPACINGS * s)
    s[planar] *= cfg.stuff_spacing_factor
    return s, planar


def max_initial_surfels(cfg: TrainConfig) -> int:
    """The most initial surfels any capture gets: the budget (budget_factor x this) stays within
    cfg.max_surfels (0 = no cap)."""
    return int(cfg.max_surfels / max(cfg.budget_factor, 1.0)) if cfg.max_surfels > 0 else 0


# ------------------------------------------------------------------------------------------------
# initialisation


def _logit(p):
    p = torch.as_tensor(p, dtype=torch.float32).clamp(1e-4, 1 - 1e-4)
    return torch.log(p) - torch.log1p(-p)


def make_params(means, quats, scales, opacities, colors) -> dict:
    """Leaf tensors of the optimised parametrisation from plain surfel values."""
    return {"means": torch.as_tensor(means, dtype=torch.float32).clone().requires_grad_(True),
            "quats": torch.as_tensor(quats, dtype=torch.float32).clone().requires_grad_(True),
            "log_scales": torch.log(torch.as_tensor(scales, dtype=torch.float32).clamp_min(1e-7))
            .requires_grad_(True),
            "opacity_logit": _logit(opacities).requires_grad_(True),
            "color_logit": _logit(colors).requires_grad_(True)}


def surfel_tensors(params: dict) -> tuple:
    """(means [N,3], unit quats [N,4], scales [N,2], opacities [N], colors [N,3]) from the
    parametrisation; differentiable in the leaf tensors."""
    q = params["quats"]
    return (params["means"], q / q.norm(dim=1, keepdim=True).clamp_min(1e-12), params["log_scales"].exp(),
            torch.sigmoid(params["opacity_logit"]), torch.sigmoid(params["color_logit"]))


def surfel_values(params: dict) -> dict:
    """Checkpoint surfels (contract) from the parametrisation (detached)."""
    with torch.no_grad():
        means, quats, scales, opacities, colors = surfel_tensors(params)
        n = means.shape[0]
        return {"means": means.detach().clone(), "quats": quats.clone(), "scales": scales.clone(),
                "opacities": opacities.clone(), "colors": colors.clone(),
                "semantic": torch.zeros(n, 0), "instance": torch.zeros(n, 0)}


def init_from_prior(frames, cfg: TrainConfig, spacing: float, classes=None, log=print, sweeps=()):
    """SOGMM prior of the back-projected frames -> surfels on its patches at `spacing` (on average:
    finer on things, coarser elsewhere, when the frames carry masks; see relative_density).

    Returns (params, index (SOGMMIndex), info dict with K, area, n_init).
    """
    from scipy.spatial import cKDTree

    from psimap.geometry.sogmm import SOGMMIndex, sample_surfels

    t0 = time.perf_counter()
    sogmm, pts4, stride = fit_prior(frames, cfg, spacing, classes, log, sweeps)
    side = sogmm.extents()
    areas = side[:, 0] * side[:, 1]
    area = float(areas.sum())
    cap = max_initial_surfels(cfg)
    info = {"sogmm_K": sogmm.K, "area": area}
    if cfg.distance_spacing:
        s_k, planar = component_spacing(sogmm, spacing, cfg)
        n_need = float((areas / s_k**2).sum())
        rel = 1.0 / s_k**2
        spacing_note = (f"spacing {s_k.min() * 100:.1f}..{s_k.max() * 100:.1f} cm by viewing distance "
                        f"(median-depth rule: {spacing * 100:.1f} cm), {float(areas[planar].sum()):.1f} m^2 "
                        f"large planar stuff at {cfg.stuff_spacing_factor:g}x")
        info.update(spacing_min=float(s_k.min()), spacing_max=float(s_k.max()),
                    planar_area=float(areas[planar].sum()))
    else:
        n_need = area / spacing**2
        rel = None
        spacing_note = f"spacing {spacing * 100:.1f} cm"
    scale = math.sqrt(n_need / cap) if cap and n_need > cap else 1.0
    n_init = max(MIN_SURFELS, int(round(n_need / scale**2)))
    if not cfg.distance_spacing:
        rel = relative_density(sogmm, spacing, cfg, n_init)
    means, quats, scales, _ = sample_surfels(sogmm, n_init, relative_density=rel, seed=cfg.seed)
    if sogmm.detail is not None and rel is not None:
        on = sogmm.detail > 0.5
        dens = rel * n_init / float((areas * rel).sum())
        log(f"things: {int(on.sum())} of {sogmm.K} components, {float(areas[on].sum()):.1f} m^2, "
            f"{np.median(dens[on]) / max(np.median(dens[~on]) if (~on).any() else 1.0, 1e-12):.1f}x the "
            f"surfels per m^2 of the rest (medians)")
    if scale > 1.0:
        log(f"surfel cap: the spacing asked for {int(round(n_need))} surfels; spacing raised {scale:.2f}x to "
            f"{n_init} (max_surfels {cfg.max_surfels} / budget_factor {cfg.budget_factor:g})")
    log(f"SOGMM prior: K = {sogmm.K} components from {len(pts4)} points, residual "
        f"{sogmm.fit_stats.get('residual_mean', float('nan')) * 1000:.1f} mm (budget "
        f"{sogmm.fit_stats.get('residual_budget', float('nan')) * 1000:.1f} mm), {time.perf_counter() - t0:.1f} s; "
        f"{n_init} surfels over {area:.1f} m^2, {spacing_note}")
    info.update(n_init=len(means), n_needed=int(round(n_need)), spacing_scale=scale)
    # colour: the image colour of the nearest observed point
    p, c = observed_points(frames, stride, sweeps)
    _, nn = cKDTree(p).query(means, k=1)
    colors = c[nn]
    params = make_params(means, quats, scales, np.full(len(means), INIT_OPACITY), colors)
    return params, SOGMMIndex(sogmm), info


def init_from_points(frames, cfg: TrainConfig, spacing: float, log=print, sweeps=()):
    """Baseline without the prior (plain 2DGS): surfels at observed points, isotropic kNN scales,
    random rotations, as many as the prior would give for the voxelised observed surface."""
    from scipy.spatial import cKDTree

    from psimap.geometry.points import voxel_downsample

    stride = point_stride(frames)
    p, c = observed_points(frames, stride, sweeps)
    pc = voxel_downsample(np.concatenate([p, c], 1), spacing)
    cap = max_initial_surfels(cfg)
    if cap and len(pc) > cap:
        # a voxel sqrt(n / cap) x coarser keeps about cap points of a surface (n scales with 1 / voxel^2)
        log(f"surfel cap: {len(pc)} observed points at {spacing * 100:.1f} cm; voxel raised "
            f"{math.sqrt(len(pc) / cap):.2f}x")
        pc = voxel_downsample(np.concatenate([p, c], 1), spacing * math.sqrt(len(pc) / cap))
    means, colors = pc[:, :3], pc[:, 3:6]
    d, _ = cKDTree(means).query(means, k=4)
    s = np.clip(d[:, 1:].mean(1), 1e-4, 10 * spacing)
    rng = np.random.default_rng(cfg.seed)
    q = rng.normal(size=(len(means), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    log(f"baseline init: {len(means)} surfels from observed points (no prior)")
    params = make_params(means, q, np.stack([s, s], 1), np.full(len(means), INIT_OPACITY), np.clip(colors, 0, 1))
    return params, None, {"sogmm_K": 0, "area": float(len(means) * spacing**2), "n_init": len(means)}


# ------------------------------------------------------------------------------------------------
# training


def on_things(means, index) -> torch.Tensor | None:
    """[N] bool: surfels whose nearest prior component is on a thing (density control serves them
    first), or None when the prior knows no things."""
    if index is None or index.sogmm.detail is None:
        return None
    return torch.as_tensor(index.sogmm.detail > 0.5)[index.nearest(means.detach()).cpu()]


def make_optimizer(params: dict, cfg: TrainConfig, extent: float):
    """Adam over the surfel parameters, one group per name (PARAM_NAMES order, group 0 = means);
    returns (optimizer, the position step: lr_means x the scene extent)."""
    lrs = {"means": cfg.lr_means * extent, "quats": cfg.lr_quats, "log_scales": cfg.lr_scales,
           "opacity_logit": cfg.lr_opacity, "color_logit": cfg.lr_colors}
    groups = [{"params": [params[k]], "lr": lrs[k], "name": k} for k in PARAM_NAMES]
    # eps as in 3DGS: surfel gradients are tiny, and Adam's default 1e-8 would shrink their steps;
    # fused: one pass per tensor (the per-op default made ~10 passes over every surfel parameter)
    return torch.optim.Adam(groups, eps=1e-15, fused=True), lrs["means"]


def render(params: dict, fr: TrainFrame):
    """RenderOutput of all surfels in the view `fr`."""
    from psimap.render import rasterize

    return rasterize(*surfel_tensors(params), fr.viewmat, fr.K, fr.width, fr.height, backend="auto")


def loss_terms(params: dict, fr: TrainFrame, cfg: TrainConfig, index, spacing: float,
               regularize: bool, generator: torch.Generator | None = None,
               geo_samples: int = 8192, geo_scale: float = 1.0, lidar_view=None) -> tuple[dict, object]:
    """Weighted loss terms of one view (name -> scalar tensor) and the render output; L_geo's weight
    is cfg.lambda_geo x geo_scale (its schedule). With a LiDAR view (psimap.train.lidar.LidarView),
    the range term of its returns joins, at cfg.lambda_range (each return with its weight)."""
    out = render(params, fr)
    if lidar_view is not None and cfg.lambda_range > 0:
        from psimap.train.lidar import range_l1

        terms_range = cfg.lambda_range * range_l1(render(params, lidar_view).depth, lidar_view)
    else:
        terms_range = None
    terms = {}
    terms["rgb"] = cfg.lambda_rgb * L.rgb_loss(out.rgb, fr.rgb, cfg.ssim_weight)
    if cfg.lambda_depth > 0:
        terms["depth"] = cfg.lambda_depth * L.depth_l1(out.depth, fr.depth, fr.valid)
    if cfg.lambda_depth_median > 0:
        terms["depth_median"] = cfg.lambda_depth_median * L.depth_l1(
            out.median_depth, fr.depth, fr.valid & (out.median_depth > 0))
    scales = params["log_scales"].exp()
    if cfg.lambda_iso > 0:
        terms["iso"] = cfg.lambda_iso * L.iso_loss(scales, spacing)
    if cfg.use_prior and cfg.lambda_geo * geo_scale > 0 and index is not None:
        from psimap.geometry.sogmm import geo_loss

        n = params["means"].shape[0]
        # an unbiased estimate of the mean over a random subset keeps the per-step cost bounded
        sub = torch.randperm(n, generator=generator)[:geo_samples] if n > geo_samples else slice(None)
        R = quat_to_rotmat_torch(params["quats"][sub])
        terms["geo"] = cfg.lambda_geo * geo_scale * geo_loss(params["means"][sub], R[:, :, 2], index,
                                                             lambda_n=cfg.lambda_geo_normal)
    if regularize and cfg.lambda_normal > 0:
        terms["normal"] = cfg.lambda_normal * L.normal_consistency(out.normal, out.alpha, out.depth, fr.K)
    if regularize and cfg.lambda_dist > 0:
        terms["distortion"] = cfg.lambda_dist * out.distortion.mean()
    if terms_range is not None:
        terms["range"] = terms_range
    return terms, out


@torch.no_grad()
def depth_error(params: dict, frames) -> float:
    """Mean |rendered depth - observed depth| (m) over the valid pixels of `frames`."""
    tot, cnt = 0.0, 0
    for fr in frames:
        out = render(params, fr)
        v = fr.valid
        tot += float((out.depth - fr.depth).abs()[v].sum())
        cnt += int(v.sum())
    return tot / max(cnt, 1)


@torch.no_grad()
def range_error(params: dict, views) -> float:
    """Mean |rendered depth - measured depth| (m) over the returns of LiDAR views (0 without any)."""
    from psimap.train.lidar import range_l1

    tot, cnt = 0.0, 0
    for v in views:
        tot += float(range_l1(render(params, v).depth, v, weighted=False)) * v.z.numel()
        cnt += v.z.numel()
    return tot / max(cnt, 1)


def lidar_setup(frames, sweeps, cfg: TrainConfig, log) -> tuple[list, dict]:
    """The virtual views of the sweeps with each return's weight (psimap.train.lidar.range_weight:
    depth-image noise at its range / LiDAR range noise) and metrics for the checkpoint."""
    if not sweeps:
        return [], {}
    from psimap.geometry.depth_noise import estimate_depth_noise, noise_at
    from psimap.train.lidar import lidar_views, range_noise, range_weight

    views = [v for s in sweeps for v in lidar_views(s, cfg.max_depth)]
    sigma_l = range_noise(sweeps)
    model = estimate_depth_noise([fr.depth.numpy() for fr in frames])
    for v in views:
        w = range_weight(noise_at(v.r, model) if len(model[0]) else None, sigma_l)
        v.w = torch.as_tensor(np.broadcast_to(w, v.r.shape).copy(), dtype=torch.float32)
    n = sum(len(s.points) for s in sweeps)
    w_all = torch.cat([v.w for v in views]) if views else torch.ones(1)
    log(f"LiDAR: {len(sweeps)} sweeps, {n} returns, range noise {sigma_l * 1000:.1f} mm; {len(views)} virtual "
        f"views; return weights {float(w_all.min()):.2f}..{float(w_all.max()):.2f} (median "
        f"{float(w_all.median()):.2f})" + ("" if len(model[0]) else " (no depth images)"))
    return views, {"lidar_sweeps": len(sweeps), "lidar_returns": n, "lidar_noise": sigma_l,
                   "range_weight": float(w_all.mean())}


def panoptic_phase(params: dict, frames, classes, cfg: TrainConfig, *, index, spacing: float,
                   extent: float, lr_means: float, generator: torch.Generator, rng: np.random.Generator,
                   log, progress: bool) -> tuple[dict, dict]:
    """The panoptic field (paper §4.2) trained on the surfel set the geometry schedule froze
    (`psimap.panoptic.fit.train_field`); with cfg.panoptic_geometry the geometry keeps training
    with its own losses and the panoptic ones. Returns (checkpoint part, metrics).

    params: the leaf tensors (PARAM_NAMES), replaced by detached ones on return; frames:
    TrainFrames; lr_means: the position step the geometry schedule ended at (continued).
    """
    from psimap.panoptic.fit import JointGeometry, train_field

    for k in PARAM_NAMES:
        params[k] = params[k].detach().clone().requires_grad_(cfg.panoptic_geometry)
    joint = None
    if cfg.panoptic_geometry:
        optimizer, _ = make_optimizer(params, cfg, extent)
        optimizer.param_groups[0]["lr"] = lr_means
        joint = JointGeometry(params={k: params[k] for k in PARAM_NAMES}, optimizer=optimizer,
                              terms=lambda fr: loss_terms(params, fr, cfg, index, spacing, True, generator)[0])
    state, metrics = train_field(frames, classes, cfg.panoptic_config(), lambda: surfel_tensors(params),
                                 iters=cfg.panoptic_iters, scene_scale=extent, rng=rng, generator=generator,
                                 joint=joint, log=log, progress=progress, log_every=cfg.log_every)
    for k in PARAM_NAMES:
        params[k] = params[k].detach()
    return state, metrics


def _isatty() -> bool:
    return sys.stderr.isatty()


def train(data, cfg: TrainConfig | None = None, *, resume=None, progress: bool | None = None,
          log=None, callback=None):
    """Train a surfel map on `data` (a folder path or a FrameSequence); returns a psimap.scene.Scene.

    resume: a Scene or checkpoint path to continue from (its surfels; cfg.iters more steps).
    callback: called as callback(step, params, elapsed_s) after every step (benchmarks snapshot
    `surfel_values(params)` with it).
    Raises PsimapError (Diverged) when a loss term or gradient stays non-finite; never returns NaN.
    """
    threads = torch.get_num_threads()
    native_threads = _native_threads()
    # one torch thread outside the geometry steps (small tensors: extra threads only spin-wait);
    # the renderer's kernels, most of a step, use the cores (_set_threads)
    torch.set_num_threads(1)
    try:
        return _train(data, cfg, resume=resume, progress=progress, log=log, callback=callback)
    finally:
        torch.set_num_threads(threads)
        if native_threads:
            from psimap.render import native

            native.set_num_threads(native_threads)


def _train(data, cfg, *, resume, progress, log, callback):
    from tqdm import tqdm

    from psimap.scene import Scene, load_scene

    cfg = cfg or TrainConfig()
    log = log or (lambda msg: print(msg, file=sys.stderr))
    progress = _isatty() if progress is None else progress
    t_start = time.perf_counter()
    cpu_start = time.process_time()
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    _set_threads(cfg)

    if isinstance(data, (str, bytes)) or hasattr(data, "__fspath__"):
        from psimap.data import load

        seq = load(data)
        data_path = str(data)
    else:
        seq, data_path = data, str(getattr(data, "root", ""))
    frames, low, skipped, sweeps = prepare_frames(seq, cfg, log)
    spacing = target_spacing(frames, cfg.spacing_pixels, sweeps)
    p_all, _ = backprojected(frames[:: max(1, len(frames) // EXTENT_FRAMES)], EXTENT_PIXEL_STEP)
    if sweeps:
        p_all = np.concatenate([p_all] + [s.points[::EXTENT_PIXEL_STEP] for s in sweeps])
    views, lidar_info = lidar_setup(frames, sweeps, cfg, log)
    extent = float(np.linalg.norm(np.percentile(p_all, 100 - EXTENT_PERCENTILE, 0)
                                  - np.percentile(p_all, EXTENT_PERCENTILE, 0)))

    classes = list(getattr(seq, "classes", []) or [])
    index = None
    steps_before = 0
    if resume is not None:
        prev = resume if isinstance(resume, Scene) else load_scene(resume)
        s = prev.surfels
        params = make_params(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"])
        steps_before = int(prev.metrics.get("steps", 0))
        info = {"sogmm_K": int(prev.metrics.get("sogmm_K", 0)),
                "n_init": int(prev.metrics.get("n_init", len(prev))),
                "area": float(prev.metrics.get("prior_area", len(prev) * spacing**2))}
        if cfg.use_prior and cfg.lambda_geo > 0:
            from psimap.geometry.sogmm import SOGMMIndex

            index = SOGMMIndex(fit_prior(frames, cfg, spacing, classes, log, sweeps)[0])
        log(f"resuming from {getattr(prev, 'path', None) or 'scene'}: {len(prev)} surfels, "
            f"{steps_before} steps done")
    elif cfg.use_prior:
        params, index, info = init_from_prior(frames, cfg, spacing, classes, log, sweeps)
    else:
        params, index, info = init_from_points(frames, cfg, spacing, log, sweeps)
    budget = max(int(cfg.budget_factor * info["n_init"]), MIN_SURFELS)
    if cfg.max_surfels > 0:
        budget = min(budget, max(int(cfg.max_surfels), MIN_SURFELS))

    eval_frames = frames[:: max(1, len(frames) // EVAL_FRAMES)][:EVAL_FRAMES]
    depth_err_start = depth_error(params, eval_frames)
    range_err_start = range_error(params, views)
    optimizer, lr_means0 = make_optimizer(params, cfg, extent)
    grad_stats = GradStats.zeros(params["means"].shape[0])
    iters = int(cfg.iters)
    lowres_steps = int(cfg.lowres_until * iters)
    reg_from = int(cfg.regularize_from * iters)
    dens_from, dens_until = int(cfg.densify_from * iters), int(cfg.densify_until * iters)
    ema, first_loss = {}, None
    guard = NonFiniteGuard()
    recent, window = [], max(1, iters // LOSS_END_PART)
    history = []
    dens_log = []
    # the plateau rule may end the geometry steps once the surfel set is settled (density control
    # done) and the schedule's switches (low resolution, regularisers) are behind
    plateau = Plateau(int(cfg.plateau_window), float(cfg.plateau_tol))
    settled_from = dens_until
    stop, steps_done = "cap", iters
    bar = tqdm(total=iters, desc="train", disable=not progress, dynamic_ncols=True)
    order = rng.integers(0, len(frames), size=iters)
    # one LiDAR view per step, alongside the frame (a separate stream: the frame order is unchanged)
    view_order = np.random.default_rng(cfg.seed + 1).integers(0, max(len(views), 1), size=iters)
    lidar_every = max(1, int(cfg.lidar_every))
    # torch stays on one thread: on two threads the tabletop's geometry steps took 55 s instead of
    # 65 s on an idle machine, but 383 s (344 s of CPU) at load 5-7: torch's thousands of small
    # parallel regions per step spin-wait for a core, where the renderer's few large ones do not
    for step in range(iters):
        fi = int(order[step])
        fr = low[fi] if step < lowres_steps else frames[fi]
        # L_geo's weight goes linearly from lambda_geo to geo_final x lambda_geo over the schedule
        geo_scale = 1.0 + (cfg.geo_final - 1.0) * step / max(iters - 1, 1)
        terms, out = loss_terms(params, fr, cfg, index, spacing, step >= reg_from, gen,
                                geo_scale=geo_scale,
                                lidar_view=views[int(view_order[step])] if views and step % lidar_every == 0 else None)
        bad = backward_if_finite(terms, {k: params[k] for k in PARAM_NAMES})
        if bad is not None:
            # skip this update: one bad frame must not poison the map; a persistent one is an error
            optimizer.zero_grad(set_to_none=True)
            try:
                guard.skip(bad, f"training diverged at step {steps_before + step} (frame {fr.name})")
            except Diverged:
                bar.close()
                raise
            continue
        guard.ok()
        if step < min(dens_until, settled_from):
            accumulate(grad_stats, params["means"].grad, params["means"].detach(), fr.viewmat, fr.K,
                       fr.width, fr.height)
        # position step decays exponentially (coarse moves first, then refinement)
        optimizer.param_groups[0]["lr"] = lr_means0 * MEANS_LR_END ** (step / max(iters - 1, 1))
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        vals = {k: float(v.detach()) for k, v in terms.items()}
        vals["total"] = float(sum(vals.values()))
        if first_loss is None:
            first_loss = dict(vals)
        for k, v in vals.items():
            ema[k] = v if k not in ema else (1 - LOSS_EMA) * ema[k] + LOSS_EMA * v
        recent.append(vals)
        if len(recent) > window:
            recent.pop(0)
        plateau.add(fi, sum(vals.get(k, 0.0) for k in DATA_TERMS))
        if dens_from <= step < min(dens_until, settled_from) and (step + 1) % cfg.densify_every == 0:
            r = densify_and_prune(params, optimizer, grad_stats, grad_threshold=cfg.grad_threshold,
                                  large_scale=cfg.split_scale * spacing, prune_opacity=cfg.prune_opacity,
                                  max_scale=cfg.prune_scale * extent, budget=budget, generator=gen,
                                  first=on_things(params["means"], index))
            dens_log.append({"step": steps_before + step + 1, **r})
            log(f"density control at step {steps_before + step + 1}: {r['cloned']} cloned, {r['split']} split, "
                f"{r['pruned']} pruned -> {r['surfels']} surfels (budget {budget})")
            grad_stats = GradStats.zeros(params["means"].shape[0])
            if plateau.window and r["cloned"] + r["split"] + r["pruned"] <= DENSITY_SETTLED * r["surfels"]:
                settled_from = step + 1         # a round that hardly changed the set: it is frozen
                log(f"density control settled at step {steps_before + step + 1}")
        done = plateau.stalled(step + 1 - max(settled_from, lowres_steps, reg_from))
        if done:
            stop, steps_done = "plateau", step + 1
            log(f"geometry converged at step {steps_before + step + 1}: the frames' loss improved "
                f"{plateau.gain * 100:.2f} % over the last {plateau.window} steps (< {plateau.tol * 100:g} %)")
        if (step + 1) % cfg.log_every == 0 or step == iters - 1 or done:
            history.append({"step": steps_before + step + 1, "loss": ema["total"],
                            "surfels": int(params["means"].shape[0]),
                            "time_s": time.perf_counter() - t_start})
            bar.set_postfix(loss=f"{ema['total']:.4f}", surfels=int(params["means"].shape[0]))
        bar.update(1)
        if callback is not None:
            callback(steps_before + step + 1, params, time.perf_counter() - t_start)
        if done:
            break
    bar.close()

    # final prune of surfels that ended up invisible (opacity faded) or degenerate
    with torch.no_grad():
        keep = torch.sigmoid(params["opacity_logit"]) >= cfg.prune_opacity
        for k in PARAM_NAMES:
            params[k] = params[k].detach()[keep]
    panoptic_state, panoptic_metrics = None, {}
    if cfg.panoptic and cfg.panoptic_iters > 0:
        from psimap.panoptic.fit import labelled

        if labelled(frames):
            panoptic_state, panoptic_metrics = panoptic_phase(
                params, frames, classes, cfg, index=index, spacing=spacing, extent=extent,
                lr_means=optimizer.param_groups[0]["lr"], generator=gen, rng=rng, log=log,
                progress=progress)
        else:
            log("panoptic: the frames carry no semantic / instance pseudo-labels; skipped")
    depth_err_end = depth_error(params, eval_frames)
    range_err_end = range_error(params, views)
    if views:
        log(f"LiDAR range error {range_err_start * 100:.2f} -> {range_err_end * 100:.2f} cm over {len(views)} views")
        lidar_info.update(range_l1_start=range_err_start, range_l1_end=range_err_end)
    loss_end = {k: float(np.mean([r[k] for r in recent if k in r])) for k in (recent[-1] if recent else {})}
    seconds = time.perf_counter() - t_start
    n = int(params["means"].shape[0])
    depth_note = (f"depth error {depth_err_start * 100:.2f} -> {depth_err_end * 100:.2f} cm"
                  if any(bool(fr.valid.any()) for fr in eval_frames) else "no depth images")
    log(f"trained {steps_done} steps ({stop}{'' if stop == 'plateau' else f' of {iters}'}) in {seconds:.1f} s: loss {first_loss['total'] if first_loss else float('nan'):.4f} -> "
        f"{loss_end.get('total', float('nan')):.4f}, {depth_note}, {n} surfels (budget {budget})")
    # CPU seconds = wall time on an idle machine (training is single-threaded by default)
    metrics = {"steps": steps_before + steps_done, "seconds": seconds,
               "geometry_steps": steps_done, "geometry_stop": stop, "plateau_gain": plateau.gain,
               "plateau_checks": plateau.checks,
               "density_settled": steps_before + min(settled_from, dens_until),
               "n_needed": int(info.get("n_needed", info["n_init"])),
               "spacing_scale": float(info.get("spacing_scale", 1.0)),
               "cpu_seconds": time.process_time() - cpu_start, "surfels": n, "budget": budget,
               "sogmm_K": info["sogmm_K"], "n_init": info["n_init"], "prior_area": info["area"],
               "spacing": spacing, "extent": extent,
               "loss_start": first_loss or {}, "loss_end": loss_end, "depth_l1_start": depth_err_start,
               "depth_l1_end": depth_err_end, "skipped_frames": skipped, "skipped_steps": guard.skipped,
               "history": history, "densify": dens_log, **lidar_info, **panoptic_metrics}
    cams = {"K": torch.stack([fr.K.double() for fr in frames]),
            "c2w": torch.as_tensor(np.stack([fr.c2w for fr in frames])),
            "width": frames[0].width, "height": frames[0].height, "names": [fr.name for fr in frames]}
    config = {**cfg.to_dict(), "data": data_path}
    surfels = surfel_values(params)
    queries = None
    if panoptic_state is not None:
        surfels.update(panoptic_state["surfels"])
        queries = panoptic_state["queries"]
        metrics["instance_class"] = {int(k): int(v) for k, v in panoptic_state["instance_class"].items()}
    return Scene(surfels, classes=classes, cameras=cams, queries=queries, config=config, metrics=metrics)


def _native_threads() -> int:
    """The native kernels' thread count now (0 when the native backend is not built)."""
    from psimap.render.api import native_available

    if not native_available():
        return 0
    from psimap.render import native

    return native.get_num_threads()


def _set_threads(cfg: TrainConfig) -> None:
    """The renderer's threads: cfg.threads, or every core this process may use. Any count gives
    the same bits (the native backward reduces in tile order)."""
    from psimap.render.api import native_available

    if not native_available():     # the torch reference: torch's own (single) thread
        return
    from psimap.render import native

    native.set_num_threads(render_threads(cfg))


def render_threads(cfg: TrainConfig) -> int:
    """Threads of the geometry steps: cfg.threads, or every core this process may use."""
    return int(cfg.threads) if cfg.threads > 0 else available_cores()

