"""Every training weight and schedule in one dataclass, with defaults and help text.

The panoptic field's own settings live in `psimap.panoptic.config.PanopticConfig`; the few that
`psimap train` exposes (`PANOPTIC_FIELDS`) take their defaults from it.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from psimap.data.frames import TRAIN_FRAMES
from psimap.panoptic.config import PanopticConfig

# TrainConfig field -> PanopticConfig field it sets (names kept: they are checkpoint config keys)
PANOPTIC_FIELDS = {"panoptic_feat_dim": "feat_dim", "panoptic_topk": "topk",
                   "lambda_ins": "w_ins", "lambda_sem": "w_sem"}


def _f(default, help: str):
    return field(default=default, metadata={"help": help})


@dataclass
class TrainConfig:
    # ---- schedule --------------------------------------------------------------------------------
    iters: int = _f(350, "optimisation steps (one random training frame per step; the cap of the "
                            "plateau rule); on the demo scene F1 rises to ~360 steps and is flat after "
                            "(benchmarks/RESULTS.md). 450 -> 350 (2026-11-24, one run each): demo F1 "
                            "0.9649 -> 0.9644, Chamfer 1.20 -> 1.24 cm; 640x480 tabletop F1 0.873 -> "
                            "0.873, PQ 0.983 -> 0.985, object F 0.916 -> 0.915 (250: 0.873 / 0.979 / "
                            "0.916); geometry steps 22 % shorter")
    seed: int = _f(0, "random seed: same seed, same result on CPU")
    deterministic: bool = _f(True, "no effect, kept so older manifests and checkpoints load: training is "
                                   "bit-reproducible on any number of threads (the native backward "
                                   "reduces per tile, then per surfel in tile order)")
    threads: int = _f(0, "native renderer threads (0 = every core this process may use); the "
                         "result does not depend on them, and torch stays on one thread")
    lowres_until: float = _f(0.3, "fraction of the steps rendered at half resolution (cheap, "
                                  "coarse geometry first)")
    log_every: int = _f(50, "steps between progress-bar / log updates")

    # ---- loss weights (paper §4.2 and 2DGS) -----------------------------------------------------
    lambda_rgb: float = _f(1.0, "lambda_1: photometric loss L_rgb")
    ssim_weight: float = _f(0.2, "lambda_s: D-SSIM share of L_rgb = (1 - s) L1 + s D-SSIM")
    lambda_depth: float = _f(1.0, "depth L1 against the observed depth (valid pixels), per metre")
    lambda_depth_median: float = _f(1.0, "depth L1 of the median depth (the surfel where transmittance "
                                          "crosses 0.5, what the mesh fuses) against the observed depth; "
                                          "the expected-depth loss alone leaves layered surfels whose "
                                          "front one is off")
    prior_noise: bool = _f(True, "the SOGMM fit knows each point's depth noise (sigma(z) estimated "
                                 "from the depth images): a patch whose residual the noise explains "
                                 "stops splitting, so noisy planes stay large, well-averaged patches")
    thing_detail: bool = _f(True, "model things finer than stuff when the frames carry masks: the "
                                  "prior splits thing points into patches a few thing spacings wide, "
                                  "things get surfels at thing_spacing_pixels (the rest of the scene "
                                  "shares what is left of the same count) and density control serves "
                                  "surfels on things first; without masks nothing changes")
    thing_spacing_pixels: float = _f(2.5, "target surfel spacing on things, in pixels at the median "
                                          "viewing distance (spacing_pixels elsewhere). Finer measured "
                                          "better (benchmarks/RESULTS.md, surfels: 2 px doubles the "
                                          "surfels on things), but below 2.5 px the test demo's scene "
                                          "(64x48) finds a box that export pins as unstable (its table "
                                          "top is fused short) and 1.5 px drops its PQ to 0.336")
    lambda_geo: float = _f(0.3, "lambda_2: L_geo, SOGMM point-to-plane distance (per metre) + "
                                "lambda_n normal alignment (the prior's patches fit the noisy points to "
                                "~1 cm; 1.0 held surfels on them and cost accuracy)")
    lambda_geo_normal: float = _f(0.1, "lambda_n: weight of 1 - |n_i . n_k| inside L_geo")
    geo_final: float = _f(0.0, "L_geo's weight at the last step, as a fraction of lambda_geo (linear "
                               "schedule; 1 = constant). 0: the prior guides early and the depth refines "
                               "last; on the demo scenes (seeds 0 / 1) Chamfer-L1 1.292 -> 1.282 and "
                               "3.679 -> 3.672 cm, F1 0.9650 -> 0.9653 and 0.9322 -> 0.9328")
    lambda_iso: float = _f(0.05, "lambda_5: L_iso = ((s1 - s2) / spacing)^2, anisotropy penalty "
                                 "(scales in units of the initial surfel spacing)")
    lambda_normal: float = _f(0.05, "2DGS normal consistency: rendered normal vs normal of the "
                                    "rendered depth")
    lambda_dist: float = _f(0.0, "2DGS depth distortion (concentrates blending weights along a ray)")
    regularize_from: float = _f(0.2, "fraction of the steps after which normal consistency and "
                                     "distortion switch on (they need a roughly placed surface)")
    use_prior: bool = _f(True, "initialise from and regularise with the SOGMM prior; False = the "
                               "plain-2DGS baseline (points + kNN scales, no L_geo)")

    # ---- learning rates (positions scale with the scene extent) --------------------------------
    lr_means: float = _f(2e-4, "position step, in units of the scene extent (decays exponentially to "
                                "trainer.MEANS_LR_END of it by the last step)")
    lr_quats: float = _f(2e-3, "rotation (quaternion) step")
    lr_scales: float = _f(5e-3, "log-scale step")
    lr_opacity: float = _f(5e-2, "opacity-logit step")
    lr_colors: float = _f(5e-2, "colour-logit step")

    # ---- adaptive density control -----------------------------------------------------------------
    densify_from: float = _f(0.1, "fraction of steps before the first densification")
    densify_until: float = _f(0.7, "fraction of steps after which the surfel set is frozen")
    densify_every: int = _f(100, "steps between densification rounds")
    grad_threshold: float = _f(2e-4, "mean screen-space position gradient in NDC units (as 3DGS / "
                                     "2DGS) that marks a surfel under-fitting: clone it if small, "
                                     "split it if large")
    split_scale: float = _f(2.0, "a surfel is 'large' (split, not cloned) beyond this many initial "
                                 "spacings")
    prune_opacity: float = _f(0.05, "prune surfels whose opacity falls below this")
    prune_scale: float = _f(0.1, "prune surfels larger than this fraction of the scene extent")
    budget_factor: float = _f(1.5, "surfel budget = this x the count that covers the prior's area at "
                                   "the target spacing (2.0 cost 1/3 more time for Chamfer 1.62 vs "
                                   "1.66 cm on the demo scene)")
    distance_spacing: bool = _f(True, "surfel spacing per prior component from its own points' viewing "
                                     "distance (spacing_pixels footprints there; a far wall coarser than a "
                                     "near table), large planar stuff stuff_spacing_factor coarser; False: "
                                     "one spacing at the median depth for all. On by default since "
                                     "2026-11-28 (#20; False -> True, benchmarks/RESULTS.md end_to_end): "
                                     "tabletop 129k -> 52k surfels, train 88 -> 60 s, F1 0.872 -> 0.874, PQ "
                                     "0.984 -> 0.984; room 136k -> 56k, train 74 -> 61 s, PQ 0.924 -> 0.929; "
                                     "demo PQ 0.773 -> 0.815 (mean of seeds 0-2; the 0.869 -> 0.818 that kept "
                                     "it off was one run inside the demo's seed-to-seed spread)")
    stuff_spacing_factor: float = _f(2.0, "large planar stuff (components off things whose shorter side spans "
                                          "trainer.LARGE_PLANE_SPACINGS spacings: walls, floor, ceiling) is "
                                          "spaced this many times coarser (1 = no change)")
    max_surfels: int = _f(200_000, "cap on the surfel budget on any capture (initial surfels: this / "
                                   "budget_factor; the spacing is raised to fit, and logged). Training costs "
                                   "about 1.5 us of CPU per surfel and step and ~3.5 kB per surfel: 200k "
                                   "surfels is ~2.5 min and ~0.7 GB for 450 steps; 0 = no cap")
    plateau_window: int = _f(50, "end the geometry steps when the frames' loss improved less than "
                                 "plateau_tol over the last this-many steps (checked every window once "
                                 "density control has settled); iters stays the cap; 0 = always run iters")
    plateau_tol: float = _f(0.03, "relative gain of the frames' loss over one plateau_window below which the "
                                  "geometry steps end (the decaying step size keeps the loss falling ~2 percent per "
                                  "25 steps on a fitted toy scene, with no gain in F1)")
    spacing_pixels: float = _f(3.0, "target surfel spacing in pixels at the median viewing distance "
                                    "(finer detail cannot be seen by the training views)")

    # ---- panoptic field (paper §4), trained jointly with geometry after densification ------------
    panoptic: bool = _f(True, "train the panoptic field when the frames carry semantic / instance "
                              "pseudo-labels")
    panoptic_iters: int = _f(400, "panoptic-field steps after the geometry schedule, on its frozen "
                                  "surfel set (geometry keeps training only with panoptic_geometry)")
    lambda_ins: float = _f(PanopticConfig.w_ins, "lambda_3: L_ins, Dice + BCE of Hungarian-matched "
                                                 "query masks")
    lambda_sem: float = _f(PanopticConfig.w_sem, "lambda_4: L_sem, cross-entropy of the rendered "
                                                 "semantic logits")
    panoptic_topk: int = _f(PanopticConfig.topk, "Top-K hard selection: features blend over the K "
                                                 "largest weights")
    panoptic_feat_dim: int = _f(PanopticConfig.feat_dim, "instance feature size per surfel and query")
    panoptic_geometry: bool = _f(False, "panoptic losses also move geometry in the panoptic steps "
                                        "(on the demo scene joint updates lowered F1@5cm from 0.950 to "
                                        "0.843 and PQ too; see benchmarks/RESULTS.md)")

    # ---- data -----------------------------------------------------------------------------------
    max_frames: int = _f(TRAIN_FRAMES, "use at most this many frames (evenly spaced; `psimap segment` "
                                       "labels these by default)")
    max_width: int = _f(320, "train at most this image width (larger frames are block-averaged "
                              "down by an integer factor)")
    max_depth: float = _f(0.0, "ignore observed depth beyond this (m); 0 = keep all")
    lidar: bool = _f(True, "use the LiDAR sweeps the frames carry (lidar_file_path): prior input and "
                           "a range term; frames without depth images then still train colour")
    lambda_range: float = _f(1.0, "LiDAR range term: L1 of rendered vs measured depth at each return "
                                  "(per metre), each return weighted by the depth-image noise at its "
                                  "range / the LiDAR noise (psimap.train.lidar.range_weight)")
    lidar_every: int = _f(2, "render one LiDAR view for the range term every this many steps (a view "
                             "costs about half a 160x120 frame: most of a render's cost is the surfels "
                             "a 90-degree view sees)")

    def to_dict(self) -> dict:
        return asdict(self)

    def panoptic_config(self) -> PanopticConfig:
        """The panoptic field's settings: PanopticConfig defaults with this config's overrides."""
        return PanopticConfig(**{p: getattr(self, t) for t, p in PANOPTIC_FIELDS.items()})
