"""Real-data layouts -> lazily loaded FrameSequence, and `load(path)` that detects the layout.

Layouts (all poses camera-to-world, OpenCV camera axes on disk already, so no conversion):
- psimap scene folder, or nerfstudio's processed layout (`transforms.json`, see scene_format).
- 7-Scenes / tsdf-fusion: `frame-NNNNNN.color.jpg|png`, `.depth.png` (uint16 mm, 0 and 65535
  invalid), `.pose.txt` (4x4), `camera-intrinsics.txt` (3x3; the 7-Scenes Kinect default
  fx=fy=585, cx=320, cy=240 when absent, as in the original per-sequence folders).
- ScanNet exported frames (SensReader): `color/N.jpg depth/N.png pose/N.txt intrinsic/...`,
  optional `label-filt/N.png` (semantic) and `instance-filt/N.png` (instance). Colour (1296x968)
  is resized to the depth size (640x480), labels by nearest neighbour. K is `intrinsic_depth.txt`
  (the camera whose pixels depth holds), else `intrinsic_color.txt` scaled to the depth size.
  The labels are ScanNet's cross-view-consistent annotation: they fill `.semantic`/`.instance` and
  also `.gt_semantic`/`.gt_instance`. Class table from `classes.json` or
  `scannetv2-labels.combined.tsv` (next to the scan or one level up), else empty.
  Real ScanNet has frames whose pose is `-inf` (tracking lost): they are SKIPPED with a warning
  naming the files, since a scan with a few lost frames is still usable.
- Replica, NICE-SLAM layout: `results/frameNNNNNN.jpg`, `results/depthNNNNNN.png` (uint16,
  metres = value / 6553.5), `traj.txt` (one row-major 4x4 c2w per line). Intrinsics from
  `cam_params.json` (Replica's {"camera": {w, h, fx, fy, cx, cy, scale}}) next to the folder or one
  level up, else the standard Replica ones (1200x680, fx=fy=600, cx=599.5, cy=339.5).
- TUM RGB-D and BOP scene folders: psimap/data/capture_formats.py.
Each fills `FrameSequence.report` (what it read, skipped and assumed).
"""
from __future__ import annotations

import json
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from psimap import PsimapError
from psimap.data.capture_formats import is_bop, is_tum, load_bop, load_tum
from psimap.data.frames import ClassInfo, Frame, FrameSequence, LoadReport
from psimap.data.label_overlay import apply_label_overlay
from psimap.data.scene_format import (TRANSFORMS, check_pose, image_size, read_depth_png, read_label_png,
                                      read_rgb, read_scene)

SEVEN_SCENES_K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])
REPLICA_CAMERA = {"w": 1200, "h": 680, "fx": 600.0, "fy": 600.0, "cx": 599.5, "cy": 339.5, "scale": 6553.5}
# ScanNet's structural classes; everything else in its label table is a thing.
_SCANNET_STUFF = {"wall", "floor", "ceiling"}


@dataclass(frozen=True)
class Layout:
    """One capture layout `psimap.data.load` reads: `detect(folder) -> bool` says whether a folder
    is one (from the files present, cheaply), `read(folder) -> FrameSequence` opens it lazily."""

    name: str
    detect: Callable[[Path], bool]
    read: Callable[[Path], FrameSequence]
    what: str               # what the detection looks for, as the error message names it


def _is_7scenes(p: Path) -> bool:
    return (p / "camera-intrinsics.txt").is_file() or next(p.glob("frame-*.pose.txt"), None) is not None


def load(path: str | os.PathLike) -> FrameSequence:
    """Open posed RGB-D frames; the layout (LAYOUTS: psimap scene folder or nerfstudio
    transforms.json, 7-Scenes, ScanNet, Replica, TUM RGB-D, BOP) is detected from the files present.
    Returns a FrameSequence whose frames are read on access; `.describe()` says what was read and
    assumed."""
    p = Path(path)
    if not p.exists():
        raise PsimapError(f"no such file or folder: {p}")
    layout = detect_layout(p)
    seq = next(lay for lay in LAYOUTS if lay.name == layout).read(p)
    # labels.json (psimap segment / import-masks) supplies labels for any layout
    return apply_label_overlay(seq)


def detect_layout(p: Path) -> str:
    """The name of the first of LAYOUTS that `p` is; PsimapError if none matches."""
    if p.is_file():
        if p.suffix == ".json":
            return "psimap"
        raise PsimapError(f"{p}: expected a scene folder (or its transforms.json), got a file")
    for lay in LAYOUTS:
        if lay.detect(p):
            return lay.name
    raise PsimapError(f"{p}: not a recognised layout (expected " + "; ".join(lay.what for lay in LAYOUTS) + ")")


def _read_matrix(path: Path, allow_nonfinite: bool = False) -> np.ndarray:
    """Whitespace-separated text matrix -> float64 array (ScanNet writes -inf, which parses)."""
    if not path.is_file():
        raise PsimapError(f"missing file: {path}")
    try:
        m = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise PsimapError(f"cannot parse numbers in {path}: {e}") from None
    if not allow_nonfinite and not np.all(np.isfinite(m)):
        raise PsimapError(f"{path} has non-finite values (inf/nan)")
    return m


def _intrinsics(path: Path) -> np.ndarray:
    m = _read_matrix(path)
    if m.shape not in ((3, 3), (4, 4)):
        raise PsimapError(f"{path}: intrinsics must be a 3x3 or 4x4 matrix, got {m.shape}")
    K = m[:3, :3].copy()
    if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1.0) > 1e-6:
        raise PsimapError(f"{path}: not a pinhole intrinsics matrix (fx, fy > 0, K[2,2] = 1)")
    return K


def _pose(path: Path) -> np.ndarray:
    m = _read_matrix(path, allow_nonfinite=True)
    if m.shape != (4, 4):
        raise PsimapError(f"{path}: pose must be a 4x4 matrix, got {m.shape}")
    return m


def _numbered(folder: Path, pattern: str) -> dict[int, Path]:
    """{frame number: path} for files whose name matches `pattern` (one int group)."""
    rx = re.compile(pattern)
    out = {}
    for p in folder.iterdir() if folder.is_dir() else ():
        m = rx.fullmatch(p.name)
        if m:
            out[int(m.group(1))] = p
    return out


def _rgbd_frame(rgb_path: Path, depth_path: Path, depth_scale: float, invalid: tuple[int, ...], K, c2w,
                name: str, resize_rgb: bool = False, labels: dict | None = None) -> Frame:
    depth = read_depth_png(depth_path, depth_scale, invalid)
    size = (depth.shape[1], depth.shape[0])
    rgb = read_rgb(rgb_path, size=size if resize_rgb else None)
    if rgb.shape[:2] != depth.shape:
        raise PsimapError(f"colour image {rgb_path} is {rgb.shape[1]}x{rgb.shape[0]} but depth image "
                          f"{depth_path} is {depth.shape[1]}x{depth.shape[0]}")
    maps = {k: read_label_png(p, size=size) for k, p in (labels or {}).items()}
    return Frame(rgb=rgb, depth=depth, K=K.copy(), c2w=c2w.copy(), name=name, **maps)


# --------------------------------------------------------------------------------------------------


def load_7scenes(root: str | os.PathLike) -> FrameSequence:
    """7-Scenes / tsdf-fusion folder of frame-NNNNNN.{color.jpg|color.png, depth.png, pose.txt}."""
    root = Path(root)
    colors = _numbered(root, r"frame-(\d+)\.color\.(?:jpg|jpeg|png)")
    poses = _numbered(root, r"frame-(\d+)\.pose\.txt")
    ids = sorted(set(colors) | set(poses))
    if not ids:
        raise PsimapError(f"{root}: no frame-NNNNNN.color.jpg / .pose.txt files")
    report = LoadReport(depth="uint16 PNG x 0.001 m (millimetres; 0 and 65535 invalid)",
                        poses="frame-*.pose.txt, camera-to-world 4x4, OpenCV camera axes")
    if (root / "camera-intrinsics.txt").is_file():
        K = _intrinsics(root / "camera-intrinsics.txt")
        report.intrinsics = "camera-intrinsics.txt"
    else:
        K = SEVEN_SCENES_K.copy()
        report.intrinsics = "7-Scenes Kinect default fx=fy=585, cx=320, cy=240"
        report.assumed.append("no camera-intrinsics.txt: the 7-Scenes Kinect default intrinsics")
    records = []
    for i in ids:
        stem = f"frame-{i:06d}"
        color = colors.get(i, root / f"{stem}.color.jpg")
        depth = root / f"{stem}.depth.png"
        pose_path = poses.get(i, root / f"{stem}.pose.txt")
        for p in (color, depth, pose_path):
            if not p.is_file():
                raise PsimapError(f"missing file: {p}")
        records.append((color, depth, check_pose(_pose(pose_path), str(pose_path)), stem))

    report.resolution = image_size(records[0][1])
    report.labels = "none (7-Scenes has no masks)"

    def load_frame(i: int) -> Frame:
        color, depth, c2w, stem = records[i]
        # Kinect raw depth: 65535 marks pixels without a measurement, like 0.
        return _rgbd_frame(color, depth, 0.001, (0, 65535), K, c2w, stem)

    return FrameSequence(loader=load_frame, count=len(records), classes=[], root=str(root), layout="7scenes",
                         names=[r[3] for r in records], report=report)


# --------------------------------------------------------------------------------------------------


def _scannet_classes(root: Path) -> list[ClassInfo]:
    """Class table: classes.json ([{id, name, isthing}]) or ScanNet's label tsv, next to the scan or
    one level up; empty when neither exists."""
    for folder in (root, root.parent):
        if (folder / "classes.json").is_file():
            try:
                rows = json.loads((folder / "classes.json").read_text())
                return [ClassInfo(int(r["id"]), str(r["name"]), bool(r.get("isthing", True))) for r in rows]
            except (json.JSONDecodeError, KeyError, TypeError, ValueError):
                raise PsimapError(f"{folder / 'classes.json'}: expected [{{id, name, isthing}}]") from None
        tsv = folder / "scannetv2-labels.combined.tsv"
        if tsv.is_file():
            lines = tsv.read_text().splitlines()
            head = lines[0].split("\t") if lines else []
            if "id" not in head or "raw_category" not in head:
                raise PsimapError(f"{tsv}: expected the columns 'id' and 'raw_category'")
            ci, ni = head.index("id"), head.index("raw_category")
            out = []
            for line in lines[1:]:
                cols = line.split("\t")
                if len(cols) > max(ci, ni) and cols[ci].strip().isdigit():
                    name = cols[ni].strip()
                    out.append(ClassInfo(int(cols[ci]), name, name not in _SCANNET_STUFF))
            return out
    return []


def load_scannet(root: str | os.PathLike) -> FrameSequence:
    """ScanNet exported frames. Frames whose pose is non-finite are skipped with a warning."""
    root = Path(root)
    colors = _numbered(root / "color", r"(\d+)\.(?:jpg|jpeg|png)")
    if not colors:
        raise PsimapError(f"{root / 'color'}: no N.jpg colour frames")
    ids = sorted(colors)
    depth0 = root / "depth" / f"{ids[0]}.png"
    if not depth0.is_file():
        raise PsimapError(f"missing file: {depth0}")
    dw, dh = image_size(depth0)
    intr = root / "intrinsic"
    report = LoadReport(resolution=(dw, dh), depth="uint16 PNG x 0.001 m (millimetres; 0 invalid)",
                        poses="pose/N.txt, camera-to-world 4x4, OpenCV camera axes")
    if (intr / "intrinsic_depth.txt").is_file():
        K = _intrinsics(intr / "intrinsic_depth.txt")
        report.intrinsics = "intrinsic/intrinsic_depth.txt"
    elif (intr / "intrinsic_color.txt").is_file():
        report.intrinsics = f"intrinsic/intrinsic_color.txt scaled to the depth size {dw}x{dh}"
        K = _intrinsics(intr / "intrinsic_color.txt")
        cw, ch = image_size(colors[ids[0]])
        # Pixel-corner convention: scaling an image by s maps (u + 0.5) to s (u + 0.5).
        sx, sy = dw / cw, dh / ch
        K = np.array([[K[0, 0] * sx, 0.0, (K[0, 2] + 0.5) * sx - 0.5],
                      [0.0, K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5], [0.0, 0.0, 1.0]])
    else:
        raise PsimapError(f"missing file: {intr / 'intrinsic_depth.txt'} (or intrinsic_color.txt)")
    records, skipped = [], []
    for i in ids:
        depth, pose_path = root / "depth" / f"{i}.png", root / "pose" / f"{i}.txt"
        for p in (depth, pose_path):
            if not p.is_file():
                raise PsimapError(f"missing file: {p}")
        c2w = _pose(pose_path)
        if not np.all(np.isfinite(c2w)):
            skipped.append(pose_path)
            continue
        labels = {}
        for key, sub in (("semantic", "label-filt"), ("instance", "instance-filt")):
            p = root / sub / f"{i}.png"
            if (root / sub).is_dir():
                if not p.is_file():
                    raise PsimapError(f"missing file: {p}")
                labels[key] = p
        records.append((colors[i], depth, check_pose(c2w, str(pose_path)), str(i), labels))
    if skipped:
        report.skipped.append(f"{len(skipped)} of {len(ids)} frames: non-finite pose (tracking lost)")
        shown = ", ".join(str(p) for p in skipped[:3]) + (" ..." if len(skipped) > 3 else "")
        warnings.warn(f"ScanNet {root}: skipped {len(skipped)} of {len(ids)} frames with non-finite poses "
                      f"(tracking lost): {shown}", stacklevel=2)
    if not records:
        raise PsimapError(f"ScanNet {root}: every pose is non-finite, no usable frame")

    classes = _scannet_classes(root)
    report.labels = ("label-filt/ + instance-filt/ (ScanNet's annotation, also the ground truth), "
                     f"{len(classes)} classes" if records[0][4] else "none (no label-filt/ or instance-filt/)")
    if image_size(records[0][0]) != (dw, dh):
        report.assumed.append(f"colour {'x'.join(map(str, image_size(records[0][0])))} resized to the depth size")

    def load_frame(i: int) -> Frame:
        color, depth, c2w, name, labels = records[i]
        f = _rgbd_frame(color, depth, 0.001, (0,), K, c2w, name, resize_rgb=True, labels=labels)
        # ScanNet's label-filt / instance-filt are its cross-view-consistent annotation, so they are
        # also the ground truth that `psimap eval` compares against.
        f.gt_semantic = None if f.semantic is None else f.semantic.copy()
        f.gt_instance = None if f.instance is None else f.instance.copy()
        if f.depth.shape != (dh, dw):
            raise PsimapError(f"depth image {depth} is {f.width}x{f.height}, expected {dw}x{dh} like {depth0}")
        return f

    return FrameSequence(loader=load_frame, count=len(records), classes=classes, root=str(root),
                         layout="scannet", names=[r[3] for r in records], report=report)


# --------------------------------------------------------------------------------------------------


def _replica_camera(root: Path) -> tuple[dict, Path | None]:
    """Camera parameters and the file they came from (None: the Replica default)."""
    for p in (root / "cam_params.json", root.parent / "cam_params.json"):
        if p.is_file():
            try:
                cam = json.loads(p.read_text())
                cam = cam.get("camera", cam)
                out = {k: float(cam[k]) for k in ("w", "h", "fx", "fy", "cx", "cy")}
                out["scale"] = float(cam.get("scale", REPLICA_CAMERA["scale"]))
            except (json.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError):
                raise PsimapError(f"{p}: expected {{\"camera\": {{w, h, fx, fy, cx, cy[, scale]}}}}") from None
            if min(out.values()) <= 0 or not all(np.isfinite(list(out.values()))):
                raise PsimapError(f"{p}: camera parameters must be finite and positive")
            return out, p
    return dict(REPLICA_CAMERA), None


def load_replica(root: str | os.PathLike) -> FrameSequence:
    """Replica in NICE-SLAM layout: results/frame*.jpg, results/depth*.png, traj.txt."""
    root = Path(root)
    colors = _numbered(root / "results", r"frame(\d+)\.(?:jpg|jpeg|png)")
    depths = _numbered(root / "results", r"depth(\d+)\.png")
    ids = sorted(colors)
    if not ids:
        raise PsimapError(f"{root / 'results'}: no frameNNNNNN.jpg colour frames")
    for i in ids:
        if i not in depths:
            raise PsimapError(f"missing file: {root / 'results' / ('depth' + colors[i].stem[5:] + '.png')}")
    traj = root / "traj.txt"
    rows = [r for r in traj.read_text().splitlines() if r.strip()]
    if len(rows) < len(ids):
        raise PsimapError(f"{traj} has {len(rows)} poses for {len(ids)} frames")
    cam, cam_file = _replica_camera(root)
    report = LoadReport(resolution=(int(round(cam["w"])), int(round(cam["h"]))),
                        depth=f"uint16 PNG / {cam['scale']:g} m (0 invalid)",
                        poses="traj.txt, one row-major camera-to-world 4x4 per line, OpenCV camera axes",
                        intrinsics=str(cam_file) if cam_file else "the standard Replica camera (1200x680, fx=fy=600)",
                        labels="none")
    if cam_file is None:
        report.assumed.append("no cam_params.json: the standard Replica camera")
    K = np.array([[cam["fx"], 0.0, cam["cx"]], [0.0, cam["fy"], cam["cy"]], [0.0, 0.0, 1.0]])
    hw = (int(round(cam["h"])), int(round(cam["w"])))
    records = []
    for n, i in enumerate(ids):
        try:
            vals = np.array([float(v) for v in rows[n].split()])
        except ValueError:
            raise PsimapError(f"{traj} line {n + 1}: not numbers") from None
        if vals.size != 16:
            raise PsimapError(f"{traj} line {n + 1}: expected 16 numbers (a 4x4 pose), got {vals.size}")
        c2w = check_pose(vals.reshape(4, 4), f"{traj} line {n + 1}")
        records.append((colors[i], depths[i], c2w, colors[i].stem))

    def load_frame(i: int) -> Frame:
        color, depth, c2w, name = records[i]
        f = _rgbd_frame(color, depth, 1.0 / cam["scale"], (0,), K, c2w, name)
        if f.depth.shape != hw:
            raise PsimapError(f"depth image {depth} is {f.width}x{f.height} but the camera is {hw[1]}x{hw[0]} "
                              f"(cam_params.json or the Replica default)")
        return f

    return FrameSequence(loader=load_frame, count=len(records), classes=[], root=str(root), layout="replica",
                         names=[r[3] for r in records], report=report)


# The layouts `load` detects, tried in this order (adding one: a reader and a line here,
# docs/extending.md).
LAYOUTS: list[Layout] = [
    Layout("psimap", lambda p: (p / TRANSFORMS).is_file(), lambda p: read_scene(p), "transforms.json"),
    Layout("7scenes", _is_7scenes, lambda p: load_7scenes(p), "7-Scenes frame-*.pose.txt"),
    Layout("scannet", lambda p: all((p / d).is_dir() for d in ("color", "depth", "pose")),
           lambda p: load_scannet(p), "ScanNet color/ depth/ pose/"),
    Layout("replica", lambda p: (p / "traj.txt").is_file() and (p / "results").is_dir(),
           lambda p: load_replica(p), "Replica results/ + traj.txt"),
    # After the layouts above: a TUM or BOP folder has none of their files, and they win on theirs.
    Layout("tum", is_tum, lambda p: load_tum(p), "TUM RGB-D rgb.txt + depth.txt"),
    Layout("bop", is_bop, lambda p: load_bop(p), "or BOP scene_camera.json"),
]
