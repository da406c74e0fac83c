"""The psimap scene folder (docs/scene-format.md): writer, lazy reader, ground truth, labeled PLY.

Layout (nerfstudio style, poses OpenGL on disk, OpenCV in memory)::

    transforms.json   images/<stem>.png   depth/<stem>.png (uint16)   semantic/ instance/ (uint16)
    lidar/<stem>.npy  gt/mesh.ply (per-face `instance`, `semantic`)  gt/instance/ gt/semantic/
    gt/objects/<id>.ply   gt/instances.json

The image helpers here (`read_rgb`, `read_depth_png`, `read_label_png`) are shared with the
real-data loaders in `psimap.data.loaders`; they turn every malformed file into a PsimapError that
names it.
"""
from __future__ import annotations

import json
import math
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from psimap import PsimapError
from psimap.data.frames import ClassInfo, Frame, FrameSequence
from psimap.io_utils import atomic_dir, atomic_path, check_output_dir
from psimap.transforms import PIXEL_CENTER

# OpenGL camera (x right, y up, z back) <-> OpenCV camera (x right, y down, z forward): flip y and z.
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])

TRANSFORMS = "transforms.json"
_UINT16_MAX = 65535


# --------------------------------------------------------------------------------------------------
# image I/O


def _open_image(path: Path):
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise PsimapError(f"missing file: {path}")
    try:
        img = Image.open(path)
        img.load()
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise PsimapError(f"cannot read image {path}: {e}") from None
    return img


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(W, H) of an image from its header only (cheap: for reports and checks before loading)."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise PsimapError(f"missing file: {path}")
    try:
        with Image.open(path) as img:
            return img.size
    except (UnidentifiedImageError, OSError) as e:
        raise PsimapError(f"cannot read image {path}: {e}") from None


def read_rgb(path: str | os.PathLike, size: tuple[int, int] | None = None) -> np.ndarray:
    """Colour image -> [H, W, 3] float32 in [0, 1]. `size` (W, H): resize to it (area average when
    shrinking, so no aliasing; bilinear when enlarging)."""
    from PIL import Image

    img = _open_image(Path(path))
    if img.mode in ("I;16", "I;16B", "I;16L", "I", "F"):
        raise PsimapError(f"colour image {path} is not 8-bit RGB (mode {img.mode})")
    img = img.convert("RGB")
    if size is not None and img.size != tuple(size):
        shrink = size[0] <= img.size[0] and size[1] <= img.size[1]
        img = img.resize(tuple(size), Image.BOX if shrink else Image.BILINEAR)
    return np.asarray(img, dtype=np.float32) / 255.0


def read_depth_png(path: str | os.PathLike, scale: float, invalid: tuple[int, ...] = (0,)) -> np.ndarray:
    """16-bit depth PNG -> [H, W] float32 metres (value * scale); raw values in `invalid` -> 0."""
    path = Path(path)
    img = _open_image(path)
    if img.mode not in ("I;16", "I;16B", "I;16L", "I"):
        raise PsimapError(f"depth image {path} must be a 16-bit single-channel PNG, got mode {img.mode!r}"
                          f" (8-bit depth would lose all precision)")
    raw = np.asarray(img)
    if raw.ndim != 2:
        raise PsimapError(f"depth image {path} must have one channel, got shape {raw.shape}")
    raw = raw.astype(np.int64)
    depth = (raw * float(scale)).astype(np.float32)
    bad = np.isin(raw, invalid) | (raw < 0)
    depth[bad] = 0.0
    return depth


def read_label_png(path: str | os.PathLike, size: tuple[int, int] | None = None) -> np.ndarray:
    """Label image (8- or 16-bit, one channel) -> [H, W] uint16. `size` (W, H): nearest resize."""
    from PIL import Image

    path = Path(path)
    img = _open_image(path)
    if img.mode not in ("L", "P", "I;16", "I;16B", "I;16L", "I"):
        raise PsimapError(f"label image {path} must be a single-channel 8/16-bit PNG, got mode {img.mode!r}")
    if size is not None and img.size != tuple(size):
        # Labels are ids: never interpolate them.
        img = img.resize(tuple(size), Image.NEAREST)
    lab = np.asarray(img)
    if lab.min(initial=0) < 0 or lab.max(initial=0) > _UINT16_MAX:
        raise PsimapError(f"label image {path} has ids outside 0..65535")
    return lab.astype(np.uint16)


def _write_png(path: Path, arr: np.ndarray) -> None:
    from PIL import Image

    # Low zlib level: writing speed matters to the synthetic generator, size barely changes.
    Image.fromarray(arr).save(path, format="PNG", compress_level=1)


def check_pose(c2w: np.ndarray, source: str) -> np.ndarray:
    """Validate a camera-to-world matrix: [4, 4], finite, rotation orthonormal. Returns float64."""
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape != (4, 4):
        raise PsimapError(f"pose in {source} must be a 4x4 matrix, got shape {c2w.shape}")
    if not np.all(np.isfinite(c2w)):
        raise PsimapError(f"pose in {source} has non-finite values (inf/nan)")
    R = c2w[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or abs(np.linalg.det(R) - 1.0) > 1e-3:
        raise PsimapError(f"pose in {source} is not a rigid transform (rotation block not orthonormal)")
    return c2w


# --------------------------------------------------------------------------------------------------
# labeled PLY (trimesh drops unknown per-face properties on export, so this is hand-written)

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


@dataclass
class PlyData:
    """Raw PLY contents: vertices [V, 3] float64, faces [F, 3] int64 (triangles; may be empty),
    vertex_props / face_props: other per-element properties by name ([V] / [F] arrays)."""

    vertices: np.ndarray
    faces: np.ndarray
    vertex_props: dict[str, np.ndarray] = field(default_factory=dict)
    face_props: dict[str, np.ndarray] = field(default_factory=dict)


def write_labeled_ply(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray,
                      face_props: dict[str, np.ndarray] | None = None,
                      vertex_colors: np.ndarray | None = None) -> None:
    """Binary little-endian PLY with int32 per-face properties (e.g. `instance`, `semantic`).

    vertices: [V, 3] float; faces: [F, 3] int; face_props: name -> [F] int;
    vertex_colors: [V, 3|4] uint8 or None. Written atomically.
    """
    vertices = np.asarray(vertices, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    face_props = dict(face_props or {})
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise PsimapError(f"PLY {path}: vertices must be [V, 3], got {vertices.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise PsimapError(f"PLY {path}: face indices out of range 0..{len(vertices) - 1}")
    vfields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if vertex_colors is not None:
        vertex_colors = np.asarray(vertex_colors)
        if vertex_colors.dtype != np.uint8:
            vertex_colors = np.clip(np.round(vertex_colors * (255 if vertex_colors.max(initial=0) <= 1 else 1)),
                                    0, 255).astype(np.uint8)
        names = ["red", "green", "blue", "alpha"][: vertex_colors.shape[1]]
        vfields += [(n, "u1") for n in names]
    vrec = np.empty(len(vertices), dtype=vfields)
    vrec["x"], vrec["y"], vrec["z"] = vertices.T
    if vertex_colors is not None:
        for k, n in enumerate(names):
            vrec[n] = vertex_colors[:, k]
    ffields = [("n", "u1"), ("idx", "<i4", (3,))] + [(n, "<i4") for n in face_props]
    frec = np.empty(len(faces), dtype=ffields)
    frec["n"] = 3
    frec["idx"] = faces
    for n, v in face_props.items():
        v = np.asarray(v).reshape(-1)
        if len(v) != len(faces):
            raise PsimapError(f"PLY {path}: face property {n!r} has {len(v)} values for {len(faces)} faces")
        frec[n] = v
    header = ["ply", "format binary_little_endian 1.0", "comment written by psimap",
              f"element vertex {len(vertices)}"]
    header += [f"property {'float' if t == '<f4' else 'uchar'} {n}" for n, t in vfields]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header += [f"property int {n}" for n in face_props]
    header += ["end_header"]
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vrec.tobytes())
        fh.write(frec.tobytes())


def read_ply(path: str | os.PathLike) -> PlyData:
    """Read a PLY (ascii or binary, either endianness) with any scalar vertex/face properties.

    Faces must be triangles (the only kind psimap writes); other elements are skipped.
    """
    path = Path(path)
    if not path.is_file():
        raise PsimapError(f"missing file: {path}")
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise PsimapError(f"{path} is not a PLY file (no 'ply' magic / end_header)")
    nl = data.find(b"\n", end)
    body = data[nl + 1:]
    lines = data[:end].decode("ascii", "replace").splitlines()
    fmt = None
    elements: list[list] = []  # [name, count, [(prop name, dtype | ("list", count dtype, item dtype))]]
    for line in lines[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        try:
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element":
                elements.append([tok[1], int(tok[2]), []])
            elif tok[0] == "property":
                if tok[1] == "list":
                    elements[-1][2].append((tok[4], ("list", _PLY_TYPES[tok[2]], _PLY_TYPES[tok[3]])))
                else:
                    elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]]))
        except (IndexError, KeyError, ValueError):
            raise PsimapError(f"{path}: malformed PLY header line {line!r}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise PsimapError(f"{path}: unsupported PLY format {fmt!r}")
    endian = ">" if fmt == "binary_big_endian" else "<"
    parsed: dict[str, dict[str, np.ndarray]] = {}
    try:
        if fmt == "ascii":
            parsed = _read_ply_ascii(body, elements)
        else:
            parsed = _read_ply_binary(body, elements, endian)
    except (ValueError, IndexError) as e:
        raise PsimapError(f"{path}: truncated or malformed PLY body ({e})") from None
    vert = parsed.get("vertex", {})
    if not all(k in vert for k in "xyz"):
        raise PsimapError(f"{path}: PLY has no vertex x/y/z")
    vertices = np.stack([vert.pop(k).astype(np.float64) for k in "xyz"], axis=1)
    face = parsed.get("face", {})
    faces = np.zeros((0, 3), dtype=np.int64)
    for key in ("vertex_indices", "vertex_index"):
        if key in face:
            faces = face.pop(key).astype(np.int64)
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise PsimapError(f"{path}: face indices out of range")
    return PlyData(vertices, faces, vert, face)


def _read_ply_binary(body: bytes, elements, endian: str) -> dict:
    out, off = {}, 0
    for name, count, props in elements:
        if any(isinstance(t, tuple) for _, t in props):
            # Fast path: assume all lists hold 3 items (triangles) and check that assumption.
            fields = []
            for pname, t in props:
                if isinstance(t, tuple):
                    fields += [(pname + "#n", endian + t[1]), (pname, endian + t[2], (3,))]
                else:
                    fields.append((pname, endian + t))
            dt = np.dtype(fields)
            if off + dt.itemsize * count > len(body):
                raise ValueError(f"element {name!r} runs past the end of the file")
            rec = np.frombuffer(body, dtype=dt, count=count, offset=off)
            for pname, t in props:
                if isinstance(t, tuple) and count and not np.all(rec[pname + "#n"] == 3):
                    raise ValueError(f"element {name!r} has non-triangle lists (only triangles supported)")
            off += dt.itemsize * count
        else:
            dt = np.dtype([(pname, endian + t) for pname, t in props])
            if off + dt.itemsize * count > len(body):
                raise ValueError(f"element {name!r} runs past the end of the file")
            rec = np.frombuffer(body, dtype=dt, count=count, offset=off)
            off += dt.itemsize * count
        out[name] = {pname: np.array(rec[pname]) for pname, _ in props}
    return out


def _read_ply_ascii(body: bytes, elements) -> dict:
    rows = body.decode("ascii", "replace").splitlines()
    out, r = {}, 0
    for name, count, props in elements:
        chunk = rows[r:r + count]
        if len(chunk) < count:
            raise ValueError(f"element {name!r} has {len(chunk)} of {count} rows")
        r += count
        cols: dict[str, list] = {p: [] for p, _ in props}
        for row in chunk:
            tok = row.split()
            i = 0
            for pname, t in props:
                if isinstance(t, tuple):
                    n = int(tok[i])
                    if n != 3:
                        raise ValueError(f"element {name!r} has non-triangle lists")
                    cols[pname].append([float(x) for x in tok[i + 1:i + 1 + n]])
                    i += 1 + n
                else:
                    cols[pname].append(float(tok[i]))
                    i += 1
        out[name] = {p: np.asarray(cols[p], dtype=(t[2] if isinstance(t, tuple) else t)).reshape(
            (count, 3) if isinstance(t, tuple) else (count,)) for p, t in props}
    return out


def read_labeled_mesh(path: str | os.PathLike):
    """Labeled PLY -> (trimesh.Trimesh with the file's face order, {prop name: [F] int64})."""
    import trimesh

    ply = read_ply(path)
    colors = None
    if all(k in ply.vertex_props for k in ("red", "green", "blue")):
        colors = np.stack([ply.vertex_props[k] for k in ("red", "green", "blue")], axis=1).astype(np.uint8)
    # process=False keeps faces and their order so face labels stay aligned.
    mesh = trimesh.Trimesh(ply.vertices, ply.faces, vertex_colors=colors, process=False)
    props = {k: np.asarray(v).astype(np.int64) for k, v in ply.face_props.items()}
    return mesh, props


# --------------------------------------------------------------------------------------------------
# writer


def _frame_stem(frame: Frame, i: int) -> str:
    stem = frame.name or f"frame_{i:05d}"
    if any(c in stem for c in "/\\") or stem in (".", ".."):
        raise PsimapError(f"frame {i}: name {stem!r} cannot be used as a file name")
    return stem


def _as_label(arr, what: str, hw) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.shape != tuple(hw):
        raise PsimapError(f"{what}: shape {arr.shape} does not match the depth size {tuple(hw)}")
    if arr.size and (arr.min() < 0 or arr.max() > _UINT16_MAX):
        raise PsimapError(f"{what}: ids must lie in 0..65535")
    return arr.astype(np.uint16)


def write_scene(out_dir: str | os.PathLike, frames: list[Frame], classes: list[ClassInfo], *,
                depth_unit_scale_factor: float = 0.001, gt_mesh=None,
                gt_face_instance: np.ndarray | None = None, gt_face_semantic: np.ndarray | None = None,
                gt_objects: dict | None = None, gt_instances: list[dict] | None = None,
                overwrite: bool = False) -> Path:
    """Write frames (+ optional ground truth) as a psimap scene folder, atomically.

    frames: Frame list (rgb [H,W,3] in [0,1], depth [H,W] metres, K [3,3], c2w [4,4] OpenCV, optional
    semantic / instance / gt_semantic / gt_instance [H,W] and lidar [N,4]). All frames share one
    image size; intrinsics that differ from the first frame's are written per frame.
    gt_mesh: trimesh.Trimesh; gt_face_instance / gt_face_semantic: [F] int; gt_objects: {instance id:
    trimesh}; gt_instances: [{"id", "semantic", "name", ...}] (extra JSON-able fields are kept). Depth is quantised to
    `depth_unit_scale_factor` metres; non-finite or negative depth is written as invalid (0).
    A scene folder psimap generated at `out_dir` is replaced; any other non-empty folder is refused
    unless `overwrite` (psimap.io_utils rules: nothing psimap did not write is deleted).
    Returns the folder path.
    """
    out_dir = Path(out_dir)
    if not frames:
        raise PsimapError("write_scene: no frames to write")
    scale = float(depth_unit_scale_factor)
    if not (scale > 0 and math.isfinite(scale)):
        raise PsimapError(f"write_scene: depth_unit_scale_factor must be > 0, got {depth_unit_scale_factor}")
    h, w = frames[0].depth.shape[:2]
    K0 = np.asarray(frames[0].K, dtype=np.float64)
    stems = [_frame_stem(f, i) for i, f in enumerate(frames)]
    if len(set(stems)) != len(stems):
        raise PsimapError("write_scene: frame names must be unique")
    meta = {
        "camera_model": "OPENCV",
        "fl_x": float(K0[0, 0]), "fl_y": float(K0[1, 1]), "cx": float(K0[0, 2]), "cy": float(K0[1, 2]),
        "w": int(w), "h": int(h), "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "depth_unit_scale_factor": scale,
        "classes": [{"id": int(c.id), "name": str(c.name), "isthing": bool(c.isthing)} for c in classes],
        "frames": [],
    }
    if any(c.id == 0 for c in classes):
        raise PsimapError("write_scene: class id 0 is reserved for void / no label")

    check_output_dir(out_dir, "scene", overwrite=overwrite)

    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    # PNG encoding (zlib) releases the GIL: encode on a few threads while the next frame is checked.
    with atomic_dir(out_dir, "scene", overwrite=overwrite) as tmp, ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool:
        png_jobs = []
        for sub in ("images", "depth"):
            (tmp / sub).mkdir()
        for i, (f, stem) in enumerate(tqdm(list(zip(frames, stems)), desc="writing frames", unit="frame",
                                           disable=None, leave=False)):
            what = f"frame {i} ({stem})"
            depth = np.asarray(f.depth, dtype=np.float64)
            if depth.shape != (h, w):
                raise PsimapError(f"write_scene: {what} depth is {depth.shape}, expected {(h, w)}")
            rgb = np.asarray(f.rgb, dtype=np.float32)
            if rgb.shape != (h, w, 3):
                raise PsimapError(f"write_scene: {what} rgb is {rgb.shape}, expected {(h, w, 3)}")
            K = np.asarray(f.K, dtype=np.float64)
            if K.shape != (3, 3) or not np.all(np.isfinite(K)):
                raise PsimapError(f"write_scene: {what} K must be a finite 3x3 matrix")
            c2w = check_pose(f.c2w, f"write_scene {what}")
            rgb8 = np.round(np.clip(np.nan_to_num(rgb), 0.0, 1.0) * 255.0).astype(np.uint8)
            png_jobs.append(pool.submit(_write_png, tmp / "images" / f"{stem}.png", rgb8))
            q = np.where(np.isfinite(depth) & (depth > 0), np.round(depth / scale), 0.0)
            if q.max(initial=0) > _UINT16_MAX:
                raise PsimapError(f"write_scene: {what} depth {depth[np.isfinite(depth)].max():.3f} m exceeds "
                                  f"the uint16 range at depth_unit_scale_factor={scale}; use a larger factor")
            png_jobs.append(pool.submit(_write_png, tmp / "depth" / f"{stem}.png", q.astype(np.uint16)))
            entry = {"file_path": f"images/{stem}.png", "depth_file_path": f"depth/{stem}.png",
                     "transform_matrix": (c2w @ GL_TO_CV).tolist()}
            if not np.allclose(K, K0, rtol=0, atol=1e-9):
                entry.update(fl_x=float(K[0, 0]), fl_y=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]))
            for key, arr, sub in (("semantic_file_path", f.semantic, "semantic"),
                                  ("instance_file_path", f.instance, "instance"),
                                  (None, f.gt_semantic, "gt/semantic"),
                                  (None, f.gt_instance, "gt/instance")):
                if arr is None:
                    continue
                (tmp / sub).mkdir(parents=True, exist_ok=True)
                png_jobs.append(pool.submit(_write_png, tmp / sub / f"{stem}.png",
                                            _as_label(arr, f"write_scene: {what} {sub}", (h, w))))
                if key:
                    entry[key] = f"{sub}/{stem}.png"
            if f.lidar is not None:
                pts = np.asarray(f.lidar, dtype=np.float32)
                if pts.ndim != 2 or pts.shape[1] != 4:
                    raise PsimapError(f"write_scene: {what} lidar must be [N, 4], got {pts.shape}")
                (tmp / "lidar").mkdir(exist_ok=True)
                np.save(tmp / "lidar" / f"{stem}.npy", pts)
                entry["lidar_file_path"] = f"lidar/{stem}.npy"
                if f.lidar_origin is not None:
                    entry["lidar_origin"] = [float(v) for v in np.asarray(f.lidar_origin).reshape(3)]
            meta["frames"].append(entry)
        for job in png_jobs:
            job.result()              # re-raise any write error before the folder is published
        (tmp / TRANSFORMS).write_text(json.dumps(meta, indent=1))
        _write_gt(tmp / "gt", gt_mesh, gt_face_instance, gt_face_semantic, gt_objects, gt_instances)
    return out_dir


def _write_gt(gt_dir: Path, mesh, face_instance, face_semantic, objects, instances) -> None:
    if mesh is not None:
        nf = len(mesh.faces)
        props = {}
        for name, arr in (("instance", face_instance), ("semantic", face_semantic)):
            arr = np.zeros(nf, dtype=np.int64) if arr is None else np.asarray(arr).reshape(-1)
            if len(arr) != nf:
                raise PsimapError(f"write_scene: gt face {name} labels have {len(arr)} values for {nf} faces")
            props[name] = arr
        colors = None
        vc = getattr(getattr(mesh, "visual", None), "vertex_colors", None)
        if getattr(mesh.visual, "kind", None) == "vertex" and vc is not None and len(vc) == len(mesh.vertices):
            colors = np.asarray(vc)[:, :3]
        gt_dir.mkdir(parents=True, exist_ok=True)
        write_labeled_ply(gt_dir / "mesh.ply", mesh.vertices, mesh.faces, props, vertex_colors=colors)
    elif face_instance is not None or face_semantic is not None:
        raise PsimapError("write_scene: gt face labels given without gt_mesh")
    if objects:
        (gt_dir / "objects").mkdir(parents=True, exist_ok=True)
        for oid, obj in objects.items():
            obj.export(gt_dir / "objects" / f"{int(oid)}.ply")
    if instances is not None:
        gt_dir.mkdir(parents=True, exist_ok=True)
        try:
            rows = [{**r, "id": int(r["id"]), "semantic": int(r["semantic"]), "name": str(r.get("name", ""))}
                    for r in instances]
            text = json.dumps(rows, indent=1, default=_json_plain)
        except (KeyError, TypeError, ValueError) as e:
            raise PsimapError(f"write_scene: gt_instances must be dicts with 'id' and 'semantic' ({e})") from None
        (gt_dir / "instances.json").write_text(text)


def _json_plain(v):
    """numpy scalars / arrays in extra instance fields -> plain JSON values."""
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(f"{type(v).__name__} is not JSON serialisable")


# --------------------------------------------------------------------------------------------------
# reader


# Pinhole camera models (COLMAP names, as nerfstudio writes them) psimap reads; the others
# (OPENCV_FISHEYE, FISHEYE624, EQUIRECTANGULAR, VR180_*, ...) need reprojecting first.
PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
# Lens distortion that moves no pixel further than this is ignored; more is undistorted.
MAX_IGNORED_DISTORTION_PX = 0.5
# Colour and depth at different resolutions must show the same view: aspect ratios within 1 %.
_ASPECT_TOLERANCE = 0.01


def _resized_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """K [3, 3] of the same view resampled by sx, sy (pixel edges scale, centres do not)."""
    K = np.array(K, np.float64)
    K[0, 0], K[1, 1] = K[0, 0] * sx, K[1, 1] * sy
    K[0, 2] = (K[0, 2] + 0.5 - PIXEL_CENTER) * sx - 0.5 + PIXEL_CENTER
    K[1, 2] = (K[1, 2] + 0.5 - PIXEL_CENTER) * sy - 0.5 + PIXEL_CENTER
    return K


def read_scene(root: str | os.PathLike) -> FrameSequence:
    """Open a scene folder (or its transforms.json) as a lazily loaded FrameSequence.

    transforms.json, poses and file existence are checked up front (cheap); images are read when a
    frame is accessed. Poses are converted OpenGL -> OpenCV.

    The same reader opens nerfstudio's processed folders (`ns-process-data`: Record3D, Polycam,
    KIRI, Metashape, COLMAP with depth): a transforms.json without psimap's `classes` key is read
    as nerfstudio writes it (layout "nerfstudio"): pixel centres at +0.5 (so cx, cy move by -0.5),
    depth in millimetres unless `depth_unit_scale_factor` says otherwise. In both, depth at another
    resolution than the colour (a phone's 256x192 depth beside 1920x1440 colour) sets the frame
    size: colour and K are resampled to it; lens distortion above MAX_IGNORED_DISTORTION_PX is
    undistorted, below it ignored; non-pinhole camera models are refused.
    """
    from psimap.data.frames import LoadReport
    from psimap.data.lens import COEFFS, max_displacement

    root = Path(root)
    tf_path = root if root.is_file() else root / TRANSFORMS
    root = tf_path.parent
    if not tf_path.is_file():
        raise PsimapError(f"missing file: {tf_path}")
    try:
        meta = json.loads(tf_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise PsimapError(f"{tf_path} is not valid JSON: {e}") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise PsimapError(f"{tf_path} has no 'frames' list (not a nerfstudio transforms.json)")
    layout = "psimap" if "classes" in meta else "nerfstudio"
    model = meta.get("camera_model", "OPENCV")
    if model not in PINHOLE_MODELS:
        raise PsimapError(f"{tf_path}: camera_model {model!r} is not a pinhole camera (psimap reads "
                          f"{', '.join(PINHOLE_MODELS)}; reproject fisheye / panoramic images first)")
    report = LoadReport(poses="transform_matrix: camera-to-world, OpenGL camera axes (converted to OpenCV)")
    try:
        scale = float(meta.get("depth_unit_scale_factor", 0.001))
    except (TypeError, ValueError):
        scale = float("nan")
    if not (scale > 0 and math.isfinite(scale)):
        raise PsimapError(f"{tf_path}: depth_unit_scale_factor must be > 0, got {meta.get('depth_unit_scale_factor')}")
    if "depth_unit_scale_factor" not in meta:
        report.assumed.append("no depth_unit_scale_factor: depth PNGs in millimetres (nerfstudio's default 0.001)")
    # nerfstudio casts a pixel's ray through its centre at index + 0.5; psimap's is PIXEL_CENTER.
    half = 0.5 - PIXEL_CENTER if layout == "nerfstudio" else 0.0
    try:
        classes = [ClassInfo(int(c["id"]), str(c["name"]), bool(c.get("isthing", True)))
                   for c in meta.get("classes", [])]
    except (KeyError, TypeError, ValueError):
        raise PsimapError(f"{tf_path}: 'classes' entries need 'id' and 'name'") from None

    records, displacement, masked = [], {}, 0
    for i, fr in enumerate(meta["frames"]):
        src = f"{tf_path} frame {i}"
        if not isinstance(fr, dict):
            raise PsimapError(f"{src}: expected an object with file_path, depth_file_path, transform_matrix")
        if ("file_path" in fr and "transform_matrix" in fr and not fr.get("depth_file_path")
                and not fr.get("lidar_file_path")):
            raise PsimapError(f"{src} has no depth_file_path (nor a lidar_file_path): psimap trains on RGB-D "
                              f"frames or colour + LiDAR (a capture without depth, e.g. plain COLMAP, cannot be used)")
        try:
            fl_x = float(fr.get("fl_x", meta.get("fl_x")))
            fl_y = float(fr.get("fl_y", meta.get("fl_y", fl_x)))
            cx = float(fr.get("cx", meta.get("cx"))) - half
            cy = float(fr.get("cy", meta.get("cy"))) - half
            file_path = fr["file_path"]
            # a LiDAR + colour capture may have no depth images (psimap.train uses the sweeps)
            depth_path = fr["depth_file_path"] if not fr.get("lidar_file_path") else fr.get("depth_file_path")
            origin = fr.get("lidar_origin")
            origin = None if origin is None else np.asarray(origin, dtype=np.float64).reshape(3)
            c2w_gl = np.asarray(fr["transform_matrix"], dtype=np.float64)
            w, h = fr.get("w", meta.get("w")), fr.get("h", meta.get("h"))
            w, h = image_size(root / file_path) if w is None or h is None else (int(w), int(h))
            coeffs = {k: float(fr.get(k, meta.get(k, 0.0)) or 0.0) for k in COEFFS}
        except (KeyError, TypeError, ValueError):
            raise PsimapError(f"{src}: needs file_path, depth_file_path (or lidar_file_path), transform_matrix "
                              f"and intrinsics (fl_x, fl_y, cx, cy, w, h); lidar_origin, if given, 3 numbers") from None
        if origin is not None and not np.all(np.isfinite(origin)):
            raise PsimapError(f"{src}: lidar_origin must be finite")
        if c2w_gl.shape == (3, 4):          # some exporters drop the constant last row
            c2w_gl = np.vstack([c2w_gl, [0.0, 0.0, 0.0, 1.0]])
        K = np.array([[fl_x, 0.0, cx], [0.0, fl_y, cy], [0.0, 0.0, 1.0]])
        if not np.all(np.isfinite(K)) or fl_x <= 0 or fl_y <= 0 or w <= 0 or h <= 0:
            raise PsimapError(f"{src}: invalid intrinsics")
        if not all(math.isfinite(v) for v in coeffs.values()):
            raise PsimapError(f"{src}: non-finite distortion coefficients")
        key = (fl_x, fl_y, cx, cy, w, h, *coeffs.values())
        if key not in displacement:
            displacement[key] = max_displacement(K, (h, w), coeffs) if any(coeffs.values()) else 0.0
        lens = coeffs if displacement[key] > MAX_IGNORED_DISTORTION_PX else None
        c2w = check_pose(c2w_gl, f"{src} ({file_path})") @ GL_TO_CV
        paths = {"rgb": root / file_path}
        if depth_path:
            paths["depth"] = root / depth_path
            if Path(depth_path).suffix.lower() not in (".png", ".tif", ".tiff"):
                raise PsimapError(f"{src}: depth {depth_path} must be a 16-bit PNG (or TIFF); convert other "
                                  f"depth files to millimetre PNGs")
        for key, meta_key in (("semantic", "semantic_file_path"), ("instance", "instance_file_path"),
                              ("lidar", "lidar_file_path")):
            if fr.get(meta_key):
                paths[key] = root / fr[meta_key]
        masked += bool(fr.get("mask_path"))
        stem = Path(file_path).stem
        for key in ("semantic", "instance"):
            p = root / "gt" / key / f"{stem}.png"
            if p.is_file():
                paths["gt_" + key] = p
        for p in paths.values():
            if not p.is_file():
                raise PsimapError(f"missing file: {p} (listed in {tf_path})")
        records.append((paths, K, c2w, (h, w), stem, lens, origin))

    h0, w0 = records[0][3]
    first_depth = next((r[0]["depth"] for r in records if "depth" in r[0]), None)
    dw, dh = (w0, h0) if first_depth is None else image_size(first_depth)
    report.resolution = (dw, dh)
    report.depth = f"16-bit PNG x {scale:g} m (0 invalid)"
    n_nodepth = sum("depth" not in r[0] for r in records)
    if n_nodepth:
        report.depth += f"; {n_nodepth} of {len(records)} frames have no depth image (colour + LiDAR)"
    if (dw, dh) != (w0, h0):
        report.depth += f"; colour {w0}x{h0} resampled to the depth size {dw}x{dh} (K scaled with it)"
    report.intrinsics = f"{TRANSFORMS} fl_x, fl_y, cx, cy (camera_model {model})"
    if half:
        report.intrinsics += "; cx, cy - 0.5 (nerfstudio puts pixel centres at +0.5)"
    worst = max(displacement.values())
    if any(r[5] is not None for r in records):
        report.assumed.append(f"lens distortion moves pixels up to {worst:.1f} px: images undistorted "
                              f"(same K, pinhole)")
    elif worst > 0:
        report.assumed.append(f"lens distortion moves pixels at most {worst:.2f} px "
                              f"(<= {MAX_IGNORED_DISTORTION_PX} px): ignored")
    if "applied_transform" in meta:
        report.poses += "; world as written (applied_transform already in the poses)"
    if layout == "nerfstudio":
        report.assumed.append("world frame as written (often Y-up): gravity is found at export (--up auto)")
    if masked:
        report.assumed.append(f"mask_path of {masked} frames ignored (every pixel is used)")
    n_sem = sum("semantic" in r[0] for r in records)
    n_ins = sum("instance" in r[0] for r in records)
    report.labels = (f"semantic_file_path on {n_sem}, instance_file_path on {n_ins} of {len(records)} frames, "
                     f"{len(classes)} classes" if n_sem or n_ins else "none")

    def load_frame(i: int) -> Frame:
        from psimap.data.lens import undistort

        paths, K, c2w, (h, w), stem, lens, origin = records[i]
        # a colour + LiDAR frame has no depth image: all invalid, at the colour size
        depth = read_depth_png(paths["depth"], scale) if "depth" in paths else np.zeros((h, w), np.float32)
        fh, fw = depth.shape
        if (fh, fw) != (h, w):
            if abs((fw / fh) / (w / h) - 1.0) > _ASPECT_TOLERANCE:
                raise PsimapError(f"depth image {paths['depth']} is {fw}x{fh} but the colour camera is {w}x{h} "
                                  f"(different aspect ratios: not the same view)")
            K = _resized_intrinsics(K, fw / w, fh / h)
        rgb_size = image_size(paths["rgb"])
        if rgb_size != (w, h):
            raise PsimapError(f"colour image {paths['rgb']} is {rgb_size[0]}x{rgb_size[1]} but the camera "
                              f"({TRANSFORMS} w, h) is {w}x{h}")
        rgb = read_rgb(paths["rgb"], size=(fw, fh))
        labels = {}
        for key in ("semantic", "instance", "gt_semantic", "gt_instance"):
            if key in paths:
                lw, lh = image_size(paths[key])
                if (lw, lh) not in ((fw, fh), (w, h)):
                    raise PsimapError(f"{key} image {paths[key]} is {lw}x{lh} but the frame is {fw}x{fh} "
                                      f"(colour {w}x{h})")
                labels[key] = read_label_png(paths[key], size=(fw, fh))
        if lens is not None:
            rgb = undistort(rgb, K, lens, order=1)
            depth = undistort(depth, K, lens, order=0)
            labels = {k: undistort(v, K, lens, order=0) for k, v in labels.items()}
        lidar = read_lidar(paths["lidar"]) if "lidar" in paths else None
        return Frame(rgb=rgb, depth=depth, K=K.copy(), c2w=c2w.copy(), lidar=lidar, name=stem,
                     lidar_origin=None if origin is None else origin.copy(), **labels)

    return FrameSequence(loader=load_frame, count=len(records), classes=classes, root=str(root),
                         layout=layout, names=[r[4] for r in records], report=report)


def read_lidar(path: str | os.PathLike) -> np.ndarray:
    """LiDAR points -> [N, 4] float32 (x, y, z world, intensity). .npy (N x 4 or N x 3) or .ply
    (vertex x, y, z and an `intensity` / `reflectance` / `scalar_intensity` property; 0 if absent)."""
    path = Path(path)
    if not path.is_file():
        raise PsimapError(f"missing file: {path}")
    if path.suffix.lower() == ".npy":
        try:
            pts = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as e:
            raise PsimapError(f"cannot read LiDAR file {path}: {e}") from None
    elif path.suffix.lower() == ".ply":
        ply = read_ply(path)
        inten = next((ply.vertex_props[k] for k in ("intensity", "reflectance", "scalar_intensity")
                      if k in ply.vertex_props), np.zeros(len(ply.vertices)))
        pts = np.column_stack([ply.vertices, inten])
    else:
        raise PsimapError(f"LiDAR file {path}: unsupported extension (use .npy or .ply)")
    if pts.ndim == 2 and pts.shape[1] == 3:
        pts = np.column_stack([pts, np.zeros(len(pts))])
    if pts.ndim != 2 or pts.shape[1] != 4:
        raise PsimapError(f"LiDAR file {path} must hold N x 4 (x, y, z, intensity), got shape {pts.shape}")
    pts = pts.astype(np.float32)
    if not np.all(np.isfinite(pts)):
        raise PsimapError(f"LiDAR file {path} has non-finite values")
    return pts


# --------------------------------------------------------------------------------------------------
# ground truth


@dataclass
class GroundTruth:
    """What a scene folder's gt/ holds. mesh: trimesh.Trimesh or None; face_instance / face_semantic:
    [F] int64 (None without a mesh); objects: {instance id: path of its complete mesh};
    instances: [{"id", "semantic", "name", ...extra fields the writer was given}]."""

    mesh: object = None
    face_instance: np.ndarray | None = None
    face_semantic: np.ndarray | None = None
    objects: dict[int, Path] = field(default_factory=dict)
    instances: list[dict] = field(default_factory=list)


def read_gt(root: str | os.PathLike) -> GroundTruth:
    """Read `root/gt/` (missing parts stay None / empty)."""
    gt_dir = Path(root) / "gt"
    gt = GroundTruth()
    if (gt_dir / "mesh.ply").is_file():
        mesh, props = read_labeled_mesh(gt_dir / "mesh.ply")
        nf = len(mesh.faces)
        gt.mesh = mesh
        gt.face_instance = props.get("instance", np.zeros(nf, dtype=np.int64))
        gt.face_semantic = props.get("semantic", np.zeros(nf, dtype=np.int64))
    if (gt_dir / "objects").is_dir():
        for p in sorted((gt_dir / "objects").iterdir()):
            if p.suffix.lower() in (".ply", ".obj", ".glb", ".stl") and p.stem.lstrip("-").isdigit():
                gt.objects[int(p.stem)] = p
    if (gt_dir / "instances.json").is_file():
        try:
            rows = json.loads((gt_dir / "instances.json").read_text())
            gt.instances = [{**r, "id": int(r["id"]), "semantic": int(r["semantic"]),
                             "name": str(r.get("name", ""))} for r in rows]
        except (json.JSONDecodeError, KeyError, TypeError, ValueError):
            raise PsimapError(f"{gt_dir / 'instances.json'}: expected a list of {{id, semantic, name}}") from None
    return gt
