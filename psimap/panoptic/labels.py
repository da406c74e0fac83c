"""3D-consistent 2D panoptic labels rendered from a scene's hard per-surfel labels (`psimap labels`).

Each pixel takes the instance (and class) of the surfels that blend into it: the hard ids are
rendered as one-hot feature channels (Top-K blending of the renderer) and the pixel label is the
channel of largest blended weight. Because the ids live on the surfels, a pixel's id is the 3D
instance id, the same in every frame. Pixels the surfels do not cover (alpha <= 0.5) stay void.

Silhouettes: the renderer widens every splat to at least its screen-space low-pass filter
(sigma = sqrt(2)/2 px, render/SPEC.md). Surfels smaller than that on screen draw a silhouette set by
the filter, not by the geometry; so is every surfel seen edge-on at an object's limb, whatever its
size. A front object bleeds ~1 px over what lies behind it, which is most of a 5 px object's
mask (GT-surfel oracle at 160x120: ball IoU 0.42, mug 0.44, scene PQ 0.678). Labels are therefore
rendered with ss x ss samples per pixel and the one-hot weights box-filtered back to the pixel:
the filter's bleed shrinks to 1/ss px (oracle PQ 0.870 at ss = 2).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from psimap import PsimapError

# One-hot channels rendered per pass: bounds the [H, W, C] feature image (and the per-surfel
# one-hot) however many instances a scene holds.
CHANNELS_PER_PASS = 64
MIN_ALPHA = 0.5
# Samples per pixel side of label rendering. The filter's bleed scales as 1/ss; measured on the
# GT-surfel oracle (`benchmarks/panoptic.py --oracle-sweep`, 160x120, seed 0; RESULTS.md): scene PQ
# 0.678 / 0.870 / 0.889 / 0.897 at ss = 1 / 2 / 3 / 4, the render cost growing up to ss^2 (timings on
# a loaded CPU were 0.69 / 0.81 / 1.06 / 1.59 s per frame); 2 takes most of the gain.
DEFAULT_SUPERSAMPLE = 2


def instance_classes(scene) -> dict[int, int]:
    """{instance id: class id} by majority vote of the instance's surfels' semantic ids (void ignored)."""
    inst = scene.instance_ids().numpy().astype(np.int64)
    sem = scene.semantic_ids().numpy().astype(np.int64)
    sel = (inst > 0) & (sem > 0)
    if not sel.any():
        return {}
    pairs, counts = np.unique(np.stack([inst[sel], sem[sel]], 1), axis=0, return_counts=True)
    # Sort by (instance, count) so the last row of each instance is its majority class.
    order = np.lexsort((counts, pairs[:, 0]))
    pairs = pairs[order]
    last = np.r_[pairs[1:, 0] != pairs[:-1, 0], True]
    return {int(i): int(c) for i, c in pairs[last]}


def _argmax_ids(scene, groups: list[np.ndarray], viewmat, K, width: int, height: int, topk, backend,
                ss: int = 1):
    """Per pixel and per id group, the id whose one-hot channel has the largest blended weight.

    groups: id arrays [N] int64 (e.g. instance ids, class ids), rendered together as one channel
    list (chunked by CHANNELS_PER_PASS) -> ([label [H, W] int64 per group], alpha [H, W]). The id 0
    (none) is a channel too, so a stuff surface in front of an object hides it. ss: render at
    ss x ss samples per pixel and average weights and alpha over each pixel's samples.
    """
    import torch

    from psimap.camera import supersample_intrinsics
    from psimap.render import rasterize

    s = scene.surfels
    uniq = [np.unique(g, return_inverse=True) for g in groups]
    values = [u[0] for u in uniq]
    inverse = [torch.as_tensor(u[1].reshape(-1), dtype=torch.long) for u in uniq]
    offsets = np.cumsum([0] + [len(v) for v in values])
    best = [torch.full((height, width), -1.0) for _ in groups]
    label = [torch.zeros((height, width), dtype=torch.long) for _ in groups]
    alpha = None
    n = int(s["means"].shape[0])
    K = torch.as_tensor(supersample_intrinsics(K.numpy(), ss), dtype=K.dtype)    # validates ss
    ss = int(ss)
    for start in range(0, int(offsets[-1]), CHANNELS_PER_PASS):
        stop = min(int(offsets[-1]), start + CHANNELS_PER_PASS)
        # Surfels without a channel in this chunk still occlude (zero feature rows).
        onehot = torch.zeros(n, stop - start)
        for g, inv in enumerate(inverse):
            ch = inv + int(offsets[g])
            inside = (ch >= start) & (ch < stop)
            onehot[inside.nonzero().flatten(), ch[inside] - start] = 1.0
        with torch.no_grad():
            out = rasterize(s["means"].float(), s["quats"].float(), s["scales"].float(),
                            s["opacities"].float(), s["colors"].float(), viewmat, K, width * ss, height * ss,
                            features=onehot, topk=topk, backend=backend)
        feats, alpha = out.features, out.alpha
        if ss > 1:      # box filter: each pixel averages its ss x ss samples
            feats = feats.reshape(height, ss, width, ss, -1).mean((1, 3))
            alpha = alpha.reshape(height, ss, width, ss).mean((1, 3))
        for g in range(len(groups)):
            lo, hi = max(start, int(offsets[g])), min(stop, int(offsets[g + 1]))
            if lo >= hi:
                continue
            w, j = feats[..., lo - start:hi - start].max(-1)
            better = w > best[g]
            best[g] = torch.where(better, w, best[g])
            label[g] = torch.where(better, j + (lo - int(offsets[g])), label[g])
    ids = [torch.as_tensor(v, dtype=torch.long)[lab].numpy() for v, lab in zip(values, label)]
    return ids, alpha.numpy()


def render_labels(scene, K, c2w, width: int, height: int, topk: int | None = None,
                  backend: str = "auto", supersample: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(instance [H, W] int64, semantic [H, W] int64) of the scene seen by one camera.

    K [3, 3], c2w [4, 4] OpenCV camera-to-world. Ids are the scene's hard labels
    (`Scene.instance_ids()`, `Scene.semantic_ids()`); 0 where nothing covers the pixel
    (alpha <= 0.5) or the covering surfels carry no label. A pixel of an instance takes the
    instance's class (majority vote of its surfels, `instance_classes`). topk: blend the one-hot labels over the
    K largest weights per pixel (None = all). supersample: samples per pixel side (None =
    DEFAULT_SUPERSAMPLE; 1 = one sample per pixel, ss^2 times cheaper, silhouettes ~1 px wider).
    """
    import torch

    width, height = int(width), int(height)
    if width < 1 or height < 1:
        raise PsimapError(f"render_labels: image size must be positive, got {width}x{height}")
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
        raise PsimapError("render_labels: c2w must be a finite 4x4 camera-to-world matrix")
    empty = np.zeros((height, width), dtype=np.int64)
    if len(scene) == 0:
        return empty, empty.copy()
    viewmat = torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32)
    Kt = torch.as_tensor(np.asarray(K, dtype=np.float64), dtype=torch.float32)
    inst_ids = scene.instance_ids().numpy().astype(np.int64)
    sem_ids = scene.semantic_ids().numpy().astype(np.int64)
    ss = DEFAULT_SUPERSAMPLE if supersample is None else supersample
    (inst, sem), alpha = _argmax_ids(scene, [inst_ids, sem_ids], viewmat, Kt, width, height, topk, backend, ss)
    # One class per instance, as a COCO segment has: a pixel whose instance and class channels
    # were won by different surfels (a bottle's limb over the table) would otherwise form a
    # (table, bottle id) segment, a false positive of its own.
    votes = instance_classes(scene)
    if votes:
        lut = np.zeros(int(max(votes)) + 1, dtype=np.int64)
        lut[list(votes)] = list(votes.values())
        voted = lut[np.clip(inst, 0, len(lut) - 1)]
        sem = np.where((inst > 0) & (inst < len(lut)) & (voted > 0), voted, sem)
    covered = alpha > MIN_ALPHA
    return np.where(covered, inst, 0), np.where(covered, sem, 0)


def _views(scene, frames_or_data):
    """[(stem, K, c2w, width, height)] from a frame list, a DATA folder, or None (the scene's cameras)."""
    if frames_or_data is None:
        names = list(scene.cameras["names"])
        if not names:
            raise PsimapError("the scene has no cameras: give frames or a DATA folder to render")
        out = []
        for i, name in enumerate(names):
            K, c2w, w, h = scene.camera(i)
            out.append((str(name) or f"frame_{i:05d}", K, c2w, w, h))
        return out
    if isinstance(frames_or_data, (str, os.PathLike)):
        from psimap.data import load

        path = Path(frames_or_data)
        if not path.exists():
            raise PsimapError(f"no such data folder: {path}")
        frames_or_data = load(path)
    views = []
    for i in range(len(frames_or_data)):
        f = frames_or_data[i]
        views.append((f.name or f"frame_{i:05d}", np.asarray(f.K), np.asarray(f.c2w), f.width, f.height))
    if not views:
        raise PsimapError("no frames to render labels for")
    stems = [v[0] for v in views]
    if len(set(stems)) != len(stems):
        dup = next(s for s in stems if stems.count(s) > 1)
        raise PsimapError(f"two frames share the image stem {dup!r}: label files would collide")
    return views


def write_labels(scene, frames_or_data, out_dir, *, topk: int | None = None, backend: str = "auto",
                 progress: bool = False, overwrite: bool = False) -> Path:
    """Write 3D-consistent COCO panoptic labels of every view to `out_dir` (atomically).

    frames_or_data: a list / sequence of Frame, a DATA folder (its cameras and image stems), or None
    for the scene's own cameras. One PNG per view named after its image stem (segment id = 3D
    instance id; stuff: STUFF_OFFSET + class id) and `panoptic.json` (categories from the scene's
    class table; thing segments take their instance's class by majority vote). Returns the json path.
    overwrite: write into an `out_dir` psimap did not write (psimap.io_utils rules).
    """
    from tqdm import tqdm

    from psimap.io_utils import atomic_dir, check_output_dir
    from psimap.panoptic.coco import write_coco_panoptic

    if not scene.classes:
        raise PsimapError("the scene has no class table: it carries no panoptic labels to render")
    check_output_dir(out_dir, "labels", overwrite=overwrite)       # before the renders, not after
    views = _views(scene, frames_or_data)
    votes = instance_classes(scene)
    out_dir = Path(out_dir)

    def rendered():
        for stem, K, c2w, w, h in tqdm(views, desc="labels", unit="frame", disable=not progress):
            inst, sem = render_labels(scene, K, c2w, w, h, topk=topk, backend=backend)
            yield stem, inst, sem

    from psimap.threads import single_threaded

    # one small render per frame: spinning thread pools cost more than they give (psimap.threads)
    with single_threaded(), atomic_dir(out_dir, "labels", overwrite=overwrite) as tmp:
        write_coco_panoptic(tmp, rendered(), scene.classes, votes)
    return out_dir / "panoptic.json"


def has_labels(scene) -> bool:
    """Whether the scene carries panoptic labels (hard ids, or semantic logits / instance queries)."""
    s = getattr(scene, "surfels", None)
    if not isinstance(s, dict) or "semantic" not in s:
        return False
    return ("instance_id" in s or "semantic_id" in s or int(s["semantic"].shape[1]) > 0
            or int(scene.queries["feature"].shape[0]) > 0)


def cli_labels(opts) -> int:
    """`psimap labels scene.ckpt DATA --out DIR [--topk K]`."""
    from psimap.io_utils import check_output_dir
    from psimap.scene import load_scene

    ckpt = Path(opts.ckpt)
    if not ckpt.is_file():
        raise PsimapError(f"no such checkpoint: {ckpt}")
    check_output_dir(opts.out, "labels", overwrite=opts.overwrite, what="--out")
    scene = load_scene(ckpt)
    if not has_labels(scene):
        raise PsimapError(f"{ckpt}: the checkpoint has no panoptic labels (train with the panoptic field)")
    if opts.topk < 0:
        raise PsimapError(f"--topk must be >= 0 (0 = all), got {opts.topk}")
    path = write_labels(scene, opts.data, opts.out, topk=opts.topk or None, progress=True,
                        overwrite=opts.overwrite)
    import json

    meta = json.loads(Path(path).read_text())
    n_seg = sum(len(a["segments_info"]) for a in meta["annotations"])
    things = {s["id"] for a in meta["annotations"] for s in a["segments_info"]
              if s["category_id"] in {c["id"] for c in meta["categories"] if c["isthing"]}}
    print(f"wrote {len(meta['images'])} label PNGs + {path} ({n_seg} segments, {len(things)} 3D instances)")
    return 0
