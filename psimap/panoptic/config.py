"""Every setting of the panoptic field in one dataclass: the only place its defaults are written.

Stdlib only, so `psimap.train.config.TrainConfig` can take its panoptic defaults from here without
importing torch.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class PanopticConfig:
    feat_dim: int = 16              # instance feature size per surfel and query
    topk: int = 8                   # features blend over the K largest weights per pixel (paper §5)
    temperature: float = 0.1        # softmax temperature over query affinities
    init_frames: int = 16           # frames (spread over the sequence) whose masks seed the queries
    # masks of two of those frames share a query when each puts at least this share of the points
    # the other frame sees inside the other mask (associate.same_object_groups; one object seen
    # twice); 0 = one query per mask. Fewer initial queries (tabletop 44 -> 5, room 93 -> 24, demo
    # 85 -> 37, no group holding two objects), so cheaper first steps and an earlier settle: with
    # surfels spaced by viewing distance, over 6 / 3 / 3 view orders the demo's phase took 9.3 ->
    # 6.8 s (PQ 0.808 -> 0.811), the room's 11.9 -> 8.8 s (0.923 -> 0.931), the tabletop's 12.2 ->
    # 9.2 s (0.952 -> 0.983). (Off until 2026-11-28: on the denser surfels before, the demo lost
    # 0.02-0.05 PQ, its 5-20 px mugs and bottles going with the spare seed queries.)
    init_merge: float = 0.6
    # the semantic logits start from the labelled views' class votes on the surfels they see
    # (psimap.panoptic.lift), not from zero; False = the uniform start
    lift_semantic: bool = True
    # 2D masks smaller than this fraction of the image are ignored (5 px at 160x120: bottles and
    # balls there cover a median 7-20 px; the former 0.002 = 38 px ignored most of their masks)
    min_mask_fraction: float = 0.0003
    # pixels sampled per frame for matching and losses (all of a 160x120 frame: at 4096 a 12 px
    # mask kept ~3 pixels and its matching cost was noise)
    pixels_per_step: int = 20000
    # ... drawn as whole tiles of this many pixels a side, first the tile of a random pixel of every
    # thing mask of the frame, then random tiles: a step then reads the surfels of a few patches
    # (20k pixels in 8x8 tiles: ~42 % of a 320x240 view's blended surfels, ~25 % of a 640x480 one's)
    # where single random pixels touch ~90 % of them, and every mask is read at every step. 16 px
    # tiles touched fewer (35 / 15 %) but left a split object unmerged in one of three tabletop
    # runs. 0 = single random pixels
    sample_tile: int = 8
    w_ins: float = 1.0              # lambda_3
    w_sem: float = 1.0              # lambda_4
    lr_surfel: float = 0.02         # Adam lr of per-surfel features
    lr_query: float = 0.01          # Adam lr of queries and attention weights
    # a query's centre moves lr_query x min(1, sigma / this) a step (sigma: the geometric mean of its
    # Gaussian's axes, metres; PanopticField._step_queries): Adam's ~lr step a centre took whatever
    # its gradient drifted a mug's query (sigma 4.8 cm) 7-9 cm off its mug in 25 steps; with the
    # co-match rule (field.losses) the room kept its mug in 5 of 6 view orders, not 3 (PQ 0.889 ->
    # 0.913), the demo and tabletop unchanged (docs/architecture.md). 0 = lr_query for every query
    query_step_sigma: float = 0.1
    reject_dice: float = 0.95       # matches with Dice cost above this are not supervised
    # class term of the matching cost (0 = Dice + BCE only). Off by default: at 15 % noise (160x120,
    # seeds 0 / 1) weight 1 gave PQ 0.647 / 0.757 against 0.675 / 0.755 without it (RESULTS.md)
    w_class: float = 0.0
    adjust_start: int = 60          # first step of dynamic query adjustment
    # then every this many steps; the settle rule compares the labels at these steps. 40, not 60
    # (2026-11-29): panoptic-only over 6 view orders of the demo, tabletop and room end-to-end
    # checkpoints, 30 % fewer steps (demo 230 -> 160, tabletop 220 -> 153, room 250 -> 173 on
    # average) for the same PQ (demo 0.804 -> 0.810, tabletop 0.984 -> 0.983; room 0.905 -> 0.889,
    # its mug lost in 3 of 6 orders against 2: docs/architecture.md); more adjustments, not fewer
    # checks of one. The first adjustment stays at 60: at 40 too (adjust_start) two of six demo
    # orders fell to PQ 0.573 / 0.745 (queries of small objects dropped before their frames had
    # been drawn)
    adjust_every: int = 40
    # useless: matched in fewer of the frames that see it. Real objects' queries were matched in
    # >= 0.56 of them at 15 % noise (seeds 0-2); at 0.1 a query on a cabinet's border, matched in
    # 8 of 53 frames, survived as a false instance (seed 2: PQ 0.861 -> 0.921 at 0.3)
    min_match_rate: float = 0.3
    iom_threshold: float = 0.6      # duplicate: IoM with a larger query above this
    # 3D mask of a query for the IoM test: surfels with A(q, g) above this. (Thresholding the
    # softmax share instead collapsed two unconverged box queries into one in
    # tests/test_panoptic_field.py.)
    mask_affinity: float = 0.5
    min_instance_surfels: int = 10  # instances with fewer surfels are dropped at export
    # duplicate rule: two queries matched to two different 2D masks of one frame in at least this
    # many frames are different objects, whatever their 3D IoM (0 = off)
    distinct_frames: int = 2
    # final cleanup: a thing surfel takes the majority instance of its k nearest thing surfels
    # (argmax noise on object borders); 0 = off
    smooth_k: int = 8
    # export: a thing surfel's instance maximises p(q | g) * p(class of q | g), the instance and the
    # semantic heads combined, instead of p(q | g) alone (a mug's border surfels won by the table's
    # query but whose semantics say "mug" go to the mug)
    class_fusion: bool = True
    # an instance's class = the majority class of the 2D masks its query was matched to (a merged
    # mask goes to the larger object's query, so its class does not leak onto the smaller object,
    # whose surfels' own semantics it does drag: a mug's pixels were 49 % "table" at 15 % noise);
    # False = majority of the instance's surfels' semantic argmax
    query_class: bool = True
    spawn: bool = True              # a 2D mask that no query covers in 3D seeds a new query
    spawn_feature: bool = True      # a spawned query starts from its mask's surfels' features
    spawn_split: bool = True        # no spawn for a mask drawn mostly by a query busy with a same-class mask
    max_spawn_per_step: int = 2
    max_queries: int = 256
    # the steps end once the labels settle: at adjustment steps (adjust_every) where, twice in a
    # row, fewer than this fraction of the thing surfels changed owning query since the previous
    # one (and no stuff class segment changed by 5 %: psimap.panoptic.fit.LabelSettle); the
    # caller's step count stays the cap. They end too when over the last two periods more than
    # three times this fraction changed in each, falling by less than 20 % a period (masks that
    # disagree between views: LabelSettle, WANDER_FLOOR). 0 = always run the cap
    settle_tol: float = 0.02
    # a stuff class that holds fewer than this share of the surfels (and fewer than
    # min_instance_surfels) is label noise, a few mislabelled pixels' worth (tabletop: 18 of 128k
    # surfels "ceiling" in a room with no ceiling in view, one false segment in every view that
    # sees them): its surfels take their next most likely class
    min_stuff_share: float = 5e-4

    @property
    def query_grace(self) -> int:
        """Steps a query lives before the drop rules may judge it: what the seed queries get before
        the first adjustment (adjust_start), and at least one adjustment period. A query spawned
        for a small object seen in a few frames needs its frames drawn before it is judged useless
        or empty."""
        return max(self.adjust_start, self.adjust_every)
