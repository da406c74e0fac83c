"""Stage 3 of the renderer (SPEC.md) in plain torch: the exact, differentiable oracle.

Vectorised over (tile, pixel, surfel-in-tile) with padding: each chunk of tiles is a dense
[tiles, 256, L] problem, L = the longest tile list of the chunk. Sequential front-to-back
compositing is expressed with cumprod: the transmittance before surfel i is the product of
(1 - alpha_j) over the earlier blended surfels, and since transmittance only falls, the stop rule
marks everything from the first surfel that would drop it below 1e-4 as not blended.
Backward is torch autograd; chunks are checkpointed so memory stays bounded by one chunk.
"""
from __future__ import annotations

import math

import torch
from torch.utils.checkpoint import checkpoint

from psimap.render.output import RenderOutput
from psimap.render.binning import TILE, bin_surfels
from psimap.render.project import CHI, Projected

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_STOP = 1e-4
EDGE_ON_EPS = 1e-10
LOWPASS_RHO2_MAX = math.log(255.0)
# Per-chunk budget of (pixel, surfel) evaluations; one chunk's autograd graph is ~30 tensors of
# this many elements, i.e. ~0.25 GiB in float32 at the default.
DEFAULT_CHUNK_EVALS = 1 << 21


def blend_tiles(px: torch.Tensor, py: torch.Tensor, T: torch.Tensor, center: torch.Tensor,
                depth_key: torch.Tensor, normal_c: torch.Tensor, opac: torch.Tensor,
                colors: torch.Tensor, feats: torch.Tensor, real: torch.Tensor,
                near: float, far: float, topk: int | None):
    """Composite the padded surfel lists of a batch of tiles.

    px, py: [B, P] pixel coordinates; per tile slot (front to back): T [B, L, 3, 3],
    center [B, L, 2], depth_key [B, L], normal_c [B, L, 3], opac [B, L], colors [B, L, 3],
    feats [B, L, C], real [B, L] bool (False = padding).
    Returns rgb [B, P, 3], alpha [B, P], depth_num [B, P], median [B, P], normal [B, P, 3],
    distortion [B, P], features [B, P, C].
    """
    B, P = px.shape
    L = T.shape[1]
    x = px[:, :, None]
    y = py[:, :, None]
    T0, T1, T2 = T[:, :, 0, :], T[:, :, 1, :], T[:, :, 2, :]            # rows, [B, L, 3]

    # Homogeneous ray-splat intersection: the planes x T2 - T0 and y T2 - T1 meet the splat plane
    # along the pixel ray, and their cross product p is the hit (u, v, 1) up to scale. p is
    # bilinear in (x, y): p = x (T1 x T2) + y (T2 x T0) + T0 x T1, so one batched matmul gives it.
    ones = torch.ones_like(px)
    xy1 = torch.stack([px, py, ones], dim=-1)                               # [B, P, 3]
    coef = torch.stack([torch.linalg.cross(T1, T2), torch.linalg.cross(T2, T0), torch.linalg.cross(T0, T1)],
                       dim=1)                                               # [B, 3 (x, y, 1), L, 3 (k)]
    p = torch.bmm(xy1, coef.transpose(2, 3).reshape(B, 3, 3 * L)).view(B, P, 3, L)
    p0, p1, p2 = p[:, :, 0], p[:, :, 1], p[:, :, 2]                         # [B, P, L]
    with torch.no_grad():
        # Edge-on test |p2| > eps |hx||hy| (squared: no sqrt). |hx|^2 = x^2 |T2|^2 - 2 x T0.T2 + |T0|^2
        # (same for y), clamped at 0 against float cancellation; the test itself has no gradient.
        Td = T.detach()
        T0d, T1d, T2d = Td[:, :, 0, :], Td[:, :, 1, :], Td[:, :, 2, :]
        t22 = (T2d * T2d).sum(-1)
        hxc = torch.stack([t22, -2 * (T0d * T2d).sum(-1), (T0d * T0d).sum(-1)], 1)   # [B, 3, L]
        hyc = torch.stack([t22, -2 * (T1d * T2d).sum(-1), (T1d * T1d).sum(-1)], 1)
        pxd, pyd, onesd = px.detach(), py.detach(), ones.detach()
        hx_sq = torch.bmm(torch.stack([pxd * pxd, pxd, onesd], -1), hxc).clamp(min=0)   # [B, P, L]
        hy_sq = torch.bmm(torch.stack([pyd * pyd, pyd, onesd], -1), hyc).clamp(min=0)
        p2d = p2.detach()
        hit = (p2d * p2d) > (EDGE_ON_EPS ** 2) * hx_sq * hy_sq
    p2s = torch.where(hit, p2, torch.ones_like(p2))
    # |u|, |v| <= 1 / EDGE_ON_EPS for a true hit; the clamp only guards float32 rounding (an
    # overflowing u^2 would turn the zero gradient of an invalid hit into NaN).
    bound = 1.0 / EDGE_ON_EPS
    u = torch.where(hit, (p0 / p2s).clamp(-bound, bound), torch.zeros_like(p0))
    v = torch.where(hit, (p1 / p2s).clamp(-bound, bound), torch.zeros_like(p1))
    rho3 = u * u + v * v
    z3 = T[:, None, :, 2, 0] * u + T[:, None, :, 2, 1] * v + T[:, None, :, 2, 2]
    valid3 = hit & (rho3 <= CHI * CHI) & (z3 > near)
    g3 = torch.where(valid3, torch.exp(-0.5 * rho3), torch.zeros_like(rho3))

    # Object-space low-pass fallback (screen-space disk around the projected centre).
    dx = x - center[:, None, :, 0]
    dy = y - center[:, None, :, 1]
    rho2 = dx * dx + dy * dy
    valid2 = rho2 <= LOWPASS_RHO2_MAX
    g2 = torch.where(valid2, torch.exp(-rho2), torch.zeros_like(rho2))

    use3 = valid3 & (g3 >= g2)
    g = torch.where(use3, g3, g2)
    d = torch.where(use3, z3, depth_key[:, None, :].expand_as(z3))
    alpha = torch.clamp(opac[:, None, :] * g, max=ALPHA_MAX)
    keep = real[:, None, :] & (alpha >= ALPHA_MIN)
    a = torch.where(keep, alpha, torch.zeros_like(alpha))
    blended = keep & (torch.cumprod(1 - a.detach(), dim=-1) >= T_STOP)
    a = torch.where(blended, a, torch.zeros_like(a))
    trans_incl = torch.cumprod(1 - a, dim=-1)
    trans_excl = torch.cat([torch.ones_like(trans_incl[..., :1]), trans_incl[..., :-1]], dim=-1)
    w = a * trans_excl                                             # [B, P, L]

    rgb = torch.einsum("bpl,blc->bpc", w, colors)
    alpha_out = 1 - trans_incl[..., -1]
    depth_num = (w * d).sum(-1)
    normal = torch.einsum("bpl,blc->bpc", w, normal_c)

    # Median: the last blended surfel whose transmittance before it is still above 0.5.
    before_half = blended & (trans_excl > 0.5)
    slot = torch.arange(1, L + 1, device=w.device)
    last = (before_half * slot).amax(-1) if L else torch.zeros(w.shape[:2], dtype=torch.long, device=w.device)
    median = torch.gather(d, -1, (last - 1).clamp(min=0)[..., None])[..., 0]
    median = torch.where(last > 0, median, torch.zeros_like(median))

    # 2DGS depth distortion, sum_{i>j} w_i w_j (m_i - m_j)^2 with NDC depth m, in one pass.
    d_safe = torch.where(blended, d, torch.full_like(d, far))
    m = far * (d_safe - near) / ((far - near) * d_safe)
    wm = w * m
    A = torch.cumsum(w, -1) - w
    D = torch.cumsum(wm, -1) - wm
    D2 = torch.cumsum(wm * m, -1) - wm * m
    distortion = (w * (m * m * A + D2 - 2 * m * D)).sum(-1)

    if feats.shape[-1] == 0:
        features = w.new_zeros(w.shape[:2] + (0,))
    else:
        wf = w
        if topk is not None and topk < L:
            # Stable descending sort: among equal weights the earlier (front) surfel wins.
            top = torch.sort(w.detach(), dim=-1, descending=True, stable=True).indices[..., :topk]
            sel = torch.zeros_like(blended).scatter(-1, top, True)
            wf = torch.where(sel, w, torch.zeros_like(w))
        features = torch.einsum("bpl,blc->bpc", wf, feats)
    return rgb, alpha_out, depth_num, median, normal, distortion, features


def rasterize_reference(proj: Projected, opacities: torch.Tensor, colors: torch.Tensor,
                        features: torch.Tensor | None, width: int, height: int,
                        topk: int | None = None, tiles: str = "precise", near: float = 0.2,
                        far: float = 1000.0, background: torch.Tensor | None = None,
                        chunk_evals: int = DEFAULT_CHUNK_EVALS) -> RenderOutput:
    """Stages 2-3 of SPEC.md in torch. proj: stage-1 output for N surfels; opacities [N],
    colors [N, 3], features [N, C] or None, background [3] or None. Returns a RenderOutput."""
    device, dtype = colors.device, colors.dtype
    n = colors.shape[0]
    if features is None:
        features = colors.new_zeros(n, 0)
    C = features.shape[1]
    box = proj.box_precise if tiles == "precise" else proj.box_circle
    bins = bin_surfels(box, proj.depth_key, width, height)
    counts = bins.counts
    n_tiles = bins.tiles_x * bins.tiles_y
    n_pairs = int(bins.surfel_ids.numel())

    # Longest lists first, so each chunk pads to a similar length.
    active = torch.nonzero(counts > 0).squeeze(1)
    active = active[torch.sort(counts[active], descending=True, stable=True).indices]
    active_counts = counts[active].tolist()

    local = torch.arange(TILE * TILE, device=device)
    need_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (proj.T, proj.center, proj.depth_key, proj.normal_c, opacities, colors, features))

    # Chunks of (tiles, pixels of those tiles) holding about `chunk_evals` (pixel, slot) pairs; a tile
    # whose list alone exceeds the budget is split by pixels, so memory is bounded for any scene.
    chunks = []
    i = 0
    while i < len(active_counts):
        L = active_counts[i]
        size = max(1, chunk_evals // (TILE * TILE * L))
        if size > 1 or TILE * TILE * L <= chunk_evals:
            chunks.append((active[i:i + size], L, local))
        else:
            step = max(1, chunk_evals // L)
            chunks += [(active[i:i + 1], L, local[j:j + step]) for j in range(0, TILE * TILE, step)]
        i += size
    if not chunks:
        # Nothing binned: one empty batch keeps the outputs attached to the inputs' graph, so a loss
        # on an empty view still backpropagates (zero gradients) instead of raising.
        chunks.append((active, 1, local))

    pix_chunks, out_chunks = [], []
    evaluated = 0
    for tids, L, pixels in chunks:
        tx, ty = tids % bins.tiles_x, tids // bins.tiles_x
        px = tx[:, None] * TILE + pixels % TILE                    # [B, P]
        py = ty[:, None] * TILE + pixels // TILE
        inside = (px < width) & (py < height)
        slots = torch.arange(L, device=device)
        real = slots[None, :] < counts[tids][:, None]             # [B, L]
        idx = torch.where(real, bins.offsets[tids][:, None] + slots, torch.zeros_like(real, dtype=torch.long))
        sid = bins.surfel_ids[idx]                                 # [B, L]
        evaluated += int((inside.sum(1) * counts[tids]).sum())
        args = (px.to(dtype), py.to(dtype), proj.T[sid], proj.center[sid], proj.depth_key[sid],
                proj.normal_c[sid], opacities[sid], colors[sid], features[sid], real)
        if need_grad and len(chunks) > 1:
            outs = checkpoint(blend_tiles, *args, near, far, topk, use_reentrant=False)
        else:
            outs = blend_tiles(*args, near, far, topk)
        flat = inside.reshape(-1)
        pix_chunks.append((py * width + px).reshape(-1)[flat])
        out_chunks.append([o.reshape((o.shape[0] * o.shape[1],) + o.shape[2:])[flat] for o in outs])

    hw = height * width
    names = ["rgb", "alpha", "depth_num", "median", "normal", "distortion", "features"]
    widths = [3, None, None, None, 3, None, C]
    full = {}
    pix = torch.cat(pix_chunks)
    for k, (name, c) in enumerate(zip(names, widths)):
        shape = (hw,) if c is None else (hw, c)
        base = torch.zeros(shape, dtype=dtype, device=device)
        full[name] = base.index_copy(0, pix, torch.cat([o[k] for o in out_chunks]))
    alpha = full["alpha"]
    rgb = full["rgb"]
    if background is not None:
        rgb = rgb + (1 - alpha)[:, None] * background.to(dtype)
    has = alpha > 1e-6
    depth = torch.where(has, full["depth_num"] / torch.where(has, alpha, torch.ones_like(alpha)),
                        torch.zeros_like(alpha))
    stats = {
        "tile_pairs": n_pairs,
        "pairs_per_tile": n_pairs / max(n_tiles, 1),
        "max_pairs_per_tile": int(counts.max()) if n_tiles else 0,
        "evaluated": evaluated,
        "culled": int(n - torch.unique(bins.surfel_ids).numel()),
        "chunks": len(chunks),
        "backend": "reference",
        "tiles": tiles,
    }
    H, W = height, width
    return RenderOutput(
        rgb=rgb.reshape(H, W, 3), alpha=alpha.reshape(H, W), depth=depth.reshape(H, W),
        median_depth=full["median"].reshape(H, W), normal=full["normal"].reshape(H, W, 3),
        distortion=full["distortion"].reshape(H, W), features=full["features"].reshape(H, W, C),
        stats=stats)
