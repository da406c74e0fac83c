"""Sensor and pseudo-label noise for the synthetic benchmark scenes.

Depth: a structured-light sensor model (noise std growing with the square of the distance, Nguyen et
al. 2012 for the Kinect), invalid pixels at grazing angles, depth edges, out of range and at random.
Labels: what an open-vocabulary 2D segmenter gets wrong: instance ids with no meaning across frames
(always), touching instances merged, instances split, objects missed, classes flipped and boundaries
that wobble by a few pixels. Every function takes its `rng` so a seed fixes the result.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class DepthNoise:
    """Parameters of the depth sensor model (metres; rates are per-pixel probabilities)."""

    sigma0: float = 0.0012        # std at the sweet spot `z0`
    sigma_quad: float = 0.0019    # growth per (z - z0)^2
    z0: float = 0.4
    min_range: float = 0.25
    max_range: float = 6.0
    grazing_cos: float = 0.12     # |cos(incidence)| below this -> no return
    edge_jump: float = 0.08       # relative depth jump that marks a depth edge
    edge_dropout: float = 0.4
    dropout: float = 0.005

    @classmethod
    def degraded(cls, noise: float = 1.0, dropout: float | None = None) -> "DepthNoise":
        """The default sensor with its noise std scaled by `noise` (both terms) and, when given, the
        random per-pixel dropout rate replaced by `dropout` (a sparser sensor). Benchmarks use it
        for a depth-quality axis; degraded(1.0) equals DepthNoise()."""
        if not (noise >= 0 and np.isfinite(noise)):
            raise ValueError(f"depth noise factor must be a finite value >= 0, got {noise}")
        base = cls()
        if dropout is not None and not 0.0 <= dropout < 1.0:
            raise ValueError(f"depth dropout must lie in [0, 1), got {dropout}")
        return cls(sigma0=base.sigma0 * noise, sigma_quad=base.sigma_quad * noise,
                   dropout=base.dropout if dropout is None else float(dropout))


def depth_sigma(z: np.ndarray, p: DepthNoise) -> np.ndarray:
    """Noise std [same shape as z] in metres for true depths `z`."""
    return p.sigma0 + p.sigma_quad * (z - p.z0) ** 2


def noisy_depth(depth: np.ndarray, cos_incidence: np.ndarray, rng: np.random.Generator,
                p: DepthNoise | None = None) -> np.ndarray:
    """Sensor depth from true depth.

    depth: [..., H, W] metres (0 = no surface); cos_incidence: [..., H, W] |cos| between ray and
    surface normal. Returns [..., H, W] float32 metres, 0 = invalid.
    """
    p = p or DepthNoise()
    z = np.asarray(depth, dtype=np.float64)
    valid = (z > 0) & np.isfinite(z)
    z = np.where(valid, z, 0.0)  # NaN / inf / negative: invalid, and kept out of the arithmetic
    out = np.where(valid, z + rng.standard_normal(z.shape) * depth_sigma(z, p), 0.0)
    bad = ~valid | (z < p.min_range) | (z > p.max_range) | (cos_incidence < p.grazing_cos)
    # Depth edges: a real sensor loses the pixels where the surface jumps (shadowing, mixed pixels).
    zc = np.where(valid, z, np.inf)
    jump = np.zeros(z.shape, dtype=bool)
    for axis in (-1, -2):
        a = np.swapaxes(zc, axis, -1)
        with np.errstate(invalid="ignore"):  # inf - inf between two invalid pixels
            rel = np.abs(np.diff(a, axis=-1)) / np.minimum(a[..., 1:], a[..., :-1])
        e = np.nan_to_num(rel, nan=0.0, posinf=0.0) > p.edge_jump
        edge = np.zeros(a.shape, dtype=bool)
        edge[..., 1:] |= e
        edge[..., :-1] |= e
        jump |= np.swapaxes(edge, axis, -1)
    bad |= jump & (rng.random(z.shape) < p.edge_dropout)
    bad |= rng.random(z.shape) < p.dropout
    out[bad] = 0.0
    return np.maximum(out, 0.0).astype(np.float32)


def perturb_pose(c2w: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """c2w: [4, 4]; returns it with a random rotation (std `sigma` rad per axis) and translation
    (std `sigma` m per axis) applied, as a drifting odometry would give."""
    from scipy.spatial.transform import Rotation

    if sigma <= 0:
        return c2w.copy()
    out = c2w.copy()
    out[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, sigma, 3)).as_matrix() @ c2w[:3, :3]
    out[:3, 3] = c2w[:3, 3] + rng.normal(0.0, sigma, 3)
    return out


@dataclass
class LabelNoise:
    """Rates of pseudo-label errors (each a probability per instance or per touching pair)."""

    merge: float = 0.0        # per pair of instances touching in the image
    split: float = 0.0        # per instance
    miss: float = 0.0         # per instance
    flip: float = 0.0         # per instance: class replaced by another thing class
    jitter_px: float = 0.0    # amplitude of the boundary wobble, pixels

    @classmethod
    def from_rate(cls, rate: float) -> "LabelNoise":
        """One knob: `rate` sets merges, splits, misses and flips; boundaries wobble by ~2 px."""
        rate = float(np.clip(rate, 0.0, 1.0))
        return cls(merge=rate, split=rate / 2, miss=rate / 3, flip=rate / 3,
                   jitter_px=2.0 if rate > 0 else 0.0)


def touching_pairs(labels: np.ndarray) -> list[tuple[int, int]]:
    """Pairs (a < b) of distinct non-zero labels that are 4-neighbours somewhere in labels [H, W]."""
    pairs = set()
    for a, b in ((labels[:, 1:], labels[:, :-1]), (labels[1:, :], labels[:-1, :])):
        m = (a != b) & (a > 0) & (b > 0)
        lo = np.minimum(a[m], b[m]).astype(np.int64)
        hi = np.maximum(a[m], b[m]).astype(np.int64)
        pairs.update(zip(lo.tolist(), hi.tolist()))
    return sorted(pairs)


def _smooth_field(shape: tuple[int, int], amplitude: float, rng: np.random.Generator) -> np.ndarray:
    """Low-frequency random displacement [H, W] in pixels (cells of ~8 px, bilinear)."""
    from scipy.ndimage import zoom

    h, w = shape
    coarse = rng.uniform(-amplitude, amplitude, size=(max(2, h // 8 + 2), max(2, w // 8 + 2)))
    f = zoom(coarse, (h / coarse.shape[0], w / coarse.shape[1]), order=1)
    return f[:h, :w]


def pseudo_labels(gt_instance: np.ndarray, gt_semantic: np.ndarray, thing_classes: list[int],
                  noise: LabelNoise, rng: np.random.Generator):
    """Per-frame 2D pseudo-labels from the ground truth.

    gt_instance: [H, W] consistent instance ids (0 = stuff / none); gt_semantic: [H, W] class ids.
    thing_classes: class ids that flips may pick. Returns (instance [H, W] uint16 with ids
    1..n in random order, semantic [H, W] uint16, stats dict of error counts).
    """
    inst = gt_instance.astype(np.int64)
    sem = gt_semantic.astype(np.int64).copy()
    present = [int(i) for i in np.unique(inst) if i > 0]
    stats = {"instances": len(present), "merged": 0, "split": 0, "missed": 0, "flipped": 0}
    if not present and noise.jitter_px <= 0:
        return np.zeros_like(gt_instance, dtype=np.uint16), sem.astype(np.uint16), stats
    area = {i: int(c) for i, c in zip(*np.unique(inst[inst > 0], return_counts=True))}
    cls_of = {i: int(np.bincount(sem[inst == i]).argmax()) for i in present}

    # Merges: union-find over touching pairs; the merged segment takes its largest part's class.
    parent = {i: i for i in present}

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    if noise.merge > 0:
        for a, b in touching_pairs(inst):
            if rng.random() < noise.merge and root(a) != root(b):
                parent[root(b)] = root(a)
                stats["merged"] += 1
    seg = inst.copy()
    groups: dict[int, list[int]] = {}
    for i in present:
        groups.setdefault(root(i), []).append(i)
    for r, members in groups.items():
        if len(members) > 1:
            main = max(members, key=lambda i: area[i])
            m = np.isin(inst, members)
            seg[m] = r
            sem[m] = cls_of[main]

    next_id = (max(present) if present else 0) + 1
    h, w = seg.shape
    yy, xx = np.mgrid[0:h, 0:w]
    for s in sorted(groups):
        m = seg == s
        if noise.miss > 0 and rng.random() < noise.miss:
            seg[m] = 0
            sem[m] = 0
            stats["missed"] += 1
            continue
        if noise.flip > 0 and rng.random() < noise.flip and len(thing_classes) > 1:
            here = int(np.bincount(sem[m]).argmax())
            others = [c for c in thing_classes if c != here]
            sem[m] = others[rng.integers(len(others))]
            stats["flipped"] += 1
        if noise.split > 0 and rng.random() < noise.split and m.sum() >= 8:
            # Cut by a random line through the centroid, as a segmenter splitting a part off.
            ang = rng.uniform(0, np.pi)
            side = (xx - xx[m].mean()) * np.cos(ang) + (yy - yy[m].mean()) * np.sin(ang) > 0
            cut = m & side
            if 0 < cut.sum() < m.sum():
                seg[cut] = next_id
                next_id += 1
                stats["split"] += 1

    if noise.jitter_px > 0:
        from scipy.ndimage import map_coordinates

        dy = _smooth_field((h, w), noise.jitter_px, rng)
        dx = _smooth_field((h, w), noise.jitter_px, rng)
        coords = np.stack([np.clip(yy + dy, 0, h - 1), np.clip(xx + dx, 0, w - 1)])
        seg = map_coordinates(seg, coords, order=0, mode="nearest")
        sem = map_coordinates(sem, coords, order=0, mode="nearest")

    # Ids mean nothing across frames: a fresh random permutation every frame.
    ids = np.unique(seg[seg > 0])
    lut = np.zeros(int(seg.max()) + 1, dtype=np.int64)
    lut[ids] = rng.permutation(len(ids)) + 1
    return lut[seg].astype(np.uint16), sem.astype(np.uint16), stats
