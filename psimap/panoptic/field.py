"""The panoptic field (paper §4): per-surfel semantic logits and instance features, instance queries,
per-frame Hungarian supervision from noisy 2D masks, and dynamic query adjustment.

Rendering is injected: `losses(render, ...)` calls `render(idx [V], blocks, topk)` (blocks: feature
blocks [V, C_i]) which must return a RenderOutput of the visible surfels `idx`, the blocks side by
side (the caller renders them with its current, possibly learnable, geometry, so the panoptic
losses also reach geometry through the Top-K weights).
The training loop that drives the field is `psimap.panoptic.fit`.
"""
from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from psimap.panoptic.adjust import co_mask_duplicates, duplicate_queries, useless_queries
from psimap.panoptic.associate import MaskFrame, same_object_groups
from psimap.panoptic.config import PanopticConfig
from psimap.panoptic.matching import hungarian_match, mask_windows, masks_from_ids, matched_mask_loss
from psimap.panoptic.queries import InstanceQueries, init_from_points, softmax_last
from psimap.transforms import pixels_to_camera_torch, transform_points


@dataclass
class ClassScores:
    """The alpha-normalised class distribution of rendered pixels, class-major: one pass serves the
    matching's class cost and the semantic loss. z [S, P]: the logits s_px / max(alpha, 1e-3) of
    each pixel minus their maximum; p [S, P] = softmax over the classes; log_total [P] = log of the
    sum of exp(z). Class-major because a reduction over a few classes of a pixel-major [P, S] was
    the slow part: the loss's forward and backward over a 160x120 frame at 11 classes took ~5 ms
    (the log-softmax of transposed rows, its backward and the masked copies), now ~3 ms."""

    z: torch.Tensor
    p: torch.Tensor
    log_total: torch.Tensor

    @staticmethod
    def of(s_px: torch.Tensor, alpha_px: torch.Tensor) -> "ClassScores":
        """From blended logits s_px [P, S] and alpha_px [P] (values only: no gradient)."""
        p_n, s_n = s_px.shape
        with torch.no_grad():
            # a transposed copy into a class-major buffer (.contiguous() of the view took 2x)
            z = torch.empty(s_n, p_n, dtype=s_px.dtype, device=s_px.device).copy_(s_px.detach().T)
            z.div_(alpha_px.detach().clamp_min(1e-3))
            z.sub_(z.amax(0))            # amax: max(0).values with its indices took 30x as long
            p = z.exp()
            total = p.sum(0)
            p.div_(total)
            return ClassScores(z, p, total.log_())


class _SemanticNLL(torch.autograd.Function):
    """The semantic cross-entropy from ClassScores: forward the mean of log_total - z[col] over the
    pixels `ok`, backward (p - onehot(col)) / alpha on them, written out (see ClassScores)."""

    @staticmethod
    def forward(ctx, s_px, alpha_px, cols, ok, scores):
        c = torch.where(ok, cols, 0)
        n = ok.sum()
        nll = scores.log_total - scores.z.gather(0, c.unsqueeze(0)).squeeze(0)
        ctx.save_for_backward(alpha_px, ok, c, n)
        ctx.scores = scores
        return torch.where(ok, nll, 0.0).sum() / n

    @staticmethod
    def backward(ctx, v_loss):
        alpha_px, ok, c, n = ctx.saved_tensors
        scores = ctx.scores
        a = torch.where(ok, alpha_px, 1.0)                      # ok pixels: alpha > 0.5
        w = torch.where(ok, v_loss / n, 0.0) / a                # [P]
        g = scores.p.scatter_add(0, c.unsqueeze(0), torch.full_like(c, -1, dtype=scores.p.dtype).unsqueeze(0))
        off = torch.nonzero(~ok).squeeze(1)
        v_alpha = None
        if ctx.needs_input_grad[1]:
            # d/dalpha of z = s / alpha: -z / alpha; (p - onehot) sums to 0 over the classes, so
            # the shifted z gives the same sum
            v_alpha = -(g * scores.z).sum(0) * w
            v_alpha.index_fill_(0, off, 0.0)
        g.mul_(w)
        if off.numel():
            g.index_fill_(1, off, 0.0)      # a NaN of an ignored pixel times 0 is still NaN
        return torch.empty(g.shape[1], g.shape[0], dtype=g.dtype, device=g.device).copy_(g.T), v_alpha, None, None, None


def semantic_loss(s_px: torch.Tensor, alpha_px: torch.Tensor, cols: torch.Tensor,
                  scores: ClassScores | None = None) -> torch.Tensor | None:
    """Cross-entropy of the alpha-normalised blended class logits s_px [P, S] (alpha_px [P]) against
    the class columns cols [P] (-1 void) on the labelled, covered (alpha > 0.5) pixels; None when
    there is none. Over every pixel with the others ignored: the boolean selections of the logits
    and their scattered gradient cost more than the few pixels left out. A NaN logit or alpha of an
    ignored pixel stays out of the loss and the gradient. scores: ClassScores.of(s_px, alpha_px)
    when the caller has it. `semantic_loss_reference` is the readable torch form."""
    ok = (cols >= 0) & (alpha_px > 0.5)
    if not bool(ok.any()):
        return None
    return _SemanticNLL.apply(s_px, alpha_px, cols, ok, scores or ClassScores.of(s_px, alpha_px))


def semantic_loss_reference(s_px: torch.Tensor, alpha_px: torch.Tensor, cols: torch.Tensor) -> torch.Tensor | None:
    """semantic_loss in torch's own log-softmax and NLL (the tests hold the two together)."""
    ok = (cols >= 0) & (alpha_px > 0.5)
    if not bool(ok.any()):
        return None
    alpha = torch.where(ok, alpha_px, 1.0).unsqueeze(-1).clamp_min(1e-3)
    logits = torch.where(ok.unsqueeze(-1), s_px / alpha, 0.0)
    return F.nll_loss(torch.log_softmax(logits, -1), torch.where(ok, cols, -100), ignore_index=-100)


def rendered_blocks(out, rows: torch.Tensor | None, widths: list) -> tuple[list, torch.Tensor]:
    """([features [R, C_i] of each rendered block], alpha [R]) of a render at flat pixel indices
    rows [R] (None: every pixel). out: a render with `.at(rows)` giving the blocks (psimap.panoptic.fit's
    frozen blend, which computes only those rows) or a RenderOutput of the blocks side by side,
    features [H, W, sum C_i] and alpha [H, W]; widths: the blocks' C_i."""
    if hasattr(out, "at"):
        return out.at(rows)
    f, a = out.features.reshape(-1, out.features.shape[-1]), out.alpha.reshape(-1)
    if rows is not None:
        f, a = f[rows], a[rows]
    return list(f.split(list(widths), dim=-1)), a


def class_tables(classes) -> tuple[torch.Tensor, torch.Tensor]:
    """(ids [S] long, isthing [S] bool): column j of the semantic logits is the j-th class."""
    cls = [c if isinstance(c, dict) else {"id": c.id, "name": c.name, "isthing": c.isthing} for c in classes]
    ids = torch.tensor([int(c["id"]) for c in cls], dtype=torch.long)
    thing = torch.tensor([bool(c["isthing"]) for c in cls], dtype=torch.bool)
    return ids, thing


def id_to_column(ids: torch.Tensor, label: torch.Tensor) -> torch.Tensor:
    """Map class ids in `label` to logit columns; -1 for void (0) and ids not in the table."""
    if ids.numel() == 0:
        return torch.full_like(label, -1)
    lut = torch.full((int(max(int(ids.max()), int(label.max()) if label.numel() else 0)) + 1,), -1,
                     dtype=torch.long)
    lut[ids] = torch.arange(ids.numel())
    out = lut[label.clamp_min(0)]
    out[label <= 0] = -1
    return out


def thing_masks(instance: torch.Tensor, semantic: torch.Tensor | None, ids: torch.Tensor,
                thing: torch.Tensor, min_pixels: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Binary masks [M, H, W] of the frame's thing instances (stuff is semantic only), and each
    mask's class column [M] long: the majority class of its pixels (-1 without semantics, when
    every mask counts).
    """
    masks, _ = masks_from_ids(instance, min_pixels=min_pixels)
    if masks.shape[0] == 0 or semantic is None or ids.numel() == 0:
        return masks, torch.full((masks.shape[0],), -1, dtype=torch.long)
    cols = id_to_column(ids, semantic)
    major = []
    for m in masks:
        c = cols[m]
        c = c[c >= 0]
        major.append(int(torch.bincount(c, minlength=ids.numel()).argmax()) if c.numel() else -1)
    major = torch.tensor(major, dtype=torch.long)
    keep = (major >= 0) & thing[major.clamp_min(0)]
    return masks[keep], major[keep]


def backproject(depth: torch.Tensor, K: torch.Tensor, c2w: torch.Tensor, mask: torch.Tensor,
                trim: bool = True) -> torch.Tensor:
    """World points [P, 3] of the mask's pixels with valid depth (pixel centres at integers).

    trim: keep only the mask's main depth layer (`front_layer`). Noisy 2D masks bleed past an
    object's outline onto the surface behind it (or in front): at 15 % noise a 31 px bottle mask
    held pixels 1.1 m behind the bottle, and the query Gaussian fitted to them spanned 0.4 m
    (std) instead of 3 cm, so the query drew on everything around the bottle and was never matched.
    """
    ys, xs = torch.nonzero(mask & (depth > 0), as_tuple=True)
    z = depth[ys, xs].double()
    if trim and z.numel() >= 3:
        keep = front_layer(z)
        ys, xs, z = ys[keep], xs[keep], z[keep]
    return transform_points(pixels_to_camera_torch(xs.double(), ys.double(), z, K), c2w.double()).float()


def front_layer(z: torch.Tensor, k: float = 3.0, floor: float = 0.02) -> torch.Tensor:
    """Mask [P] bool of the depths z [P] (metres) within k robust sigmas (1.4826 MAD) of their median.

    The median lies on the surface that most of a mask's pixels see; `floor` (m) keeps flat views
    of thin objects (MAD 0) from cutting their own depth noise.
    """
    med = z.median()
    mad = (z - med).abs().median()
    return (z - med).abs() <= k * 1.4826 * mad + floor


def init_queries(frames, classes, cfg: PanopticConfig, scene_scale: float,
                 generator: torch.Generator | None = None) -> InstanceQueries:
    """Queries from the thing masks of `cfg.init_frames` frames spread over the sequence.

    Every mask gives one query (Gaussian = its back-projected points); with cfg.init_merge > 0,
    masks of different frames that show one object (`associate.same_object_groups`) share one.
    Either way more queries than objects: dynamic adjustment removes the useless and duplicate ones
    during training.
    """
    ids, thing = class_tables(classes)
    n = len(frames)
    picks = np.unique(np.linspace(0, n - 1, min(cfg.init_frames, n)).round().astype(int)) if n else []
    groups, group_frame, group_mask = [], [], []
    mask_frames = {}
    for i in picks:
        fr = frames[int(i)]
        if fr.instance is None:
            continue
        inst = torch.as_tensor(np.asarray(fr.instance, dtype=np.int64))
        sem = None if fr.semantic is None else torch.as_tensor(np.asarray(fr.semantic, dtype=np.int64))
        min_px = max(1, int(cfg.min_mask_fraction * inst.numel()))
        depth = torch.as_tensor(np.asarray(fr.depth, dtype=np.float32))
        masks, _ = thing_masks(inst, sem, ids, thing, min_px)
        for k, m in enumerate(masks):
            pts = backproject(depth, torch.as_tensor(fr.K), torch.as_tensor(fr.c2w), m)
            if pts.shape[0] >= 3:
                groups.append(pts)
                group_frame.append(int(i))
                group_mask.append(k + 1)
        if cfg.init_merge > 0:          # what the association reads of the frame: thing mask k -> id k + 1
            local = np.zeros(tuple(inst.shape), dtype=np.int64)
            for k, m in enumerate(masks):
                local[m.numpy()] = k + 1
            mask_frames[int(i)] = MaskFrame(depth=depth.numpy(), K=np.asarray(fr.K, np.float64),
                                            c2w=np.asarray(fr.c2w, np.float64), instance=local)
    if cfg.init_merge > 0 and len(groups) > 1:
        label = same_object_groups([g.numpy() for g in groups], group_frame, group_mask, mask_frames,
                                   cfg.init_merge)
        groups = [torch.cat([groups[j] for j in np.flatnonzero(label == g)]) for g in range(int(label.max()) + 1)]
    feat, mean, cov = init_from_points(groups, cfg.feat_dim, generator=generator)
    return InstanceQueries(feat, mean, cov, temperature=cfg.temperature, scene_scale=scene_scale,
                           generator=generator)


@dataclass
class FrameLabels:
    """A frame's pseudo-labels as PanopticField.losses reads them (PanopticField.frame_labels):
    training keeps one per view instead of rebuilding them every step."""

    masks: torch.Tensor              # [M, H, W] bool thing masks (thing_masks)
    mask_cls: torch.Tensor           # [M] long their class columns (-1 unknown)
    windows: torch.Tensor            # [M, H*W] bool their neighbourhoods (mask_windows)
    columns: torch.Tensor | None     # [H*W] long each pixel's class column (-1 void); None without semantics
    mask_pixels: torch.Tensor | None = None   # [sum of mask sizes] long flat pixel indices, mask by mask
    mask_offsets: torch.Tensor | None = None  # [M + 1] long where each mask's pixels start in mask_pixels

    def random_mask_pixels(self, generator: torch.Generator | None = None) -> torch.Tensor | None:
        """[M] long one uniformly random pixel (flat index) of each thing mask; None without masks."""
        if self.mask_pixels is None or self.mask_offsets is None or self.mask_offsets.numel() < 2:
            return None
        start, count = self.mask_offsets[:-1], self.mask_offsets.diff()
        pick = (torch.rand(count.numel(), generator=generator) * count).long().clamp_max(count - 1)
        return self.mask_pixels[start + pick]


@functools.lru_cache(maxsize=8)
def pixel_tiles(width: int, height: int, tile: int) -> torch.Tensor:
    """[H * W] long: the tile of each pixel of a width x height image, tiles tile x tile pixels
    numbered row by row (ceil(W / tile) a row; edge tiles cut at the border)."""
    tw = -(-width // tile)
    y, x = torch.arange(height).unsqueeze(1), torch.arange(width).unsqueeze(0)
    return ((y // tile) * tw + x // tile).flatten()


def sample_pixels(width: int, height: int, n: int, tile: int, generator: torch.Generator | None = None,
                  seeds: torch.Tensor | None = None) -> torch.Tensor | None:
    """The flat pixel indices [P] a step reads (PanopticConfig.pixels_per_step / sample_tile), or None
    for every pixel when the image has no more than n.

    tile 0: n distinct random pixels. tile > 0: whole tile x tile tiles, first the tile of each seed
    pixel seeds [S] (a random pixel of every mask: each mask is read every step, whatever its size),
    then random others up to n / tile^2 tiles in all; P can pass n only by the seeds' tiles.
    Ascending, so the rows a frozen blend slices lie in memory order."""
    hw = int(width) * int(height)
    if n >= hw:
        return None
    if tile <= 0:
        return torch.randperm(hw, generator=generator)[:n]
    n_tiles = -(-int(width) // tile) * -(-int(height) // tile)
    chosen = torch.zeros(n_tiles, dtype=torch.bool)
    if seeds is not None and seeds.numel():
        tw = -(-int(width) // tile)
        chosen[(seeds // width) // tile * tw + (seeds % width) // tile] = True
    need = max(0, n // (tile * tile) - int(chosen.sum()))
    if need:
        perm = torch.randperm(n_tiles, generator=generator)
        chosen[perm[~chosen[perm]][:need]] = True
    # the chosen tiles' pixels in ascending order: a mask over the image (gathering the tiles' pixel
    # lists and sorting them took ~3x as long, ~0.5 ms of a 320x240 step)
    return torch.nonzero(chosen[pixel_tiles(int(width), int(height), int(tile))]).flatten()


class PanopticField(nn.Module):
    """Per-surfel semantic logits [N, S] and instance features [N, F], plus the instance queries."""

    def __init__(self, n_surfels: int, classes, queries: InstanceQueries, cfg: PanopticConfig,
                 generator: torch.Generator | None = None):
        super().__init__()
        self.cfg = cfg
        self.class_ids, self.class_thing = class_tables(classes)
        s = self.class_ids.numel()
        self.semantic = nn.Parameter(torch.zeros(n_surfels, s))
        self.instance = nn.Parameter(0.1 * torch.randn(n_surfels, cfg.feat_dim, generator=generator))
        self.queries = queries
        self.matched = torch.zeros(queries.count)
        self.visible = torch.zeros(queries.count)
        # [Q, Q] frames where two queries drew inside one 2D mask / inside two different masks
        self.same = torch.zeros(queries.count, queries.count)
        self.apart = torch.zeros(queries.count, queries.count)
        # frames where both were matched (to different masks), each drawing its mask (p > 0.5 on it)
        self.comatched = torch.zeros(queries.count, queries.count)
        # [Q, S] frames in which each query was matched to a mask of each class column
        self.class_votes = torch.zeros(queries.count, self.class_ids.numel())
        self.born = torch.zeros(queries.count)        # step a query was created (pruning grace)
        # a query's id for its whole life (positions shift as queries are dropped): the settle
        # test compares which query owns a surfel across adjustments (current_labels)
        self.uid = torch.arange(queries.count)
        self._next_uid = queries.count
        self.steps = 0
        # (point set [P, 3], feature [F] or None) of masks that no query covers
        self._pending: list[tuple[torch.Tensor, torch.Tensor | None]] = []
        self.last_drops: dict[str, int] = {}          # {rule: queries dropped} at the last adjustment
        self._gen = generator
        self._surfel_step = None                     # the surfel features' step when run in the background
        self._pos_codes = None                       # [N, 6 F'] the surfels' position codes (fix_positions)
        self._affinity_at = None                     # (step, [N, Q]) affinity_all of the last adjustment
        self._grad_buffers: dict = {}                # {name: ([N, C] gradient buffer, [V] rows it holds)}
        self._make_optimizers()

    def fix_positions(self, means: torch.Tensor) -> None:
        """The surfels stay at means [N, 3] from now on (frozen geometry): their position codes are
        computed once here, and `losses` then reads them for the `means` it is given."""
        with torch.no_grad():
            self._pos_codes = self.queries.position_codes(means.detach())

    def surfel_rows(self, name: str, idx: torch.Tensor) -> torch.Tensor:
        """The rows idx [V] (all different: a view's surfels) of the per-surfel parameter `name`
        ("semantic" [N, S] or "instance" [N, F]) as a leaf [V, C] whose gradient lands in the
        parameter's: the same .grad as indexing the parameter would give, written into one buffer
        [N, C] kept across steps (its last rows zeroed, the new ones copied in). The indexing's
        backward allocated and zero-filled a fresh [N, C] tensor every step, then scattered into it:
        ~3 ms of a 136k-surfel room step (fresh pages), where these row copies take ~0.4 ms. The
        buffer is the parameter's .grad until the next step's gradient overwrites it."""
        param = getattr(self, name)
        rows = param.detach().index_select(0, idx).requires_grad_(param.requires_grad)
        if param.requires_grad:
            rows.register_hook(functools.partial(self._land_gradient, name, idx))
        return rows

    def _land_gradient(self, name: str, idx: torch.Tensor, v_rows: torch.Tensor) -> None:
        param = getattr(self, name)
        if param.grad is not None:             # accumulating onto a gradient the caller kept
            param.grad.index_add_(0, idx, v_rows.to(param.grad.dtype))
            return
        buf, held = self._grad_buffers.get(name, (None, None))
        if buf is None or buf.shape != param.shape or buf.dtype != param.dtype:
            buf = torch.zeros_like(param)
        elif held is not None:
            buf.index_fill_(0, held, 0.0)
        buf.index_copy_(0, idx, v_rows.to(buf.dtype))
        self._grad_buffers[name] = (buf, idx)
        param.grad = buf

    # ---- optimisation bookkeeping -------------------------------------------------------------
    def _make_optimizers(self) -> None:
        # fused: one pass over each tensor instead of ~10 (tabletop, 128k surfels: 6.2 -> 2.4 ms a step)
        self.opt_surfel = torch.optim.Adam([self.semantic, self.instance], lr=self.cfg.lr_surfel, fused=True)
        self.opt_query = torch.optim.Adam(list(self.queries.parameters()), lr=self.cfg.lr_query, fused=True)

    def zero_grad(self, set_to_none: bool = True) -> None:
        self.wait_step()
        self.opt_surfel.zero_grad(set_to_none=set_to_none)
        self.opt_query.zero_grad(set_to_none=set_to_none)

    def step(self, background=None) -> None:
        """One optimizer step of the surfel features and the queries, then the queued spawns.

        background: an executor (one worker) to run the surfel features' step on, so the caller can
        prepare its next step meanwhile (psimap.panoptic.fit); `wait_step` then joins it, and must
        before anything reads or zeroes the surfel features or their gradients. None: in line."""
        for p in self.queries.parameters():
            if p.grad is not None:
                torch.nan_to_num_(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
        if background is None:
            self._step_surfels()
        else:
            self._surfel_step = background.submit(self._step_surfels)
        self._step_queries()
        self.steps += 1
        self._affinity_at = None
        if self._pending:
            self.wait_step()        # a spawn re-creates both optimizers
        self._spawn_pending()

    def _step_queries(self) -> None:
        """Adam's step of the queries, with each centre's move scaled by its query's size.

        Adam moves every parameter by about lr a step whatever the size of its gradient, so a
        query's centre moved ~lr_query metres a step for queries of every size: a mug's query
        (sigma 4.8 cm) pushed once by 8 pixels of a frame drifted 9 cm (two sigmas) over the next
        25 steps on the update's momentum alone and lost its mug to the shelf's query. A centre
        moves by Adam's step times min(1, sigma / query_step_sigma), sigma = the geometric mean of
        its Gaussian's axes: the same drift in units of its own size below query_step_sigma. The
        off-diagonal of its Cholesky factor is in metres too and is scaled alike; the log-diagonal
        is scale-free and keeps Adam's step."""
        ref = self.cfg.query_step_sigma
        if ref <= 0 or self.queries.count == 0:
            self.opt_query.step()
            return
        q = self.queries
        before = [p.detach().clone() for p in (q.mean, q.offdiag)]
        scale = (q.log_diag.detach().mean(-1).exp() / ref).clamp(max=1.0)[:, None]    # [Q, 1]
        self.opt_query.step()
        with torch.no_grad():
            for p, b in zip((q.mean, q.offdiag), before):
                p.copy_(b + (p - b) * scale)

    def _step_surfels(self) -> None:
        for p in (self.semantic, self.instance):          # [N, S] and [N, F]: every surfel
            if p.grad is not None:
                torch.nan_to_num_(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
        self.opt_surfel.step()

    def wait_step(self) -> None:
        """Join the surfel features' step `step(background=...)` started (re-raises its error)."""
        pending, self._surfel_step = self._surfel_step, None
        if pending is not None:
            pending.result()

    def _spawn_pending(self) -> None:
        """Queries for masks that no existing query covered (objects the seed frames missed)."""
        if not self._pending:
            return
        pending, self._pending = self._pending, []
        room = self.cfg.max_queries - self.queries.count
        pending = pending[: max(0, room)]
        if not pending:
            return
        groups = [p for p, _ in pending]
        feat, mean, cov = init_from_points(groups, self.cfg.feat_dim, generator=self._gen)
        for i, (_, f) in enumerate(pending):
            if f is not None:
                feat[i] = f
        self.queries.add(feat, mean, cov)
        a = len(groups)
        self.matched = torch.cat([self.matched, torch.zeros(a)])
        self.visible = torch.cat([self.visible, torch.zeros(a)])
        self.same = F.pad(self.same, (0, a, 0, a))
        self.apart = F.pad(self.apart, (0, a, 0, a))
        self.comatched = F.pad(self.comatched, (0, a, 0, a))
        self.class_votes = F.pad(self.class_votes, (0, 0, 0, a))
        self.born = torch.cat([self.born, torch.full((a,), float(self.steps))])
        self.uid = torch.cat([self.uid, self._next_uid + torch.arange(a)])
        self._next_uid += a
        self._make_optimizers()

    def _queue_uncovered(self, masks: torch.Tensor, match, drawn_on, depth: torch.Tensor,
                         K: torch.Tensor, w2c: torch.Tensor, surfel_pos: torch.Tensor | None = None,
                         surfel_feat: torch.Tensor | None = None,
                         mask_cls: torch.Tensor | None = None) -> None:
        """Queue back-projected points of unmatched masks that no free query explains.

        masks [M, H, W] bool; drawn_on(m) -> [Q] the queries' mean rendered probabilities on the
        pixels of mask m that the step read (None: it read none, so nothing can be told of it);
        mask_cls [M] class columns (-1 unknown). A query matched to another mask in this frame is
        busy with that object, so only the free (unmatched) queries can cover a mask: by rendering
        it (mean probability > 0.5 over its pixels) or by holding its 3D centre within 3 sigma.
        Checking every query instead blocked objects resting on a large one (bottles on a table lie
        inside the table query's Gaussian) from ever getting a query of their own. One exception
        (`spawn_split`): when the query drawing most of the mask is busy with a mask of the same
        class, the mask is the second piece of a split object, not a new one.
        """
        taken = set(match.mask_idx.tolist())
        unmatched = [m for m in range(masks.shape[0]) if m not in taken]
        if not unmatched or self.queries.count >= self.cfg.max_queries:
            return
        free = torch.ones(self.queries.count, dtype=torch.bool)
        free[match.query_idx] = False
        busy_mask = torch.full((self.queries.count,), -1, dtype=torch.long)
        busy_mask[match.query_idx] = match.mask_idx
        c2w = torch.linalg.inv(w2c.double())
        queued = 0
        for m in unmatched:
            if queued >= self.cfg.max_spawn_per_step:
                break
            drawn = drawn_on(m)                                                        # [Q]
            if drawn is None:
                continue
            if bool(free.any()) and float(drawn[free].max()) > 0.5:
                continue
            if self.cfg.spawn_split and mask_cls is not None and int(mask_cls[m]) >= 0:
                top = int(drawn.argmax())
                if not bool(free[top]) and int(mask_cls[busy_mask[top]]) == int(mask_cls[m]):
                    continue
            pts = backproject(depth, K, c2w, masks[m])
            if pts.shape[0] < 3:
                continue
            with torch.no_grad():
                if bool(free.any()) and float(
                        self.queries.mahalanobis2(pts.mean(0, keepdim=True))[:, free].min()) < 9.0:
                    continue
            feat = self._spawn_feature(pts, surfel_pos, surfel_feat) if self.cfg.spawn_feature else None
            self._pending.append((pts, feat))
            queued += 1

    def _spawn_feature(self, pts: torch.Tensor, surfel_pos: torch.Tensor | None,
                       surfel_feat: torch.Tensor | None) -> torch.Tensor | None:
        """Feature [F] of a new query: the mean instance feature of the surfels under its mask.

        pts [P, 3] back-projected mask pixels; surfel_pos [V, 3] / surfel_feat [V, F] the visible
        surfels. A random feature loses the softmax on those surfels to the query whose object
        they were trained toward (a bottle's surfels to the shelf's query): the new query then draws
        nothing, is never matched, is pruned as useless and spawned again, over and over. Starting
        from the surfels' own features it draws them from the first step and is matched to its mask.
        Scaled to the largest query feature norm so sigmoid(f_q . f_g) is as decisive as the others'.
        """
        if surfel_pos is None or surfel_feat is None or surfel_pos.shape[0] == 0:
            return None
        from scipy.spatial import cKDTree

        # a k-d tree of the visible surfels: the [256, V] distance blocks and their argmin were ~7 ms
        # a spawn on a 640x480 real capture (125 spawns in its 240 steps)
        _, near = cKDTree(surfel_pos.detach().double().numpy()).query(pts.detach().double().numpy(), k=1)
        f = surfel_feat[torch.from_numpy(np.asarray(near, dtype=np.int64))].mean(0)
        norm = float(f.norm())
        if not norm > 1e-6:
            return None
        scale = max(1.0, float(self.queries.feature.detach().norm(dim=-1).max())) if self.queries.count else 1.0
        return f / norm * scale

    # ---- losses -------------------------------------------------------------------------------
    def losses(self, render, means: torch.Tensor, visible_idx: torch.Tensor, instance: torch.Tensor | None,
               semantic: torch.Tensor | None, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int,
               generator: torch.Generator | None = None, depth: torch.Tensor | None = None,
               labels: "FrameLabels | None" = None,
               pixels: "torch.Tensor | None | str" = "sample") -> tuple[torch.Tensor, torch.Tensor, dict]:
        """(L_ins, L_sem, info) for one frame.

        render(idx [V], blocks [[V, C_i]], topk) -> a RenderOutput of the blocks side by side or a
        frozen blend's render (`.at`; see rendered_blocks);
        means [N, 3] (detached positions are used for the queries' Gaussians); visible_idx [V]
        surfels in this view; instance / semantic [H, W] long per-frame pseudo-labels (None when
        absent); labels: this field's `frame_labels` of them, when the caller keeps it per view
        (computed here otherwise). pixels: the flat pixel indices [P] to read (the caller's
        `sample_pixels`, whose render may hold only those rows), None for every pixel, "sample" to
        draw them here.
        """
        cfg = self.cfg
        self.wait_step()
        q = self.queries.count
        s = self.class_ids.numel()
        if labels is None:
            labels = self.frame_labels(instance, semantic)
        # the sampled pixels (all of them, in order, when the frame has no more than
        # pixels_per_step: every term is a sum over pixels, so no permutation and no gathered copy);
        # a frozen blend renders only these rows (a 640x480 frame: 20k of 307k)
        pix = self.sample_pixels(width, height, labels, generator) if isinstance(pixels, str) else pixels
        pos = means.detach().index_select(0, visible_idx)
        f_vis = self.surfel_rows("instance", visible_idx)
        sem_vis = self.surfel_rows("semantic", visible_idx)     # gathered once
        codes = None if self._pos_codes is None else self._pos_codes.index_select(0, visible_idx)
        fq = self.queries.attend(f_vis, pos, codes)
        p_thing = None
        if s > 0 and bool(self.class_thing.any()) and not bool(self.class_thing.all()):
            # p(q | g) = P(thing | g) softmax_q(A / T): stuff surfels (walls, floor) belong to no
            # query, so the BCE on stuff pixels lowers P(thing) instead of the surfels' opacity. A
            # product with the thing indicator: the column gather and sum took twice as long
            # (forward and backward, 17k surfels x 11 classes: 1.26 -> 0.68 ms)
            p_thing = softmax_last(sem_vis) @ self.class_thing.to(sem_vis.dtype)
        dist = self.queries.distribution(f_vis, pos, fq, p_thing)                  # [V, Q]
        out = render(visible_idx, [dist, sem_vis], cfg.topk)
        hw = int(width) * int(height)
        frozen = hasattr(out, "columns")
        if frozen:
            # a frozen blend: the queries' render without its gradient (the matching reads it all, the
            # loss only the matched queries' columns, rendered again with it below): the [P, Q]
            # gradient, zero but in a few columns, and its product back onto the surfels are never
            # made (~5 ms of a 93-query step)
            (q_px, s_px), alpha_px = out.at(pix, detach=(0,))                        # [P, Q], [P, S], [P]
            anchor = dist
        else:
            (q_px, s_px), alpha_px = rendered_blocks(out, pix, [q, s])
            anchor = q_px
        share = 1.0 if pix is None else pix.numel() / hw
        # the class distribution of the read pixels, for the matching's class cost and the semantic loss
        wanted = labels.columns is not None or (instance is not None and q > 0 and cfg.w_class > 0)
        scores = ClassScores.of(s_px, alpha_px) if s > 0 and wanted else None

        def sampled(a):             # [..., H*W] -> [..., P]
            return a if pix is None else a[..., pix]
        info = {"queries": q, "matched": 0, "masks": 0}
        # Instance: per-frame Hungarian matching of the queries' rendered masks to the 2D masks.
        l_ins = l_sem = None
        if instance is not None and q > 0:
            min_px = max(1, int(cfg.min_mask_fraction * hw))
            masks, mask_cls = labels.masks, labels.mask_cls
            info["masks"] = int(masks.shape[0])
            with torch.no_grad():
                # a query is "seen" by this frame when it owns (p > 0.5) at least a small mask here.
                # Its centre merely projecting into the image would count hidden objects too, and
                # its summed probability counts every frame: the softmax leaves each query a little
                # mass on every surfel (then all queries were "seen" in every frame and those of
                # objects in few frames were pruned as useless). Counted on the sampled pixels.
                # the comparison written as floats (a bool tensor then cast: 1.4 -> 0.2 ms at 20k x 93)
                own_f = torch.gt(q_px, 0.5, out=torch.empty_like(q_px))            # [P, Q] 1.0 / 0.0
                own_n = own_f.sum(0)             # a float column sum (a bool one: 2.6 ms at 85 queries)
                seen = own_n >= min_px * share
                self.visible += seen.float()
            if masks.shape[0]:
                target = sampled(masks.reshape(masks.shape[0], -1)).float()          # [M, P]
                window = sampled(labels.windows).float()
                # [Q, P], a view of the render's pixel-major rows: the matching gathers and clamps the
                # pixels it reads, the loss clamps the matched rows to [1e-6, 1 - 1e-6] (a clamp to
                # [0, 1] of all of it first was a copy and a backward over [Q, P] that change nothing)
                prob = q_px.T
                match = hungarian_match(prob, target, reject_dice=cfg.reject_dice, w_class=cfg.w_class,
                                        class_cost=self._class_cost(prob, scores, mask_cls),
                                        window=window)
                if match.query_idx.numel():
                    matched = out.columns(0, match.query_idx) if frozen else None
                    l_ins = matched_mask_loss(prob, target, match, window=window, matched=matched)
                self.matched[match.query_idx] += 1
                mq = match.query_idx
                with torch.no_grad():
                    # both matched in this frame, each drawing its mask (mean probability > 0.5 on
                    # it): a match the query hardly draws (the assignment hands a leftover mask to
                    # a query at p 0.02-0.05) says nothing of two objects, and such matches of a
                    # bottle's split-off query made it "distinct" from the bottle's (tabletop: 38
                    # frames co-matched against 15 seen apart)
                    t_m = target.index_select(0, match.mask_idx)
                    drawn = (prob.index_select(0, mq) * t_m).sum(-1) / t_m.sum(-1).clamp_min(1.0)
                    sure = mq[drawn > 0.5]
                self.comatched[sure[:, None], sure[None, :]] += 1.0
                mc = mask_cls[match.mask_idx]
                if s > 0 and bool((mc >= 0).any()):
                    ok = mc >= 0
                    self.class_votes.index_put_((mq[ok], mc[ok]), torch.ones(int(ok.sum())), accumulate=True)
                with torch.no_grad():
                    # The 2D mask holding most (> iom_threshold) of each seen query's pixels; pairs
                    # of queries in one mask vs in different masks (see co_mask_duplicates).
                    inside = target @ own_f / own_n.clamp_min(1)
                    best, host = inside.max(0)
                    host = torch.where(seen & (best > cfg.iom_threshold), host, torch.full_like(host, -1))
                    both = (host >= 0)[:, None] & (host >= 0)[None, :]
                    eq = host[:, None] == host[None, :]
                    self.same += (both & eq).float()
                    self.apart += (both & ~eq).float()
                if cfg.spawn and depth is not None:
                    def drawn(m, prob=prob, target=target):     # [Q] mean probability on mask m's read pixels
                        n_read = float(target[m].sum())
                        if n_read == 0:
                            return None
                        with torch.no_grad():
                            return (prob @ target[m]) / n_read

                    self._queue_uncovered(masks, match, drawn, depth, K, w2c, pos, f_vis.detach(), mask_cls)
                info["matched"] = int(match.query_idx.numel())
        # Semantic: cross-entropy of alpha-normalised blended logits on labelled, covered pixels.
        if labels.columns is not None and s > 0:
            l_sem = semantic_loss(s_px, alpha_px, sampled(labels.columns), scores)
        if l_ins is None or l_sem is None:
            # a loss with no supervision in this frame is 0 with the graph of what it would train:
            # its parameters' gradients are then zeros, not None (Adam steps them either way).
            # Only then: the two sums and their backward were ~1.5 ms of a room step
            zero = (anchor.sum() + s_px.sum()) * 0.0
            l_ins = zero if l_ins is None else l_ins
            l_sem = zero if l_sem is None else l_sem
        return cfg.w_ins * l_ins, cfg.w_sem * l_sem, info

    def frame_labels(self, instance: torch.Tensor | None, semantic: torch.Tensor | None) -> "FrameLabels":
        """What the losses read of a frame's pseudo-labels instance / semantic [H, W] long (or None),
        the same at every step of the frame."""
        empty = torch.zeros(0, dtype=torch.long)
        columns = None if semantic is None else id_to_column(self.class_ids, semantic.reshape(-1))
        if instance is None:
            return FrameLabels(torch.zeros(0, 1, 1, dtype=torch.bool), empty, torch.zeros(0, 1, dtype=torch.bool),
                               columns)
        min_px = max(1, int(self.cfg.min_mask_fraction * instance.numel()))
        masks, mask_cls = thing_masks(instance, semantic, self.class_ids, self.class_thing, min_px)
        flat = masks.reshape(masks.shape[0], instance.numel())
        mask_idx, pixels = torch.nonzero(flat, as_tuple=True)                     # mask by mask
        offsets = torch.zeros(masks.shape[0] + 1, dtype=torch.long)
        offsets[1:] = torch.bincount(mask_idx, minlength=masks.shape[0]).cumsum(0)
        return FrameLabels(masks, mask_cls, mask_windows(masks).reshape(masks.shape[0], instance.numel()), columns,
                           mask_pixels=pixels, mask_offsets=offsets)

    def sample_pixels(self, width: int, height: int, labels: "FrameLabels",
                      generator: torch.Generator | None = None) -> torch.Tensor | None:
        """The pixels [P] a step on a frame with these labels reads (module sample_pixels, seeded by
        a random pixel of each thing mask); None: every pixel."""
        cfg = self.cfg
        if cfg.pixels_per_step >= int(width) * int(height):
            return None
        seeds = labels.random_mask_pixels(generator) if cfg.sample_tile > 0 else None
        return sample_pixels(width, height, cfg.pixels_per_step, cfg.sample_tile, generator, seeds)

    def _class_cost(self, prob: torch.Tensor, scores: "ClassScores | None",
                    mask_cls: torch.Tensor) -> torch.Tensor | None:
        """Matching class term [Q, M]: 1 - p_q(class of mask m), p_q the rendered class distribution
        averaged over query q's pixels (paper §4.2's class cost; a bottle query is not matched to a
        box mask that it happens to overlap). prob [Q, P]; scores: the pixels' ClassScores (None:
        no classes); mask_cls [M] class columns (-1: no class, cost 0). None without classes or
        weight."""
        if self.cfg.w_class <= 0 or scores is None or mask_cls.numel() == 0:
            return None
        with torch.no_grad():
            prob = prob.clamp(0.0, 1.0)
            # [S, P] @ [P, Q], transposed: prob is the pixel-major render's transpose, and the
            # product of two transposed operands ran 8x slower (2.3 ms at 20 queries, 19200 pixels)
            q_cls = (scores.p @ prob.T).T / prob.sum(-1, keepdim=True).clamp_min(1e-6)     # [Q, S]
            cost = 1.0 - q_cls[:, mask_cls.clamp_min(0)]
            return torch.where(mask_cls[None, :] >= 0, cost, torch.zeros_like(cost))

    # ---- dynamic query adjustment -------------------------------------------------------------
    def global_query_features(self, means: torch.Tensor) -> torch.Tensor:
        """Query features attended over all surfels (used for scene-wide assignment / export)."""
        with torch.no_grad():
            codes = self._pos_codes if self._pos_codes is not None and self._pos_codes.shape[0] == means.shape[0] else None
            return self.queries.attend(self.instance.detach(), means.detach(), codes)

    def affinity_all(self, means: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
        """A(q, g) for every surfel [N, Q] (chunked)."""
        fq = self.global_query_features(means)
        with torch.no_grad():
            parts = [self.queries.affinity(self.instance[i:i + chunk].detach(), means[i:i + chunk].detach(), fq)
                     for i in range(0, means.shape[0], chunk)]
        return torch.cat(parts) if parts else means.new_zeros(0, self.queries.count)

    def adjust(self, means: torch.Tensor) -> int:
        """Drop useless and duplicate queries; returns how many were removed."""
        self.wait_step()
        q = self.queries.count
        if q <= 1:
            return 0
        affinity = self.affinity_all(means)                                         # [N, Q]
        masks = affinity > self.cfg.mask_affinity
        old_enough = (self.steps - self.born) >= self.cfg.query_grace               # grace for new ones
        distinct = (self.comatched >= self.cfg.distinct_frames) if self.cfg.distinct_frames > 0 else None
        dup = duplicate_queries(masks, self.cfg.iom_threshold, distinct) & old_enough
        useless = useless_queries(self.matched, self.visible, self.cfg.min_match_rate) & old_enough
        # never matched in a frame though it has lived a full adjustment period: it owns no pixel
        # anywhere (visible stays 0, so the rate test above cannot see it) yet would own surfels
        # by argmax at export
        useless |= (self.matched == 0) & old_enough
        # frames in which the two were matched to different 2D masks also show them apart: a
        # merged 2D mask (mug + shelf, 15 % of touching pairs per frame) puts a small object's
        # query inside the large one's mask, while its few pixels rarely make it "seen" apart
        # (seed 0: the shelf's and the mug's queries, matched 26 and 25 times, were dropped so)
        fragment = co_mask_duplicates(self.same, torch.maximum(self.apart, self.comatched),
                                      self.matched) & old_enough
        empty = (masks.sum(0) == 0) & old_enough                                     # covers nothing
        drop = dup | useless | empty | fragment
        # which rule fired (a query may break several): read by the training log
        self.last_drops = {"duplicate": int(dup.sum()), "fragment": int((fragment & ~dup).sum()),
                           "useless": int((useless & ~dup & ~fragment).sum()),
                           "empty": int((empty & ~dup & ~useless & ~fragment).sum())}
        if bool(drop.all()):                                                         # keep the best one
            drop[int(torch.argmax(self.matched))] = False
        keep = ~drop
        removed = int(drop.sum())
        if removed:
            self.queries.keep(keep)
            self.matched = self.matched[keep]
            self.visible = self.visible[keep]
            self.same = self.same[keep][:, keep]
            self.apart = self.apart[keep][:, keep]
            self.comatched = self.comatched[keep][:, keep]
            self.class_votes = self.class_votes[keep]
            self.born = self.born[keep]
            self.uid = self.uid[keep]
            self._make_optimizers()
            affinity = affinity[:, keep]
        # until the next step: the kept queries' columns are what affinity_all would give again (a
        # query's attended feature and Gaussian are its own), read by the settle test's
        # current_labels at this same step (~80 ms of a room adjustment)
        self._affinity_at = (self.steps, affinity)
        return removed

    def adjustment_due(self) -> bool:
        """Whether this step is on the adjustment schedule (adjust_start, then every adjust_every)."""
        c = self.cfg
        return self.steps >= c.adjust_start and (self.steps - c.adjust_start) % c.adjust_every == 0

    def maybe_adjust(self, means: torch.Tensor) -> int:
        return self.adjust(means) if self.adjustment_due() else 0

    def semantic_columns(self) -> torch.Tensor:
        """[N] long class column of each surfel: its largest logit, except that a stuff class held by
        fewer than max(min_stuff_share x N, min_instance_surfels) surfels gives them up to their next
        class (min_stuff_share)."""
        with torch.no_grad():
            logits = self.semantic.detach()
            col = logits.argmax(-1)
            n = col.numel()
            if n == 0 or self.class_ids.numel() < 2:
                return col
            counts = torch.bincount(col, minlength=self.class_ids.numel())
            floor = max(self.cfg.min_stuff_share * n, float(self.cfg.min_instance_surfels))
            stray = (counts > 0) & (counts < floor) & ~self.class_thing
            if not bool(stray.any()):
                return col
            hit = stray[col]
            col[hit] = logits[hit].masked_fill(stray, float("-inf")).argmax(-1)
            return col

    def current_labels(self, means: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(semantic [N] long class column of each surfel's largest logit, instance [N] long the
        lifelong id (`uid`) of its query of largest affinity + 1, 0 for stuff): the export's labels
        before class fusion and smoothing, the same ids whatever queries were spawned or dropped in
        between (cheap enough to compare every adjustment period: the settle test of
        psimap.panoptic.fit)."""
        n = means.shape[0]
        self.wait_step()
        with torch.no_grad():
            q = self.queries.count
            if self.class_ids.numel():
                col = self.semantic_columns()
                thing = self.class_thing[col]
            else:
                col = torch.zeros(n, dtype=torch.long)
                thing = torch.ones(n, dtype=torch.bool)
            kept = self._affinity_at
            affinity = kept[1] if kept is not None and kept[0] == self.steps and kept[1].shape == (n, q) else None
            if affinity is None and q:
                affinity = self.affinity_all(means)
            owner = self.uid[affinity.argmax(-1)] + 1 if q else torch.zeros(n, dtype=torch.long)
            return col, torch.where(thing, owner, torch.zeros_like(owner))

    # ---- export -------------------------------------------------------------------------------
    def assign(self, means: torch.Tensor) -> dict:
        """Hard labels for the checkpoint.

        semantic_id [N] = class of the largest logit; instance_id [N] = the query of largest
        affinity for thing surfels (0 for stuff; with `class_fusion` the affinity softmax times the
        surfel's probability of the query's class), renumbered 1..I over instances with at least
        `min_instance_surfels` surfels (their queries are `kept` [I]; the others own nothing), then
        smoothed over 3D neighbours (`smooth_k`); instance_class {id: class id}: the majority class
        of the 2D masks the query was matched to (`query_class`), else of the instance's surfels;
        written to the instance's surfels.
        """
        n = means.shape[0]
        self.wait_step()
        with torch.no_grad():
            if self.class_ids.numel():
                col = self.semantic_columns()
                sem = self.class_ids[col]
                is_thing = self.class_thing[col]
            else:
                sem = torch.zeros(n, dtype=torch.long)
                is_thing = torch.ones(n, dtype=torch.bool)
            q = self.queries.count
            inst = torch.zeros(n, dtype=torch.long)
            instance_class: dict[int, int] = {}
            kept = torch.zeros(0, dtype=torch.long)      # queries that own an instance, in id order
            if q:
                aff = self.affinity_all(means)                                      # [N, Q]
                owner = aff.argmax(-1)
                voted = self.class_votes.sum(-1) > 0
                qcol = torch.where(voted, self.class_votes.argmax(-1), -1) if self.cfg.query_class else None
                if self.cfg.class_fusion and self.class_ids.numel():
                    owner = fuse_classes(aff / self.queries.temperature, self.semantic.detach(), owner,
                                         is_thing, qcol)
                owner[~is_thing] = -1
                counts = torch.bincount(owner[owner >= 0], minlength=q)
                kept = torch.nonzero(counts >= self.cfg.min_instance_surfels).flatten()
                new_id = torch.zeros(q + 1, dtype=torch.long)
                new_id[kept] = torch.arange(1, kept.numel() + 1)
                inst = torch.where(owner >= 0, new_id[owner.clamp_min(0)], inst)
                if self.cfg.smooth_k > 1:
                    inst = smooth_instances(means.detach(), inst, owner >= 0, self.cfg.smooth_k)
                    alive = torch.bincount(inst, minlength=kept.numel() + 1)[1:] > 0
                    if not bool(alive.all()):                     # an instance outvoted entirely
                        kept = kept[alive]
                        renum = torch.zeros(alive.numel() + 1, dtype=torch.long)
                        renum[1:][alive] = torch.arange(1, kept.numel() + 1)
                        inst = renum[inst]
                for j in range(1, kept.numel() + 1):
                    own = inst == j
                    members = sem[own]
                    members = members[members > 0]
                    if qcol is not None and int(qcol[kept[j - 1]]) >= 0:
                        instance_class[j] = int(self.class_ids[qcol[kept[j - 1]]])
                    elif members.numel():
                        instance_class[j] = int(torch.mode(members).values)
                    if j in instance_class:
                        # one class per instance (a COCO segment has one category): stray surfels
                        # of an instance, e.g. table surfels under a bottle's query, take its class
                        sem[own] = instance_class[j]
        return {"instance_id": inst, "semantic_id": sem, "instance_class": instance_class, "kept": kept}

    def state_for_checkpoint(self, means: torch.Tensor) -> dict:
        """Surfel features, hard labels and queries in the checkpoint's layout."""
        cov = self.queries.cov().detach()
        lab = self.assign(means)
        return {
            "surfels": {"semantic": self.semantic.detach().clone(), "instance": self.instance.detach().clone(),
                        "instance_id": lab["instance_id"], "semantic_id": lab["semantic_id"]},
            # only the queries that own an instance are stored: stored query j is instance j + 1
            "queries": {"feature": self.global_query_features(means)[lab["kept"]].clone(),
                        "mean": self.queries.mean.detach()[lab["kept"]].clone(), "cov": cov[lab["kept"]].clone()},
            "instance_class": lab["instance_class"],
            "config": asdict(self.cfg),
        }


def fuse_classes(logits: torch.Tensor, semantic: torch.Tensor, owner: torch.Tensor,
                 thing: torch.Tensor, query_class: torch.Tensor | None = None) -> torch.Tensor:
    """Instance owner [N] from both heads: argmax_q log softmax_q(logits) + log p_sem(class(q) | g).

    logits [N, Q] affinity / temperature; semantic [N, S] per-surfel class logits; owner [N] the
    instance-only argmax; thing [N] bool. class(q) = majority semantic class over the thing
    surfels q owns by `owner`; a query owning none stays out (it would not become an instance,
    and with no class it would pay no semantic term). query_class [Q] long (optional): class
    columns known from the 2D masks each query was matched to (-1 = unknown: use the surfel vote).
    """
    n, q = logits.shape
    col = semantic.argmax(-1)
    sel = thing & (owner >= 0)
    s = semantic.shape[1]
    votes = torch.zeros(q, s)
    votes.index_put_((owner[sel], col[sel]), torch.ones(int(sel.sum())), accumulate=True)
    qcls = votes.argmax(-1)
    known = votes.sum(-1) > 0
    if query_class is not None:
        qcls = torch.where(query_class >= 0, query_class, qcls)
    log_sem = torch.log_softmax(semantic, -1)[:, qcls]                                  # [N, Q]
    score = torch.log_softmax(logits, -1) + torch.where(known[None, :], log_sem, torch.full_like(log_sem, -torch.inf))
    return torch.where(thing, score.argmax(-1), owner)


def smooth_instances(means: torch.Tensor, inst: torch.Tensor, thing: torch.Tensor, k: int) -> torch.Tensor:
    """Majority vote of instance ids over each thing surfel's k nearest thing surfels (itself included).

    means [N, 3]; inst [N] long (0 = none); thing [N] bool. The per-surfel argmax of the affinity is
    noisy where two objects touch (a few table surfels under a bottle's query, a few bottle surfels
    under the shelf's): those surfels are outvoted by their neighbours. Neighbours farther than 3x
    the median nearest-neighbour distance do not vote (a lone surfel keeps its id). A surfel changes
    only to an id that holds a strict majority of its votes.
    """
    from scipy.spatial import cKDTree

    idx = torch.nonzero(thing).flatten()
    if idx.numel() <= k:
        return inst
    pts = means[idx].double().numpy()
    tree = cKDTree(pts)
    d1, _ = tree.query(pts, k=2)
    radius = 3.0 * float(np.median(d1[:, 1]))
    d, nb = tree.query(pts, k=k, distance_upper_bound=radius if radius > 0 else np.inf)
    valid = np.isfinite(d)
    uniq, lab = np.unique(inst[idx].numpy(), return_inverse=True)
    votes = np.where(valid, lab[np.minimum(nb, len(idx) - 1)], -1)                    # [T, k]
    n_lab = len(uniq)
    rows = np.repeat(np.arange(len(idx)), k)
    ok = votes.reshape(-1) >= 0
    counts = np.zeros((len(idx), n_lab), dtype=np.int64)
    np.add.at(counts, (rows[ok], votes.reshape(-1)[ok]), 1)
    best = counts.argmax(1)
    change = counts[np.arange(len(idx)), best] * 2 > valid.sum(1)
    out = inst.clone()
    new = np.where(change, uniq[best], inst[idx].numpy())
    out[idx] = torch.as_tensor(new, dtype=inst.dtype)
    return out
