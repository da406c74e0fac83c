"""Training the panoptic field (paper §4.2): the one training loop.

`psimap train` runs it after its geometry schedule, on the trained surfels
(`psimap.train.trainer`); `fit_panoptic` runs it on fixed surfels given by the caller (the
benchmark's ground-truth geometry, the tests). Each step takes one random labelled view, renders
the surfels it sees with the field's features, matches the queries to the view's 2D masks
(`PanopticField.losses`), steps the field and, on the field's schedule, drops useless and
duplicate queries. A step whose loss or gradient is NaN / inf is skipped (`psimap.nonfinite`).

Training on a frozen surfel set means densification never has to remap the per-surfel features,
and the queries are initialised from masks back-projected onto settled geometry.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from psimap import PsimapError
from psimap.data.frames import DepthSized
from psimap.nonfinite import NonFiniteGuard, backward_if_finite
from psimap.panoptic.config import PanopticConfig
from psimap.panoptic.field import PanopticField, init_queries
from psimap.render.api import project
from psimap.render.project import CHI, R_LOWPASS


@dataclass
class View(DepthSized):
    """One frame as the loop reads it: depth [H, W] float32 metres (0 = invalid), K [3, 3] float32,
    c2w [4, 4] float64 numpy (OpenCV), viewmat [4, 4] float32 world-to-camera, semantic / instance
    [H, W] long per-frame pseudo-labels (0 = none) or None. psimap.train's TrainFrame is a View
    with a colour image."""

    name: str
    depth: torch.Tensor
    K: torch.Tensor
    c2w: np.ndarray
    viewmat: torch.Tensor
    semantic: torch.Tensor | None = None
    instance: torch.Tensor | None = None


def view_of(frame) -> View:
    """The View of a psimap.data Frame (numpy arrays)."""
    def labels(a):
        return None if a is None else torch.as_tensor(np.asarray(a, dtype=np.int64))

    return View(name=frame.name, depth=torch.as_tensor(np.asarray(frame.depth, dtype=np.float32)),
                K=torch.as_tensor(frame.K, dtype=torch.float32), c2w=np.asarray(frame.c2w, np.float64),
                viewmat=torch.as_tensor(np.linalg.inv(frame.c2w), dtype=torch.float32),
                semantic=labels(frame.semantic), instance=labels(frame.instance))


def labelled(views) -> list:
    """The views that carry semantic or instance pseudo-labels (the others cannot supervise)."""
    return [v for v in views if v.instance is not None or v.semantic is not None]


@dataclass
class JointGeometry:
    """Surfel geometry optimised together with the field (TrainConfig.panoptic_geometry): the
    panoptic losses then reach it through the Top-K blending weights, next to its own losses."""

    params: dict            # {name: leaf tensor} the optimizer steps; their gradients must be finite
    terms: Callable         # view -> {name: weighted scalar loss tensor} of the geometry
    optimizer: torch.optim.Optimizer


def visible_surfels(means, quats, scales, opacities, w2c, K, width, height, near=0.2, far=1000.0):
    """Indices [V] of surfels whose 3-sigma footprint touches the image (the frustum-local set).

    means [N, 3], quats [N, 4] unit, scales [N, 2], opacities [N]; near / far: the renderer's
    default clip planes."""
    with torch.no_grad():
        p = project(means, quats, scales, opacities, w2c.to(means.dtype), K.to(means.dtype), width, height,
                    near, far)
        box = p.box_precise
        hit = p.valid & (box[:, 2] > box[:, 0]) & (box[:, 3] > box[:, 1])
    return torch.nonzero(hit).flatten()


def frustum_candidates(means, scales, w2c, K, width, height, near=0.2, far=1000.0,
                       margin_px: float = R_LOWPASS + 5.0):
    """Indices [V'] of a superset of `visible_surfels`: the surfels whose centre depth is in (near,
    far] and whose 3-sigma disk (inside the sphere of radius CHI x its larger scale) is not wholly
    outside one side of the image grown by margin_px (more than the low-pass radius and box slack
    that grow a surfel's pixel box), or reaches behind the camera plane (its box is then the whole
    image). No projection: ~6 ms where projecting every surfel took ~11 ms a room view, and the
    Top-K kernel culls the rest exactly as the projection would (a frozen blend is the same from
    either set). means [N, 3], scales [N, 2], w2c [4, 4], K [3, 3]."""
    with torch.no_grad():
        m = means.detach().double()
        w2c, K = w2c.double(), K.double()
        pc = m @ w2c[:3, :3].T + w2c[:3, 3]
        z = pc[:, 2]
        radius = CHI * scales.detach().double().abs().max(-1).values
        keep = (z > near) & (z <= far)
        crossing = keep & (z <= radius)
        u, v = K[0], K[1]
        inward = torch.stack([torch.stack([u[0], u[1], u[2] + margin_px]),
                              torch.stack([-u[0], -u[1], width + margin_px - u[2]]),
                              torch.stack([v[0], v[1], v[2] + margin_px]),
                              torch.stack([-v[0], -v[1], height + margin_px - v[2]])])       # [4, 3]
        inward = inward / inward.norm(dim=-1, keepdim=True)
        inside = ((pc @ inward.T) >= -radius[:, None]).all(-1)
        return torch.nonzero((keep & inside) | crossing).flatten()


# Frozen geometry blends the same surfels with the same weights at every step: each view's Top-K
# feature render is then one sparse matrix, kept while they fit this many bytes (up to 8 slots x 12
# bytes per pixel: ~7 MB for a 320x240 view); the other views are rasterized each step as before.
BLEND_CACHE_BYTES = 1 << 30


class BlendBuilder:
    """The frozen blends of the views, built on a second thread in the order the steps first read
    them, while the steps run on the first: the steps use one core (psimap.train's panoptic phase
    and fit_panoptic run torch on one thread), and building a view's blend (frustum_candidates,
    frozen_blend; the native kernel releases the GIL) took ~25 ms of every first step on a 320x240
    view, ~90 ms on a 640x480 one. The same blends in the same order, so the cache budget
    (BLEND_CACHE_BYTES) drops the same views: those past it come back None."""

    def __init__(self, views, first_use, geometry, topk: int, budget: int = BLEND_CACHE_BYTES):
        from concurrent.futures import ThreadPoolExecutor

        self._views, self._geometry, self._topk = views, geometry, int(topk)
        self._budget, self._bytes = int(budget), 0
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="psimap-blend")
        self._futures = {int(i): self._pool.submit(self._build, int(i)) for i in first_use}

    def _build(self, i: int) -> FrozenBlend | None:
        if self._bytes >= self._budget:
            return None
        means, quats, scales, opac = self._geometry
        fr = self._views[i]
        near = frustum_candidates(means, scales, fr.viewmat, fr.K, fr.width, fr.height)
        blend = frozen_blend(means, quats, scales, opac, near, fr.viewmat, fr.K, fr.width, fr.height,
                             self._topk)
        self._bytes += blend.nbytes if blend is not None else 0
        return blend

    def get(self, i: int) -> FrozenBlend | None:
        """View i's blend (waits for it; re-raises what building it raised)."""
        return self._futures[int(i)].result()

    def close(self) -> None:
        """Drop the blends not begun (the steps settled before reading their views)."""
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> "BlendBuilder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _RowBlend(torch.autograd.Function):
    """features [R, C] = A [R, V] @ f [V, C] with A a scipy CSR matrix (float32): on the native
    module's lanes (render.native.blend_rows, the same sums as scipy's product in the same order,
    bit for bit; 20k rows x 8 entries: 93 columns 2.5 -> 1.1 ms, 16 columns 0.43 -> 0.16 ms), scipy's
    where it is not built. The backward multiplies by the transpose in scipy (CSC: no transposed
    copy is built; on the lanes the scatter into random surfel rows took as long). scipy's
    products ran ~2x torch's sparse CSR ones here, and a CSR's row selection is a cheap slice."""

    @staticmethod
    def forward(ctx, f, A):
        ctx.A = A
        ctx.native = f.dtype == torch.float32 and A.dtype == np.float32 and A.shape[1] < 2 ** 31   # int32 columns
        if ctx.native:
            from psimap.render.api import native_available

            ctx.native = native_available()
        if ctx.native:
            from psimap.render.native import blend_rows

            return blend_rows(A, f)
        return torch.from_numpy(A @ f.detach().contiguous().numpy())

    @staticmethod
    def backward(ctx, v_features):
        return torch.from_numpy(np.ascontiguousarray(ctx.A.T @ v_features.contiguous().numpy())), None


@dataclass
class FrozenBlend:
    """One view's Top-K feature blending on frozen geometry: rendered features = A @ f for per-surfel
    features f [V, C] of the surfels `visible` [V] that some pixel's Top-K blends (the others of the
    frustum are hidden: they receive no gradient and are left out of the step). A [H*W, V] is a
    float32 scipy CSR matrix, alpha [H, W]."""

    A: object
    alpha: torch.Tensor
    visible: torch.Tensor        # [V] long surfel indices
    nbytes: int
    rows: torch.Tensor | None = None   # [R] ascending flat pixel indices of A's rows; None: every pixel

    def render(self, blocks: list) -> "BlendedPixels":
        """Feature blocks [V, C_i] -> the view's render of each, evaluated at the pixels asked for
        (differentiable in the blocks)."""
        return BlendedPixels(self, list(blocks))

    def at_pixels(self, rows: torch.Tensor) -> "FrozenBlend":
        """The blend of only the pixels rows [R] (ascending flat indices) over only the surfels they
        blend: a step that reads a few tiles of the view then gathers, attends and scatters those
        surfels, not all the view's (PanopticConfig.sample_tile)."""
        import scipy.sparse

        sub = self.A[rows.numpy()]
        cols = sub.indices
        mark = np.zeros(self.A.shape[1], dtype=bool)
        mark[cols] = True
        used = np.flatnonzero(mark)
        column = np.cumsum(mark, dtype=np.int64) - 1          # old column -> new, for the used ones
        A = scipy.sparse.csr_matrix((sub.data, column[cols].astype(cols.dtype), sub.indptr),
                                    shape=(sub.shape[0], used.size))
        return FrozenBlend(A=A, alpha=self.alpha.reshape(-1)[rows], visible=self.visible[torch.from_numpy(used)],
                           nbytes=0, rows=rows)


@dataclass
class BlendedPixels:
    """A frozen blend's render of feature blocks [V, C_i]: `at(rows)` computes only the pixel rows a
    step reads. One product per block: slicing one [R, sum C_i] render into the query and class
    columns cost each step two [R, sum C_i] zero-filled gradients and their copies in the backward
    (~4 ms of a 160x120 step at 85 queries). `columns(b, cols)` renders some columns of block b
    again on the rows of the last `at` (the matched queries: see PanopticField.losses)."""

    blend: FrozenBlend
    blocks: list
    _A: object = None               # A at the rows of the last `at`

    def at(self, rows: torch.Tensor | None, detach: tuple = ()) -> tuple[list, torch.Tensor]:
        """([features [R, C_i] per block], alpha [R]) at flat pixel indices rows [R]; None: every
        pixel in order (every pixel the blend holds, for one made by `at_pixels`). detach: indices
        of blocks rendered without a gradient (their values only)."""
        alpha = self.blend.alpha.reshape(-1)
        A = self.blend.A
        if rows is not None and self.blend.rows is not None:
            held = self.blend.rows
            if rows.numel() == held.numel() and torch.equal(rows, held):
                rows = None
            else:
                local = torch.searchsorted(held, rows).clamp_max(held.numel() - 1)
                if not bool((held[local] == rows).all()):
                    raise ValueError("BlendedPixels.at: a pixel outside the rows this blend holds")
                rows = local
        if rows is not None:
            A, alpha = A[rows.numpy()], alpha[rows]
        self._A = A
        return [_RowBlend.apply(f.detach() if b in detach else f, A) for b, f in enumerate(self.blocks)], alpha

    def columns(self, block: int, cols: torch.Tensor) -> torch.Tensor:
        """[R, len(cols)] the columns cols [C'] (long) of block `block`, rendered on the rows of the
        last `at` with their gradient: the same numbers as those columns of `at`'s render (each
        column's sums are its own)."""
        if self._A is None:
            raise ValueError("BlendedPixels.columns: call at() first")
        # index_select: the column indexing's backward (an accumulating scatter) took ~4x as long
        return _RowBlend.apply(self.blocks[block].index_select(1, cols), self._A)


def frozen_blend(means, quats, scales, opacities, visible, w2c, K, width, height, topk: int,
                 near=0.2, far=1000.0) -> FrozenBlend | None:
    """The FrozenBlend of a view whose frustum holds the surfels `visible` [V] (indices into means
    [N, 3] ...), or None where the native renderer is not built, Top-K is off or no pixel is covered
    (then every step rasterizes)."""
    import scipy.sparse

    from psimap.render.api import native_available

    if not (native_available() and means.device.type == "cpu" and topk):
        return None
    from psimap.render.native import MAX_TOPK, topk_weights

    if topk > MAX_TOPK:
        return None
    with torch.no_grad():
        idx = visible
        p = project(means[idx], quats[idx], scales[idx], opacities[idx], w2c.to(means.dtype),
                    K.to(means.dtype), width, height, near, far)
        ids, w, alpha = topk_weights(p, opacities[idx].float(), width, height, int(topk), near=near, far=far)
    # in numpy: torch's boolean-mask selections over the H x W x K slots took 12-18 ms of a 320x240
    # view (the room's 48 frozen blends: 1.65 -> 1.08 s with the two changes below)
    ids, w = ids.numpy().reshape(-1, ids.shape[-1]), w.numpy().reshape(-1, w.shape[-1])
    keep = ids >= 0
    if bool(keep.all()):                # every pixel holds K surfels (the usual case): no selection
        slots, vals, counts = ids.ravel(), w.ravel(), np.full(ids.shape[0], ids.shape[1], np.int64)
    else:
        slots, vals, counts = ids[keep], w[keep], keep.sum(1)
    if slots.size == 0:
        return None
    # slots pixel-major, as CSR rows want them (a row in Top-K order: matmul needs no sort);
    # columns: the blended surfels only, numbered in index order (a mark and a cumulative count)
    mark = np.zeros(int(idx.numel()), dtype=bool)
    mark[slots] = True
    used = np.flatnonzero(mark)
    v = int(used.size)
    # int32 indices where they fit, as scipy keeps them: int64 ones it checks and casts down,
    # ~20-60 ms of a 640x480 view
    index = np.int32 if vals.size < np.iinfo(np.int32).max else np.int64
    column = (np.cumsum(mark) - 1).astype(index)
    indptr = np.zeros(ids.shape[0] + 1, index)
    np.cumsum(counts, out=indptr[1:])
    A = scipy.sparse.csr_matrix((vals, column[slots], indptr), shape=(ids.shape[0], v))
    nbytes = int(vals.size) * 12 + 8 * int(alpha.numel())
    used = torch.from_numpy(used)
    return FrozenBlend(A=A, alpha=alpha.to(means.dtype), visible=idx[used], nbytes=nbytes)


def segment_change(prev: torch.Tensor, now: torch.Tensor, min_size: int, ignore: int | None = None) -> float:
    """Largest share of one segment's surfels that changed between two labellings [N] (codes):
    per label L, |prev == L xor now == L| / max(|prev == L|, |now == L|), over the labels with at
    least min_size surfels in either, but `ignore`. A segment that appears, vanishes or shrinks
    counts in full, however few surfels it has next to the scene (panoptic quality counts
    segments, not surfels)."""
    codes = torch.cat([prev, now]).unique()
    k = codes.numel()
    a = torch.searchsorted(codes, prev)
    b = torch.searchsorted(codes, now)
    size_a = torch.bincount(a, minlength=k).float()
    size_b = torch.bincount(b, minlength=k).float()
    moved = prev != now
    out_a = torch.bincount(a[moved], minlength=k).float()      # left label a
    in_b = torch.bincount(b[moved], minlength=k).float()       # joined label b
    big = torch.maximum(size_a, size_b)
    ok = big >= max(1, int(min_size))
    if ignore is not None:
        ok &= codes != ignore
    if not bool(ok.any()):
        return 0.0
    return float(((out_a + in_b)[ok] / big[ok]).max())


# A stuff class segment has settled when fewer than this share of its surfels changed class over a
# period (classes too small to be kept, PanopticConfig.min_stuff_share, do not count)
SETTLE_CLASS_TOL = 0.05
# Settled periods in a row before the steps end: a query the useless / duplicate rules drop later
# can sit through one calm period (tabletop with merged initial queries, one of three view orders:
# 6 instances for 5 objects when stopping after the first calm period)
SETTLE_PERIODS = 2
# Masks that disagree between views (a model-free segmenter's on a real capture: a desk cut in
# two in one view, whole in the next) leave a floor of churn far above the tolerance: the borders
# between large segments follow whichever view was drawn last. On 20 frames of 7-Scenes chess,
# labelled by `psimap segment`, 12.4, 8.9, 7.6, 6.9, 6.7, 6.1, 5.3 % of the thing surfels changed
# owner at steps 120-480, and the instances at each step agreed with those 60 steps later only
# to segment PQ 0.73-0.74 at 240, 300 and 360: the segmentation drifts, it does not converge. On
# the generated rooms with such labels the scene PQ at 240 / 300 / 360 / 400 steps was 0.350 /
# 0.312 / 0.358 / 0.352. Such labels "wander": over the last SETTLE_PERIODS periods more than
# WANDER_FLOOR x the tolerance changed in every one, and the churn fell by less than WANDER_FALL a
# period (compounded: now above (1 - WANDER_FALL)^SETTLE_PERIODS of the churn SETTLE_PERIODS periods
# before), which ends the steps too. The window, not each period alone: a churn that falls a little,
# then rises a little, then falls a little has stopped falling just as well (7-Scenes chess in a
# later run: 12.3, 8.2, 7.5, 8.4, 7.8 % and 12.6, 10.8, 8.1, 8.4, 7.2 % ran to the 400-step cap
# when a rise reset the count; it ends at 300 / 240 now). A churn rising through the whole window
# is no such sign: labels still reorganising (the two-box test scene: 0.9, 1.9, 2.7, 5.2, 2.1,
# 1.7, 0 %). The floor keeps the rule away from consistent masks whose churn passes through a few %
# on its way below the tolerance (generated captures, exact masks: a tabletop 10.2, 5.2, 4.5, 3.6,
# 1.6 %; a room view order 3.1, 1.1, 4.6, 4.6, 0.4 %), where the real capture's stayed at 6.9-12 %
WANDER_FLOOR = 3.0
WANDER_FALL = 0.2


class LabelSettle:
    """The panoptic steps' stop rule (PanopticConfig.settle_tol): at each adjustment step, compare
    the labels (PanopticField.current_labels) with the previous adjustment step's. Settled when
    fewer than `tol` of the thing surfels changed owner (a query named by its lifelong id) and no
    stuff class segment changed by SETTLE_CLASS_TOL of its surfels (segment_change): a stray stuff
    class, still shrinking, is a false segment in every view that sees it. Thing classes do not
    count: an instance takes the class of the masks its query was matched to
    (PanopticConfig.query_class), whatever its surfels' argmax says. Queries spawned or dropped
    count by the surfels they take or leave: one spawned for a noisy mask and dropped as useless a
    period later, owning nothing meanwhile, changes no label (the rule once required no query
    change at all, and such churn kept a tabletop and a room view order training 60 steps past
    labels that no longer moved; the same PQ in all 9 runs of 3 captures x 3 view orders, within
    0.001 in 4 more demo orders). The loss is no signal: it keeps falling ~10 % per period long
    after the labels settle. Small objects are not seen by the rule: the demo's 10-30-surfel
    instances swap 30-150 % of their surfels every period, whenever the steps end.

    The steps also end when the labels wander instead of settling (masks that disagree between
    views; WANDER_FLOOR says how that was measured): over the last `periods` periods (`wandering`)
    more than WANDER_FLOOR x tol of the thing surfels changed owner in each one and in the one
    before them, the churn fell by less than WANDER_FALL a period, compounded, without rising
    through all of them, and no stuff class changed by SETTLE_CLASS_TOL.
    `reason` says which rule ended the steps ("settled" or "wandering")."""

    def __init__(self, tol: float, min_stuff_share: float = 0.0, periods: int = SETTLE_PERIODS):
        self.tol = float(tol)
        self.min_stuff_share = float(min_stuff_share)
        self.periods = int(periods)
        self.calm = 0                       # settled periods in a row
        self.reason = ""
        self.prev: tuple[torch.Tensor, torch.Tensor] | None = None
        self.history: list[dict] = []

    def settled(self, field, means: torch.Tensor) -> bool:
        sem, inst = field.current_labels(means)
        classes, owners = 1.0, 1.0
        if self.prev is not None:
            classes = 0.0
            if field.class_thing.numel():
                thing_p, thing_c = field.class_thing[self.prev[0]], field.class_thing[sem]
                stuff = ~thing_p | ~thing_c
                # every thing class one code, left out: among the stuff surfels a thing class holds
                # only those that left or joined a stuff class, all of them changed (the tabletop's
                # table: ~80 such surfels, "194 % changed", kept three periods from being calm);
                # the stuff segment they left or joined counts them against its own size
                if bool(stuff.any()):
                    classes = segment_change(torch.where(thing_p, -1, self.prev[0])[stuff],
                                             torch.where(thing_c, -1, sem)[stuff],
                                             max(10, int(self.min_stuff_share * sem.numel())), ignore=-1)
            thing = (inst > 0) | (self.prev[1] > 0)
            owners = float((inst != self.prev[1])[thing].float().mean()) if bool(thing.any()) else 0.0
        self.history.append({"step": int(field.steps), "classes_changed": classes,
                             "instances_changed": owners, "queries": int(field.queries.count)})
        compared = self.tol > 0 and self.prev is not None
        calm = compared and owners < self.tol and classes < SETTLE_CLASS_TOL
        self.prev = (sem, inst)
        self.calm = self.calm + 1 if calm else 0
        self.reason = "settled" if self.calm >= self.periods else "wandering" if compared and self.wandering() else ""
        return bool(self.reason)

    @property
    def changes(self) -> list[tuple[float, float]]:
        """(share of thing surfels that changed owner, largest stuff segment change) of each
        compared period: the history after its first entry (nothing compared with tol 0)."""
        if self.tol <= 0:
            return []
        return [(h["instances_changed"], h["classes_changed"]) for h in self.history[1:]]

    def wandering(self) -> bool:
        """Whether the last `periods` periods wandered (WANDER_FLOOR): the churn above the floor
        in each of them and in the one before, falling by less than WANDER_FALL a period over them
        and not rising through all of them, and no stuff class changing by SETTLE_CLASS_TOL."""
        window = self.changes[-(self.periods + 1):]
        if self.periods < 1 or len(window) <= self.periods:
            return False
        churn = [c for c, _ in window]
        rising = all(b > a for a, b in zip(churn, churn[1:]))
        return (min(churn) > WANDER_FLOOR * self.tol and all(c < SETTLE_CLASS_TOL for _, c in window[1:])
                and churn[-1] > (1.0 - WANDER_FALL) ** self.periods * churn[0] and not rising)


def lift_semantic_start(field: PanopticField, means: torch.Tensor, views) -> float:
    """Start the field's semantic logits from the views' class votes (psimap.panoptic.lift);
    returns the share of the surfels some view voted on (the others keep the uniform start)."""
    from psimap.panoptic.field import id_to_column
    from psimap.panoptic.lift import lifted_class_votes, vote_logits

    s = field.class_ids.numel()
    if s == 0 or means.shape[0] == 0:
        return 0.0
    columns = [None if fr.semantic is None else id_to_column(field.class_ids, fr.semantic.reshape(-1))
               for fr in views]
    votes = lifted_class_votes(means, views, columns, s)
    with torch.no_grad():
        field.semantic.copy_(vote_logits(votes))
    return float((votes.sum(-1) > 0).float().mean())


def train_field(views, classes, cfg: PanopticConfig, surfels: Callable, *, iters: int, scene_scale: float,
                rng: np.random.Generator, generator: torch.Generator, joint: JointGeometry | None = None,
                backend: str = "auto", log=None, progress: bool = False,
                log_every: int = 50, frozen: bool = True) -> tuple[dict, dict]:
    """Train a new panoptic field on `views`; returns (PanopticField.state_for_checkpoint, metrics).

    views: Views (TrainFrames); those without labels are left out. surfels() -> (means [N, 3],
    quats [N, 4] unit, scales [N, 2], opacities [N], colors [N, 3]): the geometry the field is
    rendered with, read once when it is fixed (`joint` None) and every step when `joint` moves
    it. scene_scale: the scene extent (m) for the queries' positional encoding. rng draws the
    order of the views; generator every torch draw (query init, pixel samples): one seed, one
    result. Raises PsimapError when no view is labelled, Diverged when steps keep being NaN / inf.
    frozen: with fixed geometry (`joint` None) and backend "auto", each view's feature render is
    computed once as a sparse blend (frozen_blend) and every later step is a sparse matrix product;
    False rasterizes every step (the same numbers up to float rounding).
    """
    from concurrent.futures import ThreadPoolExecutor
    from contextlib import nullcontext

    from tqdm import tqdm

    from psimap.render import rasterize

    log = log or (lambda msg: None)
    t0 = time.perf_counter()
    frozen = frozen and backend in ("auto", "native")
    train_views = labelled(views)
    if not train_views:
        raise PsimapError("no frame has semantic or instance pseudo-labels: nothing to train the "
                          "panoptic field on")
    queries = init_queries(train_views, classes, cfg, scene_scale=scene_scale, generator=generator)
    means, quats, scales, opac, colors = surfels()
    n = int(means.shape[0])
    field = PanopticField(n, classes, queries, cfg, generator=generator)
    q0 = queries.count
    log(f"panoptic: {q0} initial queries from {min(cfg.init_frames, len(train_views))} frames, "
        f"{len(classes)} classes")
    visible: dict[int, torch.Tensor] = {}        # per view without a blend, while the geometry is fixed
    frame_labels: dict = {}                       # per view: PanopticField.frame_labels
    guard, removed_total = NonFiniteGuard(), 0
    settle = LabelSettle(cfg.settle_tol, cfg.min_stuff_share)
    steps_done, stop = iters, "cap"
    order = rng.integers(0, len(train_views), size=iters)
    builder = None
    if joint is None and frozen and iters > 0:
        _, first = np.unique(order, return_index=True)
        builder = BlendBuilder(train_views, order[np.sort(first)],
                               tuple(t.detach() for t in (means, quats, scales, opac)), cfg.topk)
    # the surfel features' optimizer steps (PanopticField.step); torch on one thread there too (a
    # new thread starts with OpenMP's default count, every core)
    background = ThreadPoolExecutor(max_workers=1, thread_name_prefix="psimap-adam",
                                    initializer=torch.set_num_threads, initargs=(1,))
    with background, builder or nullcontext(), tqdm(total=iters, desc="panoptic", disable=not progress,
                                                    dynamic_ncols=True) as bar:
        if joint is None:
            field.fix_positions(means)
        if cfg.lift_semantic:       # here: the first blends build meanwhile (~0.5 s on a 136k-surfel room)
            seen = lift_semantic_start(field, means.detach(), train_views)
            log(f"panoptic: semantic start from the views' class votes ({seen * 100:.0f} % of the surfels seen)")
        for step in range(iters):
            i = int(order[step])
            fr = train_views[i]
            if joint is not None:
                means, quats, scales, opac, colors = surfels()
            # the builder keeps each view's blend (None: past the cache budget, or no native kernel)
            blend = builder.get(i) if builder is not None else None
            vis = blend.visible if blend is not None else visible.get(i)
            if vis is None:
                vis = visible_surfels(means.detach(), quats.detach(), scales.detach(), opac.detach(),
                                      fr.viewmat, fr.K, fr.width, fr.height)
                if joint is None:
                    visible[i] = vis

            # the geometry's terms first: they draw from `generator` before the field does
            terms = joint.terms(fr) if joint is not None else {}
            if i not in frame_labels:
                frame_labels[i] = field.frame_labels(fr.instance, fr.semantic)
            pix = field.sample_pixels(fr.width, fr.height, frame_labels[i], generator)
            if blend is not None and pix is not None and cfg.sample_tile > 0:
                blend = blend.at_pixels(pix)   # only the surfels the sampled tiles blend take part
            if blend is not None:
                vis = blend.visible
            field.zero_grad()                  # after the sampling: joins the last surfel step

            def render(idx, blocks, topk, fr=fr, means=means, quats=quats, scales=scales, opac=opac,
                       colors=colors, blend=blend):
                if blend is not None and topk == cfg.topk:
                    return blend.render(blocks)
                return rasterize(means[idx], quats[idx], scales[idx], opac[idx], colors[idx],
                                 fr.viewmat, fr.K, fr.width, fr.height, features=torch.cat(blocks, -1),
                                 topk=topk, backend=backend)

            l_ins, l_sem, _ = field.losses(render, means, vis, fr.instance, fr.semantic, fr.K,
                                           fr.viewmat, fr.width, fr.height, generator=generator,
                                           depth=fr.depth, labels=frame_labels[i], pixels=pix)
            terms["ins"], terms["sem"] = l_ins, l_sem
            checked = {**(joint.params if joint is not None else {}),
                       "semantic": field.semantic, "instance": field.instance}
            bad = backward_if_finite(terms, checked)
            if bad is not None:
                field.zero_grad()
                if joint is not None:
                    joint.optimizer.zero_grad(set_to_none=True)
                guard.skip(bad, f"panoptic training diverged at step {step} (frame {fr.name})")
                continue
            guard.ok()
            # the surfel features' Adam (every surfel: ~2-3 ms of a room step) runs on the second core
            # while the next step draws its pixels and cuts its blend; the same operations on the
            # same numbers, so the same field
            field.step(background if joint is None else None)
            if joint is not None:
                joint.optimizer.step()
                joint.optimizer.zero_grad(set_to_none=True)
            removed = field.maybe_adjust(means.detach())
            removed_total += removed
            if removed:
                drops = ", ".join(f"{v} {k}" for k, v in field.last_drops.items() if v)
                log(f"panoptic step {step}: dropped {removed} queries ({drops}), "
                    f"{field.queries.count} left")
            if (step + 1) % log_every == 0:
                bar.set_postfix(ins=f"{float(l_ins.detach()):.3f}", sem=f"{float(l_sem.detach()):.3f}",
                                queries=field.queries.count)
            bar.update(1)
            if field.adjustment_due() and step + 1 < iters and settle.settled(field, means.detach()):
                steps_done, stop = step + 1, settle.reason
                h = settle.history[-1]
                if stop == "settled":
                    log(f"panoptic labels settled at step {step + 1}: over the last {cfg.adjust_every} steps "
                        f"{h['instances_changed'] * 100:.2f} % of the thing surfels changed instance (< "
                        f"{cfg.settle_tol * 100:g} %), no class lost or gained more than "
                        f"{h['classes_changed'] * 100:.1f} % of its surfels")
                else:
                    first = settle.changes[-(settle.periods + 1)][0]
                    log(f"panoptic labels stopped converging at step {step + 1}: over the last "
                        f"{cfg.adjust_every} steps {h['instances_changed'] * 100:.2f} % of the thing surfels "
                        f"changed instance, against {first * 100:.2f} % {settle.periods} periods of "
                        f"{cfg.adjust_every} steps before: not {WANDER_FALL * 100:g} % fewer a period. The "
                        "masks disagree between views, and more steps move the borders between instances "
                        "without settling them")
                break
    state = field.state_for_checkpoint(means.detach())
    n_inst = int(state["surfels"]["instance_id"].max()) if n else 0
    # the checkpoint keeps only the queries that own an instance at export
    q_final = int(state["queries"]["feature"].shape[0])
    metrics = {"panoptic_steps": int(steps_done), "panoptic_stop": stop,
               "panoptic_label_changes": settle.history, "panoptic_seconds": time.perf_counter() - t0,
               "queries_initial": int(q0), "queries_final": q_final,
               "queries_removed": int(removed_total), "instances": n_inst,
               "panoptic_skipped_steps": int(guard.skipped)}
    log(f"panoptic: {q_final} queries (from {q0}), {n_inst} instances, "
        f"{metrics['panoptic_seconds']:.1f} s")
    return state, metrics


def fit_panoptic(surfels: dict, frames, classes, *, iters: int = 300, cfg: PanopticConfig | None = None,
                 seed: int = 0, backend: str = "auto", progress: bool = False, log=None,
                 frozen: bool = True) -> dict:
    """Train the panoptic field on fixed geometry; returns `PanopticField.state_for_checkpoint`.
    frozen: see train_field.

    surfels: means [N, 3], quats [N, 4], scales [N, 2], opacities [N] (tensors); frames: a sequence
    of psimap.data Frames with per-frame pseudo-labels (frames without are skipped).
    """
    if not len(frames):
        raise PsimapError("fit_panoptic: no frames")
    threads = torch.get_num_threads()
    # Per-step tensors are small: torch's intra-op threads only spin-wait (measured: 40 steps took
    # 3 s on one thread, 66 s on two on a busy 2-core machine).
    torch.set_num_threads(1)
    try:
        means = surfels["means"].float()
        geometry = (means, surfels["quats"].float(), surfels["scales"].float(),
                    surfels["opacities"].float(), torch.zeros_like(means))   # no panoptic loss reads colour
        extent = float((means.max(0).values - means.min(0).values).norm()) if means.shape[0] else 1.0
        state, _ = train_field([view_of(f) for f in frames], classes, cfg or PanopticConfig(),
                               lambda: geometry, iters=iters, scene_scale=extent,
                               rng=np.random.default_rng(seed), generator=torch.Generator().manual_seed(seed),
                               backend=backend, log=log, progress=progress, frozen=frozen)
        return state
    finally:
        torch.set_num_threads(threads)
