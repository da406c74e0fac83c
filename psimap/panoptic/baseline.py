"""The naive multi-stage panoptic baseline the paper argues against (§4, "multi-stage pipelines").

Stage 1: every frame's 2D thing masks are lifted to 3D (mask pixels back-projected with depth) and
voxelised. Stage 2: the lifted masks are merged greedily, frame after frame, into global 3D
segments by voxel overlap (intersection over the smaller set, IoM, so a partial view of an object
still joins it); a final pass merges segments that overlap each other the same way, and segments
seen in fewer than `min_frames` frames are dropped as noise. Stage 3: every voxel takes the segment
(or "no instance") that most frames gave it and the class most pixels gave it, and every surfel
takes the labels of its nearest labelled voxel. Instance classes are the pixel-weighted majority of
their masks' classes.

Each decision is final once made (no joint optimisation over views), which is what makes such
pipelines brittle with noisy masks: a merged mask glues two objects for good, a split mask of a
large object whose halves never overlap spawns two instances.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psimap import PsimapError
from psimap.transforms import depth_to_world


@dataclass
class BaselineConfig:
    voxel: float = 0.0               # voxel edge in metres; 0 = two pixel footprints at the median depth
    match_iom: float = 0.5           # a lifted mask joins the segment it overlaps most if IoM >= this
    min_frames: int = 2              # segments supported by fewer frames are dropped
    min_mask_fraction: float = 0.002  # 2D masks smaller than this fraction of the image are ignored
    max_surfel_distance: float = 1.0  # in voxels: surfels farther from any labelled voxel stay unlabelled


def _thing_ids(classes) -> set[int]:
    return {int(c["id"] if isinstance(c, dict) else c.id) for c in classes
            if (c["isthing"] if isinstance(c, dict) else c.isthing)}


def _voxel_size(frames) -> float:
    """Two pixel footprints at the median depth of the sequence (what the masks can resolve)."""
    fp = []
    for f in frames[:: max(1, len(frames) // 10)]:
        d = f.depth[f.depth > 0]
        if d.size:
            fp.append(float(np.median(d)) / float(0.5 * (f.K[0, 0] + f.K[1, 1])))
    if not fp:
        raise PsimapError("baseline: no frame has valid depth to lift masks into 3D")
    return 2.0 * float(np.median(fp))


def _keys(ijk: np.ndarray) -> np.ndarray:
    """Voxel indices [P, 3] -> int64 keys (21 bits per axis, offset so negatives fit)."""
    v = ijk.astype(np.int64) + (1 << 20)
    if v.size and (v.min() < 0 or v.max() >= (1 << 21)):
        raise PsimapError("baseline: scene too large for the voxel size (more than 2^21 voxels per axis)")
    return (v[:, 0] << 42) | (v[:, 1] << 21) | v[:, 2]


def _centres(keys: np.ndarray, voxel: float) -> np.ndarray:
    ijk = np.stack([keys >> 42, (keys >> 21) & ((1 << 21) - 1), keys & ((1 << 21) - 1)], 1) - (1 << 20)
    return (ijk + 0.5) * voxel


def _mode_by_key(keys: np.ndarray, labels: np.ndarray, weights: np.ndarray | None = None):
    """For each distinct key, the label of largest total weight: (keys [U], label [U])."""
    if keys.size == 0:
        return keys, labels
    pairs, inv = np.unique(np.stack([keys, labels], 1), axis=0, return_inverse=True)
    w = np.bincount(inv.ravel(), weights=weights, minlength=len(pairs))
    order = np.lexsort((w, pairs[:, 0]))              # per key ascending weight: the last row wins
    pairs = pairs[order]
    last = np.r_[pairs[1:, 0] != pairs[:-1, 0], True]
    return pairs[last, 0], pairs[last, 1]


class _Segments:
    """Global 3D segments: sorted voxel-key arrays, frames seen, class votes (pixels per class)."""

    def __init__(self):
        self.voxels: list[np.ndarray] = []
        self.frames: list[int] = []
        self.votes: list[dict[int, int]] = []

    def best_match(self, keys: np.ndarray) -> tuple[int, float]:
        best, best_iom = -1, 0.0
        for j, vox in enumerate(self.voxels):
            inter = np.intersect1d(keys, vox, assume_unique=True).size
            if inter:
                iom = inter / min(keys.size, vox.size)
                if iom > best_iom:
                    best, best_iom = j, iom
        return best, best_iom

    def add(self, keys: np.ndarray, cls: int, pixels: int) -> int:
        self.voxels.append(keys)
        self.frames.append(1)
        self.votes.append({cls: pixels})
        return len(self.voxels) - 1

    def merge_into(self, j: int, keys: np.ndarray, cls: int, pixels: int, new_frame: bool) -> None:
        self.voxels[j] = np.union1d(self.voxels[j], keys)
        self.frames[j] += int(new_frame)
        self.votes[j][cls] = self.votes[j].get(cls, 0) + pixels


def baseline_panoptic(means, frames, classes, cfg: BaselineConfig | None = None, *,
                      progress: bool = False) -> dict:
    """Per-surfel labels from per-frame 2D masks by lift -> greedy 3D merge -> nearest voxel.

    means: [N, 3] surfel positions (numpy or torch); frames: sequence of Frame with depth and
    per-frame pseudo-labels (instance ids need not agree across frames); classes: ClassInfo / dicts.
    Returns {"instance_id": [N] int64 (0 = none, 1..I), "semantic_id": [N] int64 (0 = void),
    "instance_class": {id: class id}, "segments": I, "voxel": voxel size}.
    """
    from scipy.spatial import cKDTree
    from tqdm import tqdm

    cfg = cfg or BaselineConfig()
    means = np.asarray(means.detach().cpu().numpy() if hasattr(means, "detach") else means, dtype=np.float64)
    if means.ndim != 2 or means.shape[1] != 3:
        raise PsimapError(f"baseline: means must be [N, 3], got {means.shape}")
    if not len(frames):
        raise PsimapError("baseline: no frames")
    things = _thing_ids(classes)
    voxel = cfg.voxel if cfg.voxel > 0 else _voxel_size(frames)
    segs = _Segments()
    inst_votes: list[tuple[np.ndarray, np.ndarray]] = []     # (voxel keys, segment index or -1 = none)
    sem_votes: list[tuple[np.ndarray, np.ndarray]] = []      # (voxel keys of pixels, class id)
    for i in tqdm(range(len(frames)), desc="baseline", unit="frame", disable=not progress):
        f = frames[i]
        depth = np.asarray(f.depth, dtype=np.float64)
        points, ys, xs = depth_to_world(depth, f.K, f.c2w)
        if len(points) == 0:
            continue
        keys = _keys(np.floor(points / voxel))
        sem = np.zeros(len(ys), np.int64) if f.semantic is None else np.asarray(f.semantic, np.int64)[ys, xs]
        inst = np.zeros(len(ys), np.int64) if f.instance is None else np.asarray(f.instance, np.int64)[ys, xs]
        labelled = sem > 0
        sem_votes.append((keys[labelled], sem[labelled]))
        in_thing = np.zeros(len(ys), bool)
        min_px = max(1, int(cfg.min_mask_fraction * depth.size))
        ids, counts = np.unique(inst[inst > 0], return_counts=True)
        touched = set()
        for mid, n in zip(ids.tolist(), counts.tolist()):
            if n < min_px:
                continue
            sel = inst == mid
            cls_px = sem[sel]
            cls = int(np.bincount(cls_px).argmax()) if cls_px.size else 0
            semantic_known = f.semantic is not None
            if semantic_known and cls not in things:    # stuff is semantic only
                continue
            mkeys = np.unique(keys[sel])
            j, iom = segs.best_match(mkeys)
            if j >= 0 and iom >= cfg.match_iom:
                segs.merge_into(j, mkeys, cls if semantic_known else 0, n, new_frame=j not in touched)
            else:
                j = segs.add(mkeys, cls if semantic_known else 0, n)
            touched.add(j)
            in_thing |= sel
            inst_votes.append((mkeys, np.full(mkeys.size, j)))
        none_keys = np.unique(keys[~in_thing])
        inst_votes.append((none_keys, np.full(none_keys.size, -1)))

    # Final pass: segments that overlap each other as much as a mask would have to are one object.
    parent = list(range(len(segs.voxels)))

    def root(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    changed = True
    while changed:
        changed = False
        roots = sorted({root(a) for a in range(len(parent))}, key=lambda a: -segs.voxels[a].size)
        for ai, a in enumerate(roots):
            for b in roots[ai + 1:]:
                if root(a) != a or root(b) != b:
                    continue
                inter = np.intersect1d(segs.voxels[a], segs.voxels[b], assume_unique=True).size
                if inter and inter / min(segs.voxels[a].size, segs.voxels[b].size) >= cfg.match_iom:
                    parent[b] = a
                    segs.voxels[a] = np.union1d(segs.voxels[a], segs.voxels[b])
                    segs.frames[a] += segs.frames[b]
                    for c, v in segs.votes[b].items():
                        segs.votes[a][c] = segs.votes[a].get(c, 0) + v
                    changed = True

    roots = sorted({root(a) for a in range(len(parent)) if segs.frames[root(a)] >= cfg.min_frames})
    new_id = {r: k + 1 for k, r in enumerate(roots)}
    seg_to_id = np.array([new_id.get(root(a), 0) for a in range(len(parent))] + [0], dtype=np.int64)
    instance_class = {new_id[r]: int(max(segs.votes[r].items(), key=lambda kv: kv[1])[0]) for r in roots}

    n = len(means)
    out_inst = np.zeros(n, np.int64)
    out_sem = np.zeros(n, np.int64)
    if inst_votes and n:
        k = np.concatenate([v[0] for v in inst_votes])
        s = seg_to_id[np.concatenate([v[1] for v in inst_votes])]   # -1 (none) indexes the trailing 0
        vkeys, vinst = _mode_by_key(k, s)
        tree = cKDTree(_centres(vkeys, voxel))
        dist, nn = tree.query(means, distance_upper_bound=cfg.max_surfel_distance * voxel)
        hit = np.isfinite(dist)
        out_inst[hit] = vinst[nn[hit]]
        if sem_votes:
            sk = np.concatenate([v[0] for v in sem_votes])
            if sk.size:
                skeys, ssem = _mode_by_key(sk, np.concatenate([v[1] for v in sem_votes]))
                st = cKDTree(_centres(skeys, voxel))
                d2, nn2 = st.query(means, distance_upper_bound=cfg.max_surfel_distance * voxel)
                h2 = np.isfinite(d2)
                out_sem[h2] = ssem[nn2[h2]]
        # An instance's surfels carry its class (the pipeline's final, per-segment vote).
        cls_of = np.zeros(len(roots) + 1, np.int64)
        for iid, c in instance_class.items():
            cls_of[iid] = c
        has = out_inst > 0
        out_sem[has & (cls_of[out_inst] > 0)] = cls_of[out_inst][has & (cls_of[out_inst] > 0)]
    present = set(np.unique(out_inst[out_inst > 0]).tolist())
    # Renumber 1..I over the instances that kept at least one surfel.
    lut = np.zeros(len(roots) + 1, np.int64)
    for k, iid in enumerate(sorted(present)):
        lut[iid] = k + 1
    out_inst = lut[out_inst]
    instance_class = {int(lut[i]): c for i, c in instance_class.items() if i in present}
    return {"instance_id": out_inst, "semantic_id": out_sem, "instance_class": instance_class,
            "segments": len(present), "voxel": float(voxel)}
