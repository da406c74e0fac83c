"""Masks from 2D segmenters -> per-frame labels of a capture: `psimap import-masks`.

Formats (docs/scene-format.md, "Importing masks from 2D models"):
- COCO panoptic: a JSON (`annotations[].segments_info`, `categories`) + one RGB PNG per image whose
  segment id is R + 256 G + 256^2 B (what Mask2Former / OneFormer / detectron2 pipelines write, and
  `psimap labels`);
- COCO instances: a dataset (`images`, `annotations`, `categories`) or a results list
  (`[{image_id, category_id, segmentation, score}]`, its images and categories from `--images`);
  `segmentation` as compressed or uncompressed RLE or polygons;
- SAM automatic masks (no classes: class `object`): amg.py's folder per image (`0.png, 1.png, ...` +
  `metadata.csv`) or its JSON per image (a list of {"segmentation": RLE, "predicted_iou",
  "stability_score", ...}).

Every format becomes, per image, a list of `SourceMask`s; one overlap rule (`paint_masks`) turns them
into a semantic and an instance map; `label_overlay.write_label_overlay` writes those.
"""
from __future__ import annotations

import csv
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from psimap import PsimapError
from psimap.data.frames import ClassInfo

FORMATS = ("coco-panoptic", "coco-instances", "sam")
UNMAPPED_RULES = ("keep", "object", "void", "error")
SAM_CLASS = "object"
# A mask lying at least NESTED inside one at least 1 / NESTED_SHARE times its size is painted over
# it whatever the scores: it is a thing on (or a part of) the larger region, which would otherwise
# swallow it. A mask about as large as the one around it is a second guess of the same region: the
# scores decide between the two.
NESTED = 0.8
NESTED_SHARE = 0.5
# A mask that keeps less than this share of its pixels once the masks above it are painted (pixels
# under masks nested in it count as kept) is dropped: a duplicate of a better mask, not an object.
MIN_VISIBLE = 0.5
# --resize: the mask's and the frame's aspect ratios may differ by this much (ScanNet: 0.4 %).
RESIZE_ASPECT_TOL = 0.02


@dataclass
class SourceMask:
    """One mask as the segmenter gave it. mask: [H, W] bool; category: source category id."""

    mask: np.ndarray
    category: int
    score: float = 1.0
    iscrowd: bool = False


@dataclass
class SourceImage:
    """The masks of one image: `key` is the image's file name (or stem) the segmenter saw, matched to
    a frame name (`match_frame`); `origin` names it in errors; `read()` decodes its masks."""

    key: str
    origin: str
    read: Callable[[], list[SourceMask]]


@dataclass
class MaskSource:
    format: str
    path: Path
    categories: dict[int, tuple[str, bool]]      # source category id -> (name, isthing)
    images: list[SourceImage]
    used: set[int] = field(default_factory=set)  # category ids some mask (above --min-score) names


# --------------------------------------------------------------------------------------------------
# reading helpers


def _read_json(path: Path):
    if not path.is_file():
        raise PsimapError(f"missing file: {path}")
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise PsimapError(f"{path}: not valid JSON ({e})") from None


def _rle_counts(counts: bytes) -> list[int]:
    """The run lengths of a compressed COCO RLE string (pycocotools' LEB128-like code: 6-bit chunks
    offset by 48, 0x20 = more, the last chunk sign-extended; runs after the second are deltas).

    Decoded here only to check them: pycocotools decodes a string whose runs do not add up to
    H x W from uninitialised memory instead of failing."""
    out: list[int] = []
    p = 0
    while p < len(counts):
        x, k, more = 0, 0, True
        while more:
            if p >= len(counts):
                raise ValueError("truncated")
            c = counts[p] - 48
            if not 0 <= c < 64:
                raise ValueError(f"byte {counts[p]!r} outside the RLE alphabet")
            x |= (c & 0x1F) << (5 * k)
            more = bool(c & 0x20)
            p, k = p + 1, k + 1
            if not more and c & 0x10:
                x |= -1 << (5 * k)
        if len(out) > 2:
            x += out[-2]
        out.append(x)
    return out


def _decode(rle) -> np.ndarray:
    import warnings

    from pycocotools import mask as cocomask

    with warnings.catch_warnings():
        # pycocotools 2.0.11 asks numpy 2 for copy=False inside decode: a warning of its own making
        warnings.simplefilter("ignore", DeprecationWarning)
        return cocomask.decode(rle).astype(bool)


def decode_segmentation(seg, hw: tuple[int, int] | None, where: str) -> np.ndarray:
    """A COCO `segmentation` (compressed / uncompressed RLE, or polygons) -> [H, W] bool.

    hw: (H, W) the image entry declares (needed by polygons), or None. Malformed input is one
    PsimapError naming `where`."""
    from pycocotools import mask as cocomask

    if isinstance(seg, dict):
        try:
            h, w = (int(v) for v in seg["size"])
            counts = seg["counts"]
        except (KeyError, TypeError, ValueError):
            raise PsimapError(f"{where}: RLE needs \"size\": [H, W] and \"counts\"") from None
        if h <= 0 or w <= 0:
            raise PsimapError(f"{where}: RLE size {h}x{w} is empty")
        if hw is not None and (h, w) != tuple(hw):
            raise PsimapError(f"{where}: RLE is {w}x{h} but its image is {hw[1]}x{hw[0]}")
        try:
            if isinstance(counts, list):
                runs = [int(c) for c in counts]
                if any(c < 0 for c in runs) or any(c != v for c, v in zip(runs, counts)):
                    raise ValueError("counts must be non-negative integers")
                rle = cocomask.frPyObjects({"size": [h, w], "counts": runs}, h, w) if runs else None
            elif isinstance(counts, (str, bytes)):
                raw = counts.encode("ascii") if isinstance(counts, str) else counts
                runs = _rle_counts(raw)
                rle = {"size": [h, w], "counts": raw}
            else:
                raise ValueError("counts must be a string or a list")
            if sum(runs) != h * w or any(c < 0 for c in runs):
                raise ValueError(f"runs add up to {sum(runs)} pixels, not {h}x{w} = {h * w}")
            return _decode(rle)
        except (ValueError, TypeError, UnicodeEncodeError) as e:
            raise PsimapError(f"{where}: malformed RLE ({e})") from None
    if isinstance(seg, list):
        if hw is None:
            raise PsimapError(f"{where}: polygons need the image's height and width")
        polys = []
        for poly in seg:
            try:
                xy = np.asarray(poly, dtype=np.float64).ravel()
            except (TypeError, ValueError):
                raise PsimapError(f"{where}: a polygon must be a list of numbers x0, y0, x1, y1, ...") from None
            if xy.size < 6 or xy.size % 2 or not np.all(np.isfinite(xy)):
                raise PsimapError(f"{where}: a polygon needs at least 3 finite (x, y) points")
            polys.append(xy.tolist())
        if not polys:
            raise PsimapError(f"{where}: empty polygon list")
        rles = cocomask.frPyObjects(polys, int(hw[0]), int(hw[1]))
        return _decode(cocomask.merge(rles))
    raise PsimapError(f"{where}: segmentation must be an RLE object or a list of polygons")


def _read_binary_png(path: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise PsimapError(f"missing file: {path}")
    try:
        with Image.open(path) as img:
            arr = np.asarray(img)
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise PsimapError(f"cannot read image {path}: {e}") from None
    if arr.ndim == 3:                       # an RGB(A) mask: any non-black pixel
        arr = arr[..., :3].max(axis=-1)
    return arr > 0


def _categories(meta: dict, path: Path) -> dict[int, tuple[str, bool]]:
    cats = meta.get("categories")
    if not isinstance(cats, list) or not cats:
        raise PsimapError(f"{path}: no \"categories\" list (COCO: [{{\"id\", \"name\", \"isthing\"}}])")
    out = {}
    for c in cats:
        try:
            cid = int(c["id"])
            # COCO instances' categories have no "isthing": each is an object
            out[cid] = (str(c.get("name", cid)), bool(c.get("isthing", 1)))
        except (KeyError, TypeError, ValueError):
            raise PsimapError(f"{path}: every category needs an integer \"id\"") from None
    return out


def _score(entry: dict, where: str, *keys: str) -> float:
    s = 1.0
    for k in keys:
        if k in entry:
            try:
                v = float(entry[k])
            except (TypeError, ValueError):
                raise PsimapError(f"{where}: \"{k}\" must be a number") from None
            if not np.isfinite(v):
                raise PsimapError(f"{where}: \"{k}\" is not finite")
            s *= v
    return s


# --------------------------------------------------------------------------------------------------
# COCO panoptic


def _panoptic_png_dir(path: Path) -> list[Path]:
    """Where a panoptic JSON's PNGs are: COCO's sibling folder named after it
    (panoptic_val2017.json + panoptic_val2017/), else next to it (`psimap labels`)."""
    return [d for d in (path.with_suffix(""), path.parent) if d.is_dir()]


def read_coco_panoptic(path: Path) -> MaskSource:
    from PIL import Image

    meta = _read_json(path)
    if not isinstance(meta, dict) or not isinstance(meta.get("annotations"), list):
        raise PsimapError(f"{path}: not a COCO panoptic file (no \"annotations\" list)")
    categories = _categories(meta, path)
    image_names = {}
    for im in meta.get("images") or []:
        if isinstance(im, dict) and "id" in im and "file_name" in im:
            image_names[im["id"]] = str(im["file_name"])
    dirs = _panoptic_png_dir(path)
    source = MaskSource("coco-panoptic", path, categories, [])
    for n, ann in enumerate(meta["annotations"]):
        where = f"{path} annotation {n}"
        if not isinstance(ann, dict) or "file_name" not in ann or not isinstance(ann.get("segments_info"), list):
            raise PsimapError(f"{where}: needs \"file_name\" (its PNG) and \"segments_info\"")
        png = next((d / ann["file_name"] for d in dirs if (d / ann["file_name"]).is_file()), None)
        if png is None:
            raise PsimapError(f"{where}: missing file {ann['file_name']} (looked in "
                              + ", ".join(str(d) for d in dirs) + ")")
        segments = {}
        for s in ann["segments_info"]:
            try:
                sid, cid = int(s["id"]), int(s["category_id"])
            except (KeyError, TypeError, ValueError):
                raise PsimapError(f"{where}: every segment needs an integer \"id\" and \"category_id\"") from None
            if cid not in categories:
                raise PsimapError(f"{where}: segment {sid} has category_id {cid}, which \"categories\" "
                                  f"does not list")
            if sid <= 0:
                raise PsimapError(f"{where}: segment id {sid} (0 is void in the PNG)")
            segments[sid] = SourceMask(None, cid, _score(s, where, "score"), bool(s.get("iscrowd", 0)))
            source.used.add(cid)

        def read(png=png, segments=segments, where=where) -> list[SourceMask]:
            try:
                with Image.open(png) as img:
                    rgb = np.asarray(img.convert("RGB") if img.mode in ("RGB", "RGBA", "P") else img)
            except OSError as e:
                raise PsimapError(f"cannot read image {png}: {e}") from None
            if rgb.ndim != 3 or rgb.dtype != np.uint8:
                raise PsimapError(f"{png}: a COCO panoptic PNG is 8-bit RGB (id = R + 256 G + 256^2 B)")
            rgb = rgb.astype(np.int64)
            ids = rgb[..., 0] + 256 * rgb[..., 1] + 65536 * rgb[..., 2]
            present, inverse = np.unique(ids, return_inverse=True)
            inverse = inverse.reshape(ids.shape)
            unknown = [int(i) for i in present if i and int(i) not in segments]
            if unknown:
                raise PsimapError(f"{png}: segment ids {unknown[:5]} are not in segments_info ({where})")
            out = []
            for k, sid in enumerate(present.tolist()):
                if sid:
                    s = segments[sid]
                    out.append(SourceMask(inverse == k, s.category, s.score, s.iscrowd))
            return out

        image_id = ann.get("image_id")
        key = image_names.get(image_id, ann["file_name"]) if isinstance(image_id, (int, str)) else ann["file_name"]
        source.images.append(SourceImage(str(key), str(png), read))
    return source


# --------------------------------------------------------------------------------------------------
# COCO instances (dataset or results list)


def read_coco_instances(path: Path, images: Path | None = None, min_score: float = 0.0) -> MaskSource:
    data = _read_json(path)
    if isinstance(data, list):
        if images is None:
            raise PsimapError(f"{path} is a COCO results list: pass --images COCO.json (its \"images\" map "
                              f"image_id to file_name, its \"categories\" name the classes)")
        anns = data
    elif isinstance(data, dict) and isinstance(data.get("annotations"), list):
        anns = data["annotations"]
    else:
        raise PsimapError(f"{path}: not COCO instances (a dict with \"annotations\", or a results list)")
    meta_path = images or path
    meta = data if images is None else _read_json(images)
    if not isinstance(meta, dict) or not isinstance(meta.get("images"), list):
        raise PsimapError(f"{meta_path}: no \"images\" list ([{{\"id\", \"file_name\", \"height\", \"width\"}}])")
    categories = _categories(meta, meta_path)
    entries = {}
    for n, im in enumerate(meta["images"]):
        try:
            entries[im["id"]] = (str(im["file_name"]), (int(im["height"]), int(im["width"])))
        except (KeyError, TypeError, ValueError):
            raise PsimapError(f"{meta_path} image {n}: needs \"id\", \"file_name\", \"height\", \"width\"") from None
    by_image: dict = {k: [] for k in entries}
    source = MaskSource("coco-instances", path, categories, [])
    for n, ann in enumerate(anns):
        where = f"{path} annotation {n}"
        if not isinstance(ann, dict) or "segmentation" not in ann or "image_id" not in ann:
            raise PsimapError(f"{where}: needs \"image_id\", \"category_id\" and \"segmentation\"")
        if not isinstance(ann["image_id"], (int, str)) or ann["image_id"] not in entries:
            raise PsimapError(f"{where}: image_id {ann['image_id']!r} is not in {meta_path}'s \"images\"")
        try:
            cid = int(ann["category_id"])
        except (KeyError, TypeError, ValueError):
            raise PsimapError(f"{where}: needs an integer \"category_id\"") from None
        if cid not in categories:
            raise PsimapError(f"{where}: category_id {cid} is not in {meta_path}'s \"categories\"")
        score = _score(ann, where, "score")
        if score >= min_score:
            source.used.add(cid)
        by_image[ann["image_id"]].append((n, ann, cid, score))
    for image_id, (file_name, hw) in entries.items():
        def read(items=by_image[image_id], hw=hw) -> list[SourceMask]:
            return [SourceMask(decode_segmentation(a["segmentation"], hw, f"{path} annotation {n}"), cid, score,
                               bool(a.get("iscrowd", 0))) for n, a, cid, score in items]

        source.images.append(SourceImage(file_name, f"{meta_path} image {file_name}", read))
    return source


# --------------------------------------------------------------------------------------------------
# SAM automatic masks


def _sam_list(entries, where: str) -> list[SourceMask]:
    if not isinstance(entries, list):
        raise PsimapError(f"{where}: expected a list of masks ({{\"segmentation\": RLE, \"predicted_iou\", ...}})")
    out = []
    for n, e in enumerate(entries):
        if not isinstance(e, dict) or "segmentation" not in e:
            raise PsimapError(f"{where} mask {n}: needs \"segmentation\"")
        m = decode_segmentation(e["segmentation"], None, f"{where} mask {n}")
        out.append(SourceMask(m, 1, _score(e, f"{where} mask {n}", "predicted_iou", "stability_score")))
    return out


def _sam_folder(folder: Path) -> list[SourceMask]:
    """amg.py's folder of one image: `<i>.png` (0 / 255) + metadata.csv (id, area, ..., predicted_iou,
    stability_score); without metadata.csv every `<i>.png` with score 1."""
    meta = folder / "metadata.csv"
    if not meta.is_file():
        pngs = sorted((p for p in folder.glob("*.png") if p.stem.isdigit()), key=lambda p: int(p.stem))
        return [SourceMask(_read_binary_png(p), 1) for p in pngs]
    try:
        with open(meta, newline="") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise PsimapError(f"{meta}: {e}") from None
    out = []
    for n, row in enumerate(rows):
        where = f"{meta} row {n + 2}"
        if not row.get("id", "").strip().isdigit():
            raise PsimapError(f"{where}: \"id\" must be the mask's number (its <id>.png)")
        score = _score({k: v for k, v in row.items() if k in ("predicted_iou", "stability_score") and v not in (None, "")},
                       where, "predicted_iou", "stability_score")
        out.append(SourceMask(_read_binary_png(folder / f"{int(row['id'])}.png"), 1, score))
    return out


def read_sam(path: Path) -> MaskSource:
    categories = {1: (SAM_CLASS, True)}
    source = MaskSource("sam", path, categories, [], {1})
    if path.is_file():                          # one image's JSON list, named after the image
        source.images.append(SourceImage(path.stem, str(path), lambda: _sam_list(_read_json(path), str(path))))
        return source
    if (path / "metadata.csv").is_file():       # one image's amg folder
        source.images.append(SourceImage(path.name, str(path), lambda: _sam_folder(path)))
        return source
    for p in sorted(path.iterdir()):
        if p.is_dir() and ((p / "metadata.csv").is_file() or any(q.stem.isdigit() for q in p.glob("*.png"))):
            source.images.append(SourceImage(p.name, str(p), lambda p=p: _sam_folder(p)))
        elif p.is_file() and p.suffix.lower() == ".json":
            source.images.append(SourceImage(p.stem, str(p), lambda p=p: _sam_list(_read_json(p), str(p))))
    if not source.images:
        raise PsimapError(f"{path}: no SAM masks (a folder per image with <i>.png + metadata.csv, "
                          f"or a <image>.json list per image)")
    return source


# --------------------------------------------------------------------------------------------------
# format detection


def detect_format(path: Path) -> tuple[str, Path]:
    """(format, the file or folder to read) from what `path` holds; PsimapError when unclear."""
    if not path.exists():
        raise PsimapError(f"no such file or folder: {path}")
    if path.is_dir():
        if (path / "metadata.csv").is_file() or any((p / "metadata.csv").is_file() for p in path.iterdir()
                                                    if p.is_dir()):
            return "sam", path
        jsons = sorted(path.glob("*.json"))
        if len(jsons) == 1 and isinstance(_read_json(jsons[0]), dict):
            return detect_format(jsons[0])
        if jsons and all(isinstance(_read_json(p), list) for p in jsons):
            return "sam", path
        raise PsimapError(f"{path}: cannot tell the mask format (a COCO JSON, or SAM's folders / JSON "
                          f"lists); name it with --format")
    data = _read_json(path)
    if isinstance(data, dict) and isinstance(data.get("annotations"), list):
        first = next(iter(data["annotations"]), {})
        return ("coco-panoptic" if isinstance(first, dict) and "segments_info" in first else "coco-instances"), path
    if isinstance(data, list) and data and isinstance(data[0], dict):
        return ("coco-instances" if "image_id" in data[0] else "sam"), path
    raise PsimapError(f"{path}: cannot tell the mask format (COCO panoptic / instances JSON, or a SAM "
                      f"list); name it with --format")


def read_masks(path: str | os.PathLike, fmt: str = "auto", *, images: str | os.PathLike | None = None,
               min_score: float = 0.0) -> MaskSource:
    path = Path(path)
    if fmt == "auto":
        fmt, path = detect_format(path)
    elif not path.exists():
        raise PsimapError(f"no such file or folder: {path}")
    if fmt in ("coco-panoptic", "coco-instances") and path.is_dir():
        jsons = sorted(path.glob("*.json"))
        if len(jsons) != 1:
            raise PsimapError(f"{path}: expected one COCO JSON in the folder, found {len(jsons)}; give the file")
        path = jsons[0]
    if images and fmt != "coco-instances":
        raise PsimapError(f"--images is for COCO instance results lists, not {fmt}")
    if fmt == "coco-panoptic":
        return read_coco_panoptic(path)
    if fmt == "coco-instances":
        return read_coco_instances(path, Path(images) if images else None, min_score)
    if fmt == "sam":
        return read_sam(path)
    raise PsimapError(f"unknown mask format {fmt!r} (one of {', '.join(FORMATS)})")


# --------------------------------------------------------------------------------------------------
# frames and classes


def match_frame(key: str, names) -> str | None:
    """The frame an image file name belongs to: its base name, then with one extension after another
    taken off (`frame-000000.color.jpg` -> `frame-000000.color` -> `frame-000000`), the first that is
    a frame name; None when none is."""
    cand = re.split(r"[\\/]", str(key))[-1]
    while cand:
        if cand in names:
            return cand
        stem, dot, _ = cand.rpartition(".")
        if not dot:
            return None
        cand = stem
    return None


def read_class_map(path: str | os.PathLike) -> tuple[dict, str | None]:
    """A mapping file -> ({source name or id (str): (name, isthing or None) or None}, unmapped rule).

    {"classes": {"dining table": "table", "wall-other-merged": {"name": "wall", "isthing": false},
                 "44": null}, "unmapped": "keep"}"""
    path = Path(path)
    meta = _read_json(path)
    if not isinstance(meta, dict) or not isinstance(meta.get("classes"), dict):
        raise PsimapError(f"{path}: expected {{\"classes\": {{source name or id: class name | "
                          f"{{\"name\", \"isthing\"}} | null}}, \"unmapped\": rule}}")
    unknown_keys = set(meta) - {"classes", "unmapped"}
    if unknown_keys:
        raise PsimapError(f"{path}: unknown keys {sorted(unknown_keys)} (expected \"classes\", \"unmapped\")")
    rule = meta.get("unmapped")
    if rule is not None and rule not in UNMAPPED_RULES:
        raise PsimapError(f"{path}: \"unmapped\" must be one of {', '.join(UNMAPPED_RULES)}, got {rule!r}")
    out = {}
    for key, v in meta["classes"].items():
        if v is None:
            out[str(key)] = None
        elif isinstance(v, str) and v.strip():
            out[str(key)] = (v.strip(), None)
        elif isinstance(v, dict) and isinstance(v.get("name"), str) and v["name"].strip() \
                and isinstance(v.get("isthing", True), bool):
            out[str(key)] = (v["name"].strip(), v.get("isthing"))
        else:
            raise PsimapError(f"{path}: class {key!r}: expected a class name, {{\"name\", \"isthing\": true|false}} "
                              f"or null")
    return out, rule


def build_classes(categories: dict[int, tuple[str, bool]], used: set[int], mapping: dict | None,
                  unmapped: str) -> tuple[list[ClassInfo], dict[int, int], list[str]]:
    """(psimap class table, {source category id: psimap class id, 0 = void}, mapping keys that name
    no source category). Only the categories some mask uses become classes; several source
    categories may map to one class. A class keeps its source id (the smallest of those mapped onto
    it), so COCO ids and a generated scene's ids survive; when one is outside 1..65535 (0-based ids)
    the classes are numbered 1, 2, ... in the order of their source ids instead."""
    mapping = mapping or {}
    targets: dict[str, tuple[int, bool, str]] = {}       # name -> (smallest source id, isthing, its name)
    target_of: dict[int, str | None] = {}                # source id -> class name, None = void
    for cid in sorted(used):
        name, isthing = categories[cid]
        key = name if name in mapping else str(cid) if str(cid) in mapping else None
        if key is not None:
            if mapping[key] is None:
                target_of[cid] = None
                continue
            target, thing = mapping[key]
            thing = isthing if thing is None else thing
        elif unmapped == "keep":
            target, thing = name, isthing
        elif unmapped == "object" and isthing:
            target, thing = SAM_CLASS, True
        elif unmapped in ("object", "void"):             # "object" leaves stuff void
            target_of[cid] = None
            continue
        else:
            raise PsimapError(f"source category {name!r} (id {cid}) is not in the class mapping "
                              f"(--unmapped error); map it, or map it to null")
        if target in targets and targets[target][1] != thing:
            raise PsimapError(f"class {target!r} is a {'thing' if targets[target][1] else 'stuff'} class for "
                              f"{targets[target][2]!r} and a {'thing' if thing else 'stuff'} class for {name!r}: "
                              f"give it as {{\"name\": {json.dumps(target)}, \"isthing\": true|false}}")
        targets.setdefault(target, (cid, thing, name))    # `used` is sorted: the smallest source id
        target_of[cid] = target
    ids = {n: i for n, (i, _, _) in targets.items()}
    if any(not 0 < i <= 65535 for i in ids.values()):
        ids = {n: k + 1 for k, n in enumerate(targets)}
    classes = [ClassInfo(ids[n], n, t) for n, (_, t, _) in targets.items()]
    to_class = {cid: 0 if t is None else ids[t] for cid, t in target_of.items()}
    known = {n for n, _ in categories.values()} | {str(c) for c in categories}
    return classes, to_class, sorted(k for k in mapping if k not in known)


# --------------------------------------------------------------------------------------------------
# overlaps


def paint_order(masks: list[np.ndarray], scores: list[float]) -> tuple[list[int], list[set[int]]]:
    """(indices of `masks` from the top down, the masks nested in each). The order: a higher score
    first, then the smaller mask; but a mask nested in a larger one (>= NESTED of it inside one at
    least twice its size) always above it (a thing on a table whose mask covers it too)."""
    from pycocotools import mask as cocomask

    n = len(masks)
    areas = [int(m.sum()) for m in masks]
    priority = sorted(range(n), key=lambda i: (-scores[i], areas[i], i))
    if n < 2:
        return priority, [set() for _ in range(n)]
    rles = [cocomask.encode(np.asfortranarray(m.astype(np.uint8))) for m in masks]
    # iscrowd=1 for every "ground truth" mask makes pycocotools divide by the first one's area:
    # inside[i, j] = |i & j| / |i|
    inside = np.asarray(cocomask.iou(rles, rles, [1] * n)).reshape(n, n)
    nested = [{j for j in range(n) if j != i and areas[j] <= NESTED_SHARE * areas[i] and inside[j, i] >= NESTED}
              for i in range(n)]
    order, placed = [], set()
    while len(order) < n:
        # the best mask whose nested masks are all above it already (areas strictly shrink: no cycle)
        i = next(i for i in priority if i not in placed and nested[i] <= placed)
        order.append(i)
        placed.add(i)
    return order, nested


def paint_masks(masks: list[np.ndarray], scores: list[float], min_area: int) -> tuple[np.ndarray, list[int], dict]:
    """Resolve overlaps: (owner [H, W] int32, an index into `masks` or -1; the kept masks, top first;
    counts of the dropped: "small", "hidden").

    Masks under `min_area` pixels are dropped first. Then, from the top of `paint_order` down, each
    mask takes the pixels no mask above it took; it is dropped instead when it would get fewer than
    `min_area` pixels, or less than MIN_VISIBLE of its area counting the pixels its nested masks
    took as its own (a second, worse mask of an object already painted)."""
    shape = masks[0].shape if masks else (0, 0)
    floor = max(int(min_area), 1)
    keep = [i for i, m in enumerate(masks) if m.sum() >= floor]
    stats = {"small": len(masks) - len(keep), "hidden": 0}
    sub, nested_sub = paint_order([masks[i] for i in keep], [scores[i] for i in keep])
    owner = np.full(shape, -1, dtype=np.int32)
    kept: list[int] = []
    for k in sub:
        i = keep[k]
        m = masks[i]
        free = m & (owner < 0)
        n_free = int(free.sum())
        inner = [keep[j] for j in nested_sub[k] if keep[j] in kept]
        under_nested = int(np.isin(owner[m], inner).sum()) if inner else 0
        if n_free < floor or n_free + under_nested < MIN_VISIBLE * m.sum():
            stats["hidden"] += 1
            continue
        owner[free] = i
        kept.append(i)
    return owner, kept, stats


# --------------------------------------------------------------------------------------------------
# the import


def _fit(mask: np.ndarray, hw: tuple[int, int], resize: bool, origin: str, name: str) -> np.ndarray:
    if mask.shape == tuple(hw):
        return mask
    h, w = mask.shape
    if not resize:
        raise PsimapError(f"{origin}: mask is {w}x{h} but frame {name} is {hw[1]}x{hw[0]} "
                          f"(segment the frame's own images, or pass --resize)")
    if abs((w / h) / (hw[1] / hw[0]) - 1.0) > RESIZE_ASPECT_TOL:
        raise PsimapError(f"{origin}: mask is {w}x{h}, frame {name} is {hw[1]}x{hw[0]}: the aspect ratios "
                          f"differ, --resize would distort it")
    from PIL import Image

    # nearest neighbour: a label is an id, never an average
    return np.asarray(Image.fromarray(mask.astype(np.uint8)).resize((hw[1], hw[0]), Image.NEAREST)) > 0


def frame_labels(masks: list[SourceMask], hw: tuple[int, int], to_class: dict[int, int], thing_ids: set[int],
                 *, min_area: int, min_score: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """One frame's (semantic [H, W] uint16, instance [H, W] uint16, counts) from its masks.

    Thing masks get instance ids 1.. from the top of the paint order down; stuff and crowd regions
    instance 0."""
    stats = {"read": len(masks), "low_score": 0, "void_class": 0}
    live = []
    for m in masks:
        if m.score < min_score:
            stats["low_score"] += 1
        elif to_class.get(m.category, 0) == 0:
            stats["void_class"] += 1
        else:
            live.append(m)
    owner, order, dropped = paint_masks([m.mask for m in live], [m.score for m in live], min_area)
    stats.update(dropped)
    stats["kept"] = len(order)
    sem = np.zeros(hw, dtype=np.uint16)
    inst = np.zeros(hw, dtype=np.uint16)
    next_id = 1
    for i in order:
        cls = to_class[live[i].category]
        px = owner == i
        sem[px] = cls
        if cls in thing_ids and not live[i].iscrowd:
            if next_id > 65535:
                raise PsimapError("more than 65535 instances in one frame")
            inst[px] = next_id
            next_id += 1
    return sem, inst, stats


def min_area_pixels(min_area: float, hw: tuple[int, int]) -> int:
    """--min-area: pixels when >= 1, a share of the image when below 1."""
    if min_area < 0 or not np.isfinite(min_area):
        raise PsimapError(f"--min-area must be >= 0, got {min_area}")
    # (a hair under: 4 / 48 of 48 pixels is 4 pixels, not the 5 float rounding would make it)
    return int(np.ceil(min_area * hw[0] * hw[1] - 1e-9)) if min_area < 1 else int(np.ceil(min_area - 1e-9))


def import_masks(data: str | os.PathLike, masks: str | os.PathLike, *, fmt: str = "auto",
                 classes: str | os.PathLike | None = None, unmapped: str | None = None,
                 images: str | os.PathLike | None = None, min_area: float = 0.0005, min_score: float = 0.5,
                 resize: bool = False, force: bool = False, progress: bool = False) -> dict:
    """Convert a segmenter's masks into labels of the capture at `data` (labels.json + semantic/ +
    instance/, written by `label_overlay.write_label_overlay`). Returns a summary dict. Everything
    that can be checked before decoding a mask is checked before anything is written; a bad mask
    met later still leaves the capture as it was."""
    from tqdm import tqdm

    from psimap.data.label_overlay import check_label_write, write_label_overlay
    from psimap.data.loaders import LAYOUTS, detect_layout

    root = Path(data)
    if not root.is_dir():
        raise PsimapError(f"no such capture folder: {root}")
    min_area_pixels(min_area, (1, 1))               # refuses a negative or NaN --min-area up front
    if not 0.0 <= min_score <= 1.0:
        raise PsimapError(f"--min-score must be in 0..1, got {min_score}")
    if unmapped is not None and unmapped not in UNMAPPED_RULES:
        raise PsimapError(f"--unmapped must be one of {', '.join(UNMAPPED_RULES)}, got {unmapped!r}")
    # the layout's own frames, without a labels.json a previous import wrote (--force replaces it)
    layout = detect_layout(root)
    seq = next(lay for lay in LAYOUTS if lay.name == layout).read(root)
    names = list(seq.names) or [seq[i].name for i in range(len(seq))]
    source = read_masks(masks, fmt, images=images, min_score=min_score)
    if not source.images:
        raise PsimapError(f"{source.path}: no images in it")
    mapping, file_rule = read_class_map(classes) if classes else (None, None)
    rule = unmapped or file_rule or "keep"

    frame_of, taken = [], {}
    for img in source.images:
        name = match_frame(img.key, set(names))
        if name is None:
            raise PsimapError(f"{img.origin}: no frame of {root} is named like {img.key!r} (frames are named "
                              f"like {names[0]!r}; a mask file matches the frame its name, less extensions, "
                              f"equals)")
        if name in taken:
            raise PsimapError(f"{img.origin} and {taken[name]} both match frame {name}")
        frame_of.append(name)
        taken[name] = img.origin
    table, to_class, unused_keys = build_classes(source.categories, source.used, mapping, rule)
    if not table:
        raise PsimapError(f"{source.path}: no mask names a class to import (every category is void, "
                          f"unmapped or under --min-score)")
    check_label_write(root, taken, force=force)
    thing_ids = {c.id for c in table if c.isthing}
    index = {n: i for i, n in enumerate(names)}
    totals = {"read": 0, "kept": 0, "small": 0, "hidden": 0, "low_score": 0, "void_class": 0}
    # in the capture's frame order, so labels.json reads like the capture
    todo = sorted(zip(frame_of, source.images), key=lambda t: index[t[0]])

    def labelled():
        for name, img in tqdm(todo, desc="import-masks", unit="frame", disable=not progress):
            hw = tuple(seq[index[name]].depth.shape)
            found = img.read()
            for m in found:
                m.mask = _fit(m.mask, hw, resize, img.origin, name)
            sem, inst, stats = frame_labels(found, hw, to_class, thing_ids, min_area=min_area_pixels(min_area, hw),
                                            min_score=min_score)
            for k in totals:
                totals[k] += stats.get(k, 0)
            yield name, sem, inst

    manifest = write_label_overlay(root, table, labelled(), source=f"import-masks {source.format} {source.path}",
                                   force=force)
    missing = [n for n in names if n not in taken]
    return {"format": source.format, "masks": str(source.path), "manifest": str(manifest),
            "frames": len(names), "labelled": len(taken), "without_masks": missing,
            "classes": [(c.id, c.name, c.isthing) for c in table], "unused_mapping_keys": unused_keys,
            **totals}


def cli_import_masks(opts) -> int:
    """`psimap import-masks DATA --masks PATH [--format ...] [--classes MAP.json] ...`."""
    s = import_masks(opts.data, opts.masks, fmt=opts.format, classes=opts.classes or None,
                     unmapped=opts.unmapped or None, images=opts.images or None, min_area=opts.min_area,
                     min_score=opts.min_score, resize=opts.resize, force=opts.force, progress=True)
    miss = s["without_masks"]
    shown = ", ".join(miss[:3]) + (" ..." if len(miss) > 3 else "")
    print(f"{s['format']} masks from {s['masks']}: {s['labelled']} of {s['frames']} frames labelled"
          + (f"; {len(miss)} without masks (no labels): {shown}" if miss else ""))
    print(f"masks: {s['kept']} kept of {s['read']}; dropped {s['small']} under --min-area, {s['hidden']} "
          f"hidden by others, {s['low_score']} under --min-score, {s['void_class']} of void classes")
    print("classes: " + ", ".join(f"{n} ({'thing' if t else 'stuff'})" for _, n, t in s["classes"]))
    if s["unused_mapping_keys"]:
        print(f"note: mapping keys that name no source category: {', '.join(s['unused_mapping_keys'][:10])}")
    print(f"wrote {s['manifest']}")
    return 0
