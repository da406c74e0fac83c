"""`psimap segment DATA`: model-free pseudo-labels for every frame of a capture that has none.

Two passes. The capture-wide one reads a few evenly spaced frames and finds what one frame cannot
know: which way is up (psimap.geometry.gravity), the floor's height (the lowest large up-facing level,
when it lies well below the cameras) and the sensor's depth noise (psimap.geometry.depth_noise). The
per-frame one (psimap.segment.frame) labels each frame with those. Instance ids are per frame only:
the panoptic field makes them consistent in 3D.
"""
from __future__ import annotations

import time
from collections import deque
from pathlib import Path

import numpy as np

from psimap import PsimapError
from psimap.data.frames import TRAIN_FRAMES, evenly_spaced
from psimap.cores import available_cores
from psimap.segment.frame import (CLASS_TABLE, ORIENTATION_DEGREES, Capture, SegmentParams, SupportLevel, camera_points,
                                  horizontal_basis, pixel_normals, segment_frame)

# Frames the capture-wide pass reads (evenly spaced): enough for up and the floor in a room walk.
SURVEY_FRAMES = 24
# Pixels per survey frame (a regular subsample).
SURVEY_PIXELS = 6000
# The floor is at least this far below the median camera: a hand-held or head-mounted camera is
# 1-1.8 m up; a level closer below it is a table or counter top seen in a close-up, not the floor.
FLOOR_BELOW_CAMERA = 0.9
# ... and holds at least this share of the up-facing area the survey saw.
FLOOR_MIN_SHARE = 0.05
HISTOGRAM_BIN = 0.02
# Supports seen from above (support_levels): footprint raster cells (m), and the gaps in one that are
# closed (m): a top's pixels seen obliquely lie a few centimetres apart.
SUPPORT_CELL = 0.02
SUPPORT_GAP = 0.1
# ... at most this many cells across (a larger level gets larger cells: a warehouse floor's mezzanine),
# and the levels looked at (the most sampled first): a cap on the work, not on what a room holds.
SUPPORT_MAX_CELLS = 1000
SUPPORT_MAX_LEVELS = 32
# ... and its rim (cells) added around it: a top's front face seen through the noise.
SUPPORT_RIM_CELLS = 2


def survey(seq, indices, up_spec: str = "auto", params: SegmentParams | None = None) -> tuple[Capture, dict]:
    """The capture-wide pass over frames `indices` of `seq`: (Capture, summary dict)."""
    from psimap.geometry.depth_noise import estimate_depth_noise
    from psimap.geometry.gravity import resolve_up

    params = params or SegmentParams()
    P, Nn, A, c2ws, depths = [], [], [], [], []
    for i in indices:
        f = seq[i]
        depth = np.asarray(f.depth, np.float64)
        valid = np.isfinite(depth) & (depth > 0)
        c2w = np.asarray(f.c2w, np.float64)
        if not np.isfinite(c2w).all():
            continue
        c2ws.append(c2w)
        depths.append(np.where(valid, depth, 0.0))
        if valid.sum() < 10:
            continue
        K = np.asarray(f.K, np.float64)
        H, W = depth.shape
        pts = camera_points(depth, K)
        nrm, ok = pixel_normals(pts, valid, max(1, round(W / 160)))
        stride = max(1, int(np.sqrt(H * W / SURVEY_PIXELS)))
        sel = np.zeros_like(ok)
        sel[::stride, ::stride] = True
        sel &= ok
        z = depth[sel]
        R, t = c2w[:3, :3], c2w[:3, 3]
        P.append(pts[sel] @ R.T + t)
        Nn.append(nrm[sel] @ R.T)
        A.append(z * z / (K[0, 0] * K[1, 1]) * stride * stride)
    if not c2ws:
        raise PsimapError("no frame with a finite camera pose: nothing to segment")
    P = np.concatenate(P) if P else np.zeros((0, 3))
    Nn = np.concatenate(Nn) if Nn else np.zeros((0, 3))
    A = np.concatenate(A) if A else np.zeros(0)
    C2W = np.stack(c2ws)
    est = resolve_up(up_spec, P, Nn, A, C2W)
    up = est.up
    noise = estimate_depth_noise(depths)
    floor = floor_level(P, Nn, A, up, float(np.median(C2W[:, :3, 3] @ up)))
    supports = support_levels(P, Nn, up, floor, params)
    capture = Capture(up=up, floor=floor, noise=noise, supports=supports)
    return capture, {"up": [round(float(v), 4) for v in up], "up_source": est.source,
                     "floor": None if floor is None else round(floor, 4),
                     "supports": [{"height": round(s.height, 4), "area": round(float((s.cells == 2).sum()) * s.cell ** 2, 3)}
                                  for s in supports],
                     "camera_height": round(float(np.median(C2W[:, :3, 3] @ up)), 4),
                     "noise": {f"{z:.2f} m": round(float(s), 5) for z, s in zip(*noise)}}


def height_levels(h: np.ndarray, weights: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """(lowest height, [B] weight per HISTOGRAM_BIN from it) of heights `h` [N] (weights [N]; None:
    a count each), each bin with its two neighbours': a level spreads over a bin or two (noise, a
    tilt of a degree)."""
    lo = float(h.min())
    hist = np.bincount(np.floor((h - lo) / HISTOGRAM_BIN).astype(np.int64), weights=weights)
    return lo, hist + np.concatenate([hist[1:], [0]]) + np.concatenate([[0], hist[:-1]])


def floor_level(points, normals, area, up, camera_height: float) -> float | None:
    """Height along `up` of the floor: the lowest level holding FLOOR_MIN_SHARE of the up-facing area,
    when it lies FLOOR_BELOW_CAMERA below the median camera; None when no such level was seen.

    points / normals: [N, 3] world samples with camera-facing normals; area: [N] m^2."""
    if len(points) == 0:
        return None
    facing = normals @ up >= np.cos(np.radians(ORIENTATION_DEGREES))
    if area[facing].sum() <= 0:
        return None
    h, w = points[facing] @ up, area[facing]
    lo, level = height_levels(h, w)
    big = np.flatnonzero(level >= FLOOR_MIN_SHARE * w.sum())
    if len(big) == 0:
        return None
    b = int(big[0])
    near = np.abs(h - (lo + (b + 0.5) * HISTOGRAM_BIN)) <= 1.5 * HISTOGRAM_BIN
    floor = float(np.median(h[near]))
    if floor > camera_height - FLOOR_BELOW_CAMERA:
        return None
    return floor


def support_levels(points, normals, up, floor: float | None, params: SegmentParams) -> list[SupportLevel]:
    """The supports the survey saw from above: levels (along `up`) of up-facing samples over the
    floor, each with the footprint its samples cover (gaps of SUPPORT_GAP closed, holes filled: what
    stands on a top hides it), kept where a connected piece covers params.min_support_area (what a
    frame asks of a support plane). A frame that sees such a top only edge-on is cut at it
    (frame.cut_at_supports).

    points / normals: [N, 3] world samples with camera-facing normals."""
    from scipy import ndimage

    if len(points) == 0:
        return []
    facing = normals @ up >= np.cos(np.radians(ORIENTATION_DEGREES))
    h = points[facing] @ up
    ground = points[facing] @ horizontal_basis(up)
    if floor is not None:
        keep = h > floor + params.floor_tolerance
        h, ground = h[keep], ground[keep]
    if len(h) < 50:
        return []
    lo, level = height_levels(h)
    peaks = [b for b in np.argsort(-level, kind="stable") if level[b] >= 20
             and level[b] >= level[max(b - 1, 0)] and level[b] >= level[min(b + 1, len(level) - 1)]]
    found, taken = [], []
    for b in peaks[:SUPPORT_MAX_LEVELS]:
        centre = lo + (b + 0.5) * HISTOGRAM_BIN
        if any(abs(centre - t) < 3 * HISTOGRAM_BIN for t in taken):
            continue
        taken.append(centre)
        near = np.abs(h - centre) <= 1.5 * HISTOGRAM_BIN
        g = ground[near]
        cell = max(SUPPORT_CELL, float(np.ptp(g, axis=0).max()) / SUPPORT_MAX_CELLS)
        close = max(1, int(round(SUPPORT_GAP / cell)))
        disk = np.hypot(*np.mgrid[-close:close + 1, -close:close + 1]) <= close
        origin = g.min(0) - (close + SUPPORT_RIM_CELLS + 1) * cell
        ij = np.floor((g - origin) / cell).astype(np.int64)
        mask = np.zeros(ij.max(0) + close + SUPPORT_RIM_CELLS + 2, bool)
        mask[ij[:, 0], ij[:, 1]] = True
        mask = ndimage.binary_fill_holes(ndimage.binary_closing(mask, disk))
        parts, count = ndimage.label(mask)
        area = np.bincount(parts.ravel(), minlength=count + 1) * cell ** 2
        big = area >= params.min_support_area
        big[0] = False
        if not big.any():
            continue
        top = big[parts]
        # inside it (what stands on it), and its edge with a rim (its front and the sides of the
        # furniture it belongs to lie there, within the noise)
        cells = np.where(ndimage.binary_erosion(top), 2,
                         ndimage.binary_dilation(top, iterations=SUPPORT_RIM_CELLS)).astype(np.int8)
        found.append(SupportLevel(float(np.median(h[near])), origin, cell, cells))
    return found


def frame_indices(count: int, every: int) -> list[int]:
    """The frames to label: every `every`-th of `count`, or with every = 0 the ones `psimap train`
    reads (psimap.data.frames.evenly_spaced, at most TRAIN_FRAMES): a 1,800-frame phone capture took
    ~7 min of labels at 640x480 for the 300 frames training would use."""
    if every == 0:
        return evenly_spaced(count, TRAIN_FRAMES)
    if every < 1:
        raise PsimapError(f"--every must be >= 1 (or 0: the frames psimap train uses), got {every}")
    return list(range(0, count, every))


def segment_capture(data, *, up: str = "auto", every: int = 0, params: SegmentParams | None = None,
                    force: bool = False, preview: str | None = "", progress: bool = True,
                    preview_frames: int = 6, preview_dpi: int = 110, workers: int = 0) -> dict:
    """Label the capture at `data` and write its labels overlay (psimap.data.label_overlay) and a
    contact sheet; returns a summary dict. every: label every N-th frame; 0 = the frames `psimap
    train` reads (at most psimap.data.frames.TRAIN_FRAMES, evenly spaced; all of a shorter
    capture). preview: PNG path ("" = DATA/segment_preview.png, None = none) of `preview_frames`
    evenly spaced frames at `preview_dpi`. workers: threads labelling frames (0 = one per core this
    process may use); the labels are the same for any count."""
    from psimap.data import load
    from psimap.data.frames import ClassInfo
    from psimap.data.label_overlay import check_label_write, write_label_overlay
    from psimap.io_utils import check_output_file

    params = params or SegmentParams()
    root = Path(data)
    if not root.is_dir():
        raise PsimapError(f"no such capture folder: {data}")
    seq = load(root)
    if len(seq) == 0:
        raise PsimapError(f"{data}: the capture has no frames")
    indices = frame_indices(len(seq), every)
    names = [seq.names[i] if seq.names else None for i in indices]
    # refuse before the work, not after it
    check_label_write(root, [n for n in names if n], force=force)
    preview_path = None
    if preview is not None:
        preview_path = check_output_file(preview or root / "segment_preview.png", what="preview")

    import scipy.ndimage  # noqa: F401  (imported before the clock starts: no frame's time)

    t0 = time.perf_counter()
    survey_idx = indices[:: max(1, len(indices) // SURVEY_FRAMES)][:SURVEY_FRAMES]
    capture, found = survey(seq, survey_idx, up, params)
    t_survey = time.perf_counter() - t0
    n_show = max(1, int(preview_frames))
    show = set(indices[:: max(1, len(indices) // n_show)][:n_show])
    sheet, stats = [], {"planes": [], "objects": [], "seconds": [], "stuff": {}}
    n_workers = max(1, min(len(indices), workers or available_cores()))

    def label_one(i, f):
        ts = time.thread_time()
        if not np.isfinite(np.asarray(f.c2w)).all():
            sem = inst = np.zeros(f.depth.shape, np.uint16)
            info = {"planes": [], "objects": 0}
        else:
            sem, inst, info = segment_frame(f.depth, f.rgb, f.K, f.c2w, capture, params, seed=i)
        return sem, inst, info, time.thread_time() - ts

    def labelled():
        from concurrent.futures import ThreadPoolExecutor

        from tqdm import tqdm

        # frames are independent: one per core on threads (most of a frame is NumPy and SciPy
        # outside the GIL; each frame draws from its own seeded generator, so the labels are those
        # of one thread: tests/test_segment.py), read here in order, a few ahead of the writer
        todo = iter(zip(indices, names))
        pending = deque()
        with ThreadPoolExecutor(n_workers) as ex, tqdm(total=len(indices), desc="psimap segment: frames",
                                                       disable=not progress, leave=False) as bar:
            def submit():
                for i, name in todo:
                    f = seq[i]
                    pending.append((i, name, f, ex.submit(label_one, i, f)))
                    return

            for _ in range(2 * n_workers):
                submit()
            while pending:
                i, name, f, job = pending.popleft()
                sem, inst, info, seconds = job.result()
                submit()
                bar.update()
                stats["seconds"].append(seconds)
                stats["planes"].append(len(info["planes"]))
                stats["objects"].append(info["objects"])
                for p in info["planes"]:
                    stats["stuff"][p["class"]] = stats["stuff"].get(p["class"], 0) + 1
                if i in show:
                    sheet.append((name or f.name, np.asarray(f.rgb), sem, inst))
                yield name or f.name, sem, inst

    classes = [ClassInfo(i, n, t) for i, n, t in CLASS_TABLE]
    manifest = write_label_overlay(root, classes, labelled(), source="psimap segment", force=force)
    if preview_path is not None and sheet:
        contact_sheet(sheet, preview_path, dpi=preview_dpi)
    sec = np.asarray(stats["seconds"])
    return {"data": str(root), "frames": len(indices), "of": len(seq), "labels": str(manifest),
            "preview": None if preview_path is None else str(preview_path), **found,
            "planes_per_frame": float(np.mean(stats["planes"])),
            "objects_per_frame": float(np.mean(stats["objects"])),
            "objects_median": float(np.median(stats["objects"])),
            "stuff_planes": stats["stuff"],
            "seconds_per_frame": float(sec.mean()), "survey_seconds": t_survey,
            "seconds": time.perf_counter() - t0}


def colourise(semantic: np.ndarray, instance: np.ndarray) -> np.ndarray:
    """[H, W, 3] float image: stuff in fixed colours, each object a colour of its own, void black."""
    stuff = {1: (0.55, 0.45, 0.3), 2: (0.55, 0.6, 0.75), 3: (0.85, 0.85, 0.7), 4: (0.35, 0.65, 0.4)}
    out = np.zeros((*semantic.shape, 3))
    for c, rgb in stuff.items():
        out[semantic == c] = rgb
    ids = instance.astype(np.int64)
    palette = np.random.default_rng(7).uniform(0.15, 1.0, (int(ids.max()) + 1, 3))
    obj = ids > 0
    out[obj] = palette[ids[obj]]
    return out


def contact_sheet(frames, path, dpi: int = 110) -> None:
    """PNG of frames [(name, rgb [H, W, 3], semantic, instance)]: each RGB beside its labels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from psimap.io_utils import save_figure

    n = len(frames)
    H, W = frames[0][2].shape
    fig, axes = plt.subplots(n, 2, figsize=(2 * 3.2, n * 3.2 * H / W + 0.3), squeeze=False)
    for row, (name, rgb, sem, inst) in zip(axes, frames):
        img = np.clip(np.asarray(rgb, np.float64), 0, 1) if rgb is not None and np.ndim(rgb) == 3 else np.zeros((H, W, 3))
        row[0].imshow(img)
        row[0].set_title(name, fontsize=7)
        lab = colourise(sem, inst)
        row[1].imshow(0.35 * img + 0.65 * lab if img.shape == lab.shape else lab)
        row[1].set_title(f"{int(inst.max())} objects", fontsize=7)
        for a in row:
            a.axis("off")
    fig.suptitle("psimap segment: floor brown, wall blue, ceiling cream, support green, objects coloured",
                 fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=dpi)
    plt.close(fig)


def describe(s: dict) -> str:
    """The summary `psimap segment` prints."""
    floor = "not seen" if s["floor"] is None else f"{s['floor']:+.3f} m"
    lines = [f"labelled {s['frames']} of {s['of']} frames of {s['data']} -> {s['labels']}",
             f"  up {s['up']} ({s['up_source']}), floor level {floor}, cameras at {s['camera_height']:+.3f} m",
             "  supports seen from above: " + (", ".join(f"{v['height']:+.2f} m ({v['area']:.2f} m2)"
                                                      for v in sorted(s.get("supports", []), key=lambda v: v["height"]))
                                            or "none"),
             f"  per frame: {s['planes_per_frame']:.1f} stuff planes, {s['objects_per_frame']:.1f} objects "
             f"(median {s['objects_median']:.0f}); planes: "
             + (", ".join(f"{k} {v}" for k, v in sorted(s["stuff_planes"].items())) or "none"),
             f"  {s['seconds_per_frame'] * 1000:.0f} ms per frame, {s['seconds']:.1f} s in all "
             f"(survey {s['survey_seconds']:.1f} s)"]
    if s["preview"]:
        lines.append(f"  contact sheet: {s['preview']}")
    return "\n".join(lines)


def cli_segment(opts) -> int:
    import sys

    params = SegmentParams(noise_k=opts.noise_k, min_wall_area=opts.min_wall_area,
                           min_support_area=opts.min_support_area, colour_edge=opts.colour_edge,
                           min_object_pixels=opts.min_pixels)
    s = segment_capture(opts.data, up=opts.up, every=opts.every, params=params, force=opts.force,
                        preview=None if opts.no_preview else opts.preview, progress=sys.stderr.isatty())
    print(describe(s))
    return 0
