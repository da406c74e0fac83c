"""Capture layouts other tools write: TUM RGB-D and BOP scene folders (`loaders.LAYOUTS` lists them).

TUM RGB-D (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats):
  `rgb.txt`, `depth.txt` ("timestamp path" lines), `groundtruth.txt` ("timestamp tx ty tz qx qy
  qz qw": the colour camera's optical centre in the world, OpenCV camera axes), lines starting with
  `#` are comments. Depth PNGs are uint16, metres = value / 5000. Each colour image takes the depth
  image nearest in time within 0.02 s (one-to-one, closest pairs first, as TUM's associate.py) and
  the pose interpolated at its timestamp (slerp, lerp); colour frames outside the groundtruth's time
  span, with no groundtruth sample within TUM_MAX_POSE_DT or without a depth match are skipped
  (warned, and listed in the report). Intrinsics: `intrinsics.txt` ("fx fy cx cy", or a 3x3
  matrix) when present, else TUM's ROS default (fx=fy=525, cx=319.5, cy=239.5), which TUM
  recommends for its pre-registered depth.

BOP scene folder (https://github.com/thodan/bop_toolkit/blob/master/docs/bop_datasets_format.md):
  `scene_camera.json` {im_id: {cam_K, depth_scale, [cam_R_w2c, cam_t_w2c]}}, `scene_gt.json`
  {im_id: [{obj_id, cam_R_m2c, cam_t_m2c}]}, `rgb/` or `gray/` images, `depth/` (uint16, depth in
  mm = value x depth_scale), `mask_visib/<im_id>_<gt index>.png`. Lengths in mm become metres.
  Visible masks become labels: instance = gt index + 1, class = obj_id (things named obj_000001...);
  where visible masks overlap, the object whose centre is nearer the camera wins (it occludes).
  Without cam_R_w2c / cam_t_w2c the scene is assumed static: the world is the frame of an anchor
  object (the one seen exactly once in the most images), c2w = (T_m2c of the anchor)^-1; images
  without the anchor are skipped, and the report says how far the other objects move in that world
  (millimetres if the scene is static).
"""
from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np

from psimap import PsimapError
from psimap.data.frames import ClassInfo, Frame, FrameSequence, LoadReport
from psimap.data.scene_format import check_pose, image_size, read_depth_png, read_label_png, read_rgb

TUM_DEPTH_FACTOR = 5000.0             # TUM depth PNG units per metre
TUM_ROS_DEFAULT = (525.0, 525.0, 319.5, 239.5)   # fx fy cx cy
TUM_MAX_DT = 0.02                     # colour <-> depth association window, s (associate.py default)
TUM_MAX_POSE_DT = 0.05                # nearest groundtruth sample to a colour timestamp, s
TUM_INTRINSICS = "intrinsics.txt"
# Objects moving more than this in the anchor's world mean the scene was not static.
BOP_STATIC_TOLERANCE_M = 0.02


def _warn_skipped(what: str, root: Path, reasons: list[str]) -> None:
    if reasons:
        warnings.warn(f"{what} {root}: skipped " + "; ".join(reasons), stacklevel=3)


# --------------------------------------------------------------------------------------------------
# TUM RGB-D


def is_tum(p: Path) -> bool:
    return (p / "rgb.txt").is_file() and (p / "depth.txt").is_file()


def _tum_rows(path: Path, numbers: int | None) -> tuple[np.ndarray, list[list[str]]]:
    """Timestamps [N] and the remaining fields of each non-comment line. `numbers`: the fields must
    be that many finite numbers (groundtruth), else one path (rgb.txt / depth.txt)."""
    if not path.is_file():
        raise PsimapError(f"missing file: {path}")
    stamps, rows = [], []
    for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        cols = line.split()
        want = 1 + (numbers or 1)
        try:
            stamp = float(cols[0])
            vals = [float(c) for c in cols[1:want]] if numbers else cols[1:2]
        except ValueError:
            raise PsimapError(f"{path} line {n}: expected numbers, got {line!r}") from None
        if len(cols) < want:
            raise PsimapError(f"{path} line {n}: expected "
                              + (f"timestamp and {numbers} numbers" if numbers else "'timestamp path'")
                              + f", got {line!r}")
        if not np.isfinite(stamp) or (numbers and not np.all(np.isfinite(vals))):
            raise PsimapError(f"{path} line {n}: non-finite value (nan/inf)")
        stamps.append(stamp)
        rows.append(vals)
    if not rows:
        raise PsimapError(f"{path} lists nothing")
    return np.asarray(stamps, np.float64), rows


def associate(a: np.ndarray, b: np.ndarray, max_dt: float) -> dict[int, int]:
    """One-to-one matching of timestamps a [N] to b [M] within max_dt, closest pairs first (TUM's
    associate.py). Returns {index in a: index in b}."""
    order = np.argsort(b, kind="stable")
    bs = b[order]
    lo = np.searchsorted(bs, a - max_dt, side="left")
    hi = np.searchsorted(bs, a + max_dt, side="right")
    pairs = [(abs(a[i] - bs[j]), i, int(order[j])) for i in range(len(a)) for j in range(lo[i], hi[i])]
    pairs.sort()
    out, used = {}, set()
    for _, i, j in pairs:
        if i not in out and j not in used:
            out[i] = j
            used.add(j)
    return out


def interpolate_poses(t_gt: np.ndarray, gt: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera-to-world [len(t), 4, 4] at times t [T] (inside t_gt's span) from samples t_gt [G]
    (increasing) with rows gt [G, 7] = tx ty tz qx qy qz qw: slerp for rotation, lerp for position."""
    from scipy.spatial.transform import Rotation, Slerp

    c2w = np.tile(np.eye(4), (len(t), 1, 1))
    if len(t_gt) == 1:
        rot = Rotation.from_quat(np.repeat(gt[:, 3:7], len(t), axis=0))
    else:
        rot = Slerp(t_gt, Rotation.from_quat(gt[:, 3:7]))(t)
    c2w[:, :3, :3] = rot.as_matrix()
    c2w[:, :3, 3] = np.stack([np.interp(t, t_gt, gt[:, k]) for k in range(3)], axis=1)
    return c2w


def _tum_intrinsics(root: Path) -> tuple[np.ndarray, str | None]:
    path = root / TUM_INTRINSICS
    if not path.is_file():
        return None, None
    try:
        m = np.loadtxt(path, dtype=np.float64, ndmin=2, comments="#")
    except ValueError as e:
        raise PsimapError(f"cannot parse numbers in {path}: {e}") from None
    if m.size == 4:
        fx, fy, cx, cy = m.ravel()
    elif m.shape == (3, 3) and abs(m[2, 2] - 1.0) < 1e-6:
        fx, fy, cx, cy = m[0, 0], m[1, 1], m[0, 2], m[1, 2]
    else:
        raise PsimapError(f"{path}: expected 'fx fy cx cy' or a 3x3 intrinsics matrix, got shape {m.shape}")
    if not np.all(np.isfinite([fx, fy, cx, cy])) or fx <= 0 or fy <= 0:
        raise PsimapError(f"{path}: fx, fy must be finite and positive")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), path.name


def load_tum(root: str | os.PathLike) -> FrameSequence:
    """TUM RGB-D sequence folder (rgb.txt, depth.txt, groundtruth.txt, rgb/, depth/)."""
    root = Path(root)
    t_rgb, rgb_rows = _tum_rows(root / "rgb.txt", None)
    t_depth, depth_rows = _tum_rows(root / "depth.txt", None)
    gt_path = root / "groundtruth.txt"
    if not gt_path.is_file():
        raise PsimapError(f"missing file: {gt_path} (TUM camera poses: 'timestamp tx ty tz qx qy qz qw')")
    t_gt, gt_rows = _tum_rows(gt_path, 7)
    gt = np.asarray(gt_rows, np.float64)
    if np.any(np.linalg.norm(gt[:, 3:7], axis=1) < 1e-9):
        raise PsimapError(f"{gt_path}: a quaternion qx qy qz qw is zero")
    order = np.argsort(t_gt, kind="stable")
    t_gt, gt = t_gt[order], gt[order]
    if np.any(np.diff(t_gt) <= 0):
        raise PsimapError(f"{gt_path}: repeated timestamp {t_gt[1:][np.diff(t_gt) <= 0][0]:.6f}")

    K, k_file = _tum_intrinsics(root)
    report = LoadReport(depth=f"uint16 PNG / {TUM_DEPTH_FACTOR:g} m (0 invalid)",
                        poses="groundtruth.txt (tx ty tz qx qy qz qw), camera-to-world, OpenCV camera axes, "
                              "slerp / lerp at each colour timestamp",
                        labels="none (TUM has no masks)")
    if K is None:
        K = np.array([[TUM_ROS_DEFAULT[0], 0.0, TUM_ROS_DEFAULT[2]], [0.0, TUM_ROS_DEFAULT[1], TUM_ROS_DEFAULT[3]],
                      [0.0, 0.0, 1.0]])
        report.intrinsics = "TUM's ROS default fx=fy=525, cx=319.5, cy=239.5"
        report.assumed.append(f"no {TUM_INTRINSICS}: TUM's ROS default intrinsics fx=fy=525, cx=319.5, cy=239.5")
    else:
        report.intrinsics = k_file

    match = associate(t_rgb, t_depth, TUM_MAX_DT)
    inside = (t_rgb >= t_gt[0]) & (t_rgb <= t_gt[-1])
    k = np.clip(np.searchsorted(t_gt, t_rgb), 1, max(1, len(t_gt) - 1))
    nearest = np.minimum(np.abs(t_rgb - t_gt[k - 1]), np.abs(t_gt[np.minimum(k, len(t_gt) - 1)] - t_rgb))
    no_depth = [i for i in range(len(t_rgb)) if i not in match]
    outside = [i for i in range(len(t_rgb)) if i in match and not inside[i]]
    gap = [i for i in range(len(t_rgb)) if i in match and inside[i] and nearest[i] > TUM_MAX_POSE_DT]
    keep = [i for i in range(len(t_rgb)) if i in match and inside[i] and nearest[i] <= TUM_MAX_POSE_DT]
    reasons = [f"{len(ids)} frames: {why}" for ids, why in (
        (no_depth, f"no depth image within {TUM_MAX_DT} s"),
        (outside, "outside the groundtruth time span"),
        (gap, f"no groundtruth pose within {TUM_MAX_POSE_DT} s")) if ids]
    report.skipped += reasons
    _warn_skipped("TUM", root, reasons)
    if not keep:
        raise PsimapError(f"TUM {root}: no colour frame has both a depth image and a groundtruth pose")
    c2ws = interpolate_poses(t_gt, gt, t_rgb[keep])
    records = []
    for n, i in enumerate(keep):
        color, depth = root / rgb_rows[i][0], root / depth_rows[match[i]][0]
        for p in (color, depth):
            if not p.is_file():
                raise PsimapError(f"missing file: {p} (listed in {root / ('rgb.txt' if p == color else 'depth.txt')})")
        records.append((color, depth, check_pose(c2ws[n], f"{gt_path} at t={t_rgb[i]:.6f}"), color.stem))
    report.resolution = image_size(records[0][1])

    def load_frame(i: int) -> Frame:
        color, depth_path, c2w, name = records[i]
        depth = read_depth_png(depth_path, 1.0 / TUM_DEPTH_FACTOR)
        rgb = read_rgb(color)
        if rgb.shape[:2] != depth.shape:
            raise PsimapError(f"colour image {color} is {rgb.shape[1]}x{rgb.shape[0]} but depth image "
                              f"{depth_path} is {depth.shape[1]}x{depth.shape[0]}")
        return Frame(rgb=rgb, depth=depth, K=K.copy(), c2w=c2w.copy(), name=name)

    return FrameSequence(loader=load_frame, count=len(records), classes=[], root=str(root), layout="tum",
                         names=[r[3] for r in records], report=report)


# --------------------------------------------------------------------------------------------------
# BOP


def is_bop(p: Path) -> bool:
    return (p / "scene_camera.json").is_file()


def _read_json(path: Path):
    if not path.is_file():
        raise PsimapError(f"missing file: {path}")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise PsimapError(f"{path} is not valid JSON: {e}") from None


def _numbers(entry: dict, key: str, count: int, src: str) -> np.ndarray:
    try:
        v = np.asarray(entry[key], dtype=np.float64).reshape(-1)
    except (KeyError, TypeError, ValueError):
        raise PsimapError(f"{src}: needs {key} ({count} numbers)") from None
    if v.size != count:
        raise PsimapError(f"{src}: {key} must have {count} numbers, got {v.size}")
    if not np.all(np.isfinite(v)):
        raise PsimapError(f"{src}: {key} has non-finite values (nan/inf)")
    return v


def _rigid(R9: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R9.reshape(3, 3), t_mm / 1000.0
    return T


def _image_file(folder: Path, stem: str) -> Path | None:
    for ext in (".png", ".jpg", ".jpeg", ".tif", ".tiff"):
        if (folder / (stem + ext)).is_file():
            return folder / (stem + ext)
    return None


def load_bop(root: str | os.PathLike) -> FrameSequence:
    """BOP scene folder (scene_camera.json, scene_gt.json, rgb/ or gray/, depth/, mask_visib/)."""
    root = Path(root)
    cam_path, gt_path = root / "scene_camera.json", root / "scene_gt.json"
    cams = _read_json(cam_path)
    gts = _read_json(gt_path) if gt_path.is_file() else {}
    if not isinstance(cams, dict) or not cams or not isinstance(gts, dict):
        raise PsimapError(f"{cam_path}: expected {{image id: {{cam_K, depth_scale, ...}}}}")
    try:
        ids = sorted(int(k) for k in cams)
    except ValueError:
        raise PsimapError(f"{cam_path}: image ids must be integers") from None
    image_dir = next((root / d for d in ("rgb", "gray") if (root / d).is_dir()), None)
    if image_dir is None:
        raise PsimapError(f"BOP scene {root}: no rgb/ or gray/ image folder")
    masks_dir = root / "mask_visib"
    report = LoadReport(depth="uint16 PNG x depth_scale mm (scene_camera.json), in metres (0 invalid)",
                        intrinsics="scene_camera.json cam_K per image")

    # Objects per image: (obj_id, T_m2c in metres), in scene_gt order (the order mask_visib numbers).
    objects: dict[int, list[tuple[int, np.ndarray]]] = {}
    for i in ids:
        entries = gts.get(str(i), [])
        if not isinstance(entries, list):
            raise PsimapError(f"{gt_path} image {i}: expected a list of {{obj_id, cam_R_m2c, cam_t_m2c}}")
        objs = []
        for g, e in enumerate(entries):
            src = f"{gt_path} image {i} entry {g}"
            if not isinstance(e, dict) or not isinstance(e.get("obj_id"), int) or e["obj_id"] <= 0:
                raise PsimapError(f"{src}: needs a positive integer obj_id")
            objs.append((e["obj_id"], _rigid(_numbers(e, "cam_R_m2c", 9, src), _numbers(e, "cam_t_m2c", 3, src))))
        objects[i] = objs

    have_w2c = [isinstance(cams[str(i)], dict) and "cam_R_w2c" in cams[str(i)] for i in ids]
    c2w: dict[int, np.ndarray] = {}
    if all(have_w2c):
        for i in ids:
            src = f"{cam_path} image {i}"
            w2c = _rigid(_numbers(cams[str(i)], "cam_R_w2c", 9, src), _numbers(cams[str(i)], "cam_t_w2c", 3, src))
            c2w[i] = check_pose(np.linalg.inv(w2c), src)
        report.poses = "scene_camera.json cam_R_w2c, cam_t_w2c (mm -> m), inverted to camera-to-world, OpenCV axes"
    else:
        c2w = _anchored_poses(ids, objects, report, gt_path)

    skipped = [i for i in ids if i not in c2w]
    if skipped:
        reason = f"{len(skipped)} images: the anchor object is not seen exactly once"
        report.skipped.append(reason)
        _warn_skipped("BOP", root, [reason])
    records = []
    for i in ids:
        if i not in c2w:
            continue
        src = f"{cam_path} image {i}"
        cam = cams[str(i)]
        K = _numbers(cam, "cam_K", 9, src).reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1.0) > 1e-6:
            raise PsimapError(f"{src}: cam_K is not a pinhole intrinsics matrix")
        scale = float(_numbers(cam, "depth_scale", 1, src)[0]) if "depth_scale" in cam else 1.0
        if scale <= 0:
            raise PsimapError(f"{src}: depth_scale must be > 0")
        stem = f"{i:06d}"
        color, depth = _image_file(image_dir, stem), _image_file(root / "depth", stem)
        if color is None or depth is None:
            raise PsimapError(f"missing file: {(image_dir if color is None else root / 'depth') / stem}.png")
        masks = []
        if masks_dir.is_dir():
            masks = [masks_dir / f"{stem}_{g:06d}.png" for g in range(len(objects[i]))]
            for p in masks:
                if not p.is_file():
                    raise PsimapError(f"missing file: {p} (scene_gt.json lists {len(objects[i])} objects "
                                      f"in image {i})")
        records.append((color, depth, K, c2w[i], scale, stem, masks if masks_dir.is_dir() else None, objects[i]))
    if not records:
        raise PsimapError(f"BOP scene {root}: no usable image")
    report.resolution = image_size(records[0][1])
    obj_ids = sorted({o for objs in objects.values() for o, _ in objs})
    classes = [ClassInfo(o, f"obj_{o:06d}", True) for o in obj_ids]
    report.labels = (f"mask_visib/: instance = gt index + 1, class = obj_id ({len(classes)} object classes); "
                     "overlaps go to the object nearer the camera" if masks_dir.is_dir()
                     else "none (no mask_visib/)")
    if image_dir.name == "gray":
        report.assumed.append("gray/ images: grey copied to R, G, B")

    def load_frame(i: int) -> Frame:
        color, depth_path, K, pose, scale, stem, masks, objs = records[i]
        depth = read_depth_png(depth_path, scale / 1000.0)
        rgb = read_rgb(color)
        if rgb.shape[:2] != depth.shape:
            raise PsimapError(f"colour image {color} is {rgb.shape[1]}x{rgb.shape[0]} but depth image "
                              f"{depth_path} is {depth.shape[1]}x{depth.shape[0]}")
        labels = {}
        if masks is not None:           # mask_visib/ exists: an image without objects is all void
            semantic = np.zeros(depth.shape, np.uint16)
            instance = np.zeros(depth.shape, np.uint16)
            # Farthest centre first, so the nearer object (the occluder) paints last and wins;
            # at equal distance the lower gt index wins.
            for g in sorted(range(len(objs)), key=lambda g: (-objs[g][1][2, 3], -g)):
                m = read_label_png(masks[g])
                if m.shape != depth.shape:
                    raise PsimapError(f"mask {masks[g]} is {m.shape[1]}x{m.shape[0]} but depth image {depth_path} "
                                      f"is {depth.shape[1]}x{depth.shape[0]}")
                on = m > 0
                semantic[on], instance[on] = objs[g][0], g + 1
            labels = {"semantic": semantic, "instance": instance}
        return Frame(rgb=rgb, depth=depth, K=K.copy(), c2w=pose.copy(), name=stem, **labels)

    return FrameSequence(loader=load_frame, count=len(records), classes=classes, root=str(root), layout="bop",
                         names=[r[5] for r in records], report=report)


def _anchored_poses(ids: list[int], objects: dict, report: LoadReport, gt_path: Path) -> dict[int, np.ndarray]:
    """Camera poses of a BOP scene without cam_R_w2c: the world is the frame of the object seen
    exactly once in the most images (ties: the lowest obj_id), so c2w = (T_m2c)^-1; the report
    gives how far every other singly seen object moves in that world."""
    counts: dict[int, int] = {}
    for objs in objects.values():
        seen = [o for o, _ in objs]
        for o in set(seen):
            if seen.count(o) == 1:
                counts[o] = counts.get(o, 0) + 1
    if not counts:
        raise PsimapError(f"{gt_path.parent / 'scene_camera.json'} has no cam_R_w2c / cam_t_w2c and "
                          f"{gt_path.name} no object to anchor the camera poses to")
    anchor = min(counts, key=lambda o: (-counts[o], o))
    c2w = {}
    for i in ids:
        poses = [T for o, T in objects[i] if o == anchor]
        if len(poses) == 1:
            c2w[i] = check_pose(np.linalg.inv(poses[0]), f"{gt_path} image {i} obj_id {anchor}")
    # Static check: the centre of each other object, seen once per image, in the anchor's world.
    spread = 0.0
    for o in counts:
        if o == anchor:
            continue
        centres = np.array([(c2w[i] @ T)[:3, 3] for i in c2w for oo, T in objects[i]
                            if oo == o and [x for x, _ in objects[i]].count(o) == 1])
        if len(centres) > 1:
            spread = max(spread, float(np.linalg.norm(centres - np.median(centres, 0), axis=1).max()))
    report.poses = (f"no cam_R_w2c in scene_camera.json: world = the frame of obj_id {anchor} (seen in "
                    f"{counts[anchor]} of {len(ids)} images), c2w = (cam_R_m2c, cam_t_m2c)^-1, OpenCV axes")
    report.assumed.append(f"a static scene: camera poses from obj_id {anchor}'s pose; the other objects move "
                          f"up to {spread * 1000:.1f} mm in its frame")
    if spread > BOP_STATIC_TOLERANCE_M:
        warnings.warn(f"BOP {gt_path.parent}: objects move up to {spread * 1000:.0f} mm relative to obj_id {anchor}: "
                      f"the scene is not static, the camera poses derived from it are wrong for the rest",
                      stacklevel=3)
    return c2w
