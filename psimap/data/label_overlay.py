"""Per-frame labels added to a capture of any layout: what `psimap segment` and `psimap import-masks` write.

A capture folder (psimap scene format, 7-Scenes, ScanNet, TUM, ...) gets

    DATA/labels.json                {"format": "psimap-labels", "version": 1, "source": "...",
                                     "classes": [{"id", "name", "isthing"}],
                                     "frames": {"<frame name>": {"semantic": "semantic/<name>.png",
                                                                 "instance": "instance/<name>.png"}}}
    DATA/semantic/<name>.png        uint16 class id per pixel (0 = void)
    DATA/instance/<name>.png        uint16 instance id per pixel, per frame only (0 = none)

`psimap.data.load` reads the layout, then lets `labels.json` supply every frame's labels and the class
table: the user made them for this capture, so they take precedence over labels the layout carries.
A frame the file does not list has no labels. Frame names are the loaders' `FrameSequence.names`.

Writing never replaces a file psimap did not write without `force`: the PNGs go to a temporary folder
first and are moved into place one by one, and `labels.json` (the file the loader reads) is written
last, so an interrupted write leaves no half-labelled capture behind.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from psimap import PsimapError, __version__
from psimap.data.frames import ClassInfo, FrameSequence

MANIFEST = "labels.json"
FORMAT = "psimap-labels"
FOLDERS = ("semantic", "instance")


def label_paths(name: str) -> dict[str, str]:
    """Relative paths of a frame's label PNGs."""
    return {k: f"{k}/{name}.png" for k in FOLDERS}


def _check_classes(classes: list[ClassInfo]) -> None:
    ids = [int(c.id) for c in classes]
    if any(i <= 0 or i > 65535 for i in ids):
        raise PsimapError("label classes: ids must be in 1..65535 (0 is void)")
    if len(set(ids)) != len(ids):
        raise PsimapError("label classes: duplicate class ids")


def existing_labels(root: str | os.PathLike, names) -> list[Path]:
    """The files a label write for frames `names` would replace (manifest included)."""
    root = Path(root)
    out = [root / MANIFEST] if (root / MANIFEST).exists() else []
    for name in names:
        out += [root / rel for rel in label_paths(name).values() if (root / rel).exists()]
    return out


def check_label_write(root: str | os.PathLike, names, *, force: bool = False) -> None:
    """Refuse (PsimapError) before any work when labels exist and `force` is off."""
    found = existing_labels(root, names)
    if found and not force:
        more = f" and {len(found) - 1} more" if len(found) > 1 else ""
        raise PsimapError(f"{found[0]}{more} already exist(s); pass --force to replace the capture's labels")
    for sub in FOLDERS:
        if (Path(root) / sub).exists() and not (Path(root) / sub).is_dir():
            raise PsimapError(f"{Path(root) / sub} is a file; cannot write labels there")


def write_label_overlay(root: str | os.PathLike, classes: list[ClassInfo], labels, *, source: str,
                        force: bool = False) -> Path:
    """Write labels for frames of the capture at `root`; returns the manifest path.

    labels: iterable of (name, semantic [H, W] int, instance [H, W] int) — a generator is fine, so a
    long capture is never held in memory. The whole write is refused up front when labels exist and
    `force` is off; see the module doc for the order of the writes.
    """
    from PIL import Image

    root = Path(root)
    if not root.is_dir():
        raise PsimapError(f"no such capture folder: {root}")
    _check_classes(classes)
    known = {int(c.id) for c in classes}
    tmp = Path(tempfile.mkdtemp(prefix=".psimap-labels.", dir=root))
    frames = {}
    try:
        for name, sem, inst in labels:
            if not name or "/" in name or name in (".", ".."):
                raise PsimapError(f"label write: bad frame name {name!r}")
            sem, inst = np.asarray(sem), np.asarray(inst)
            if sem.shape != inst.shape or sem.ndim != 2:
                raise PsimapError(f"frame {name}: semantic {sem.shape} and instance {inst.shape} must be one [H, W]")
            for what, arr in (("semantic", sem), ("instance", inst)):
                if arr.size and (arr.min() < 0 or arr.max() > 65535):
                    raise PsimapError(f"frame {name}: {what} ids outside 0..65535")
            unknown = set(np.unique(sem).tolist()) - known - {0}
            if unknown:
                raise PsimapError(f"frame {name}: semantic ids {sorted(unknown)[:5]} are not in the class table")
            for sub, arr in (("semantic", sem), ("instance", inst)):
                (tmp / sub).mkdir(exist_ok=True)
                Image.fromarray(arr.astype(np.uint16)).save(tmp / sub / f"{name}.png", format="PNG",
                                                            compress_level=1)
            frames[name] = label_paths(name)
        if not frames:
            raise PsimapError("label write: no frames to label")
        check_label_write(root, frames, force=force)       # again: the folder may have changed meanwhile
        for name, rels in frames.items():
            for rel in rels.values():
                (root / rel).parent.mkdir(exist_ok=True)
                os.replace(tmp / rel, root / rel)
        manifest = {"format": FORMAT, "version": 1, "source": source, "psimap": __version__,
                    "classes": [{"id": int(c.id), "name": str(c.name), "isthing": bool(c.isthing)} for c in classes],
                    "frames": frames}
        from psimap.io_utils import write_text_atomic

        write_text_atomic(root / MANIFEST, json.dumps(manifest, indent=1))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return root / MANIFEST


def read_label_overlay(root: str | os.PathLike) -> tuple[list[ClassInfo], dict[str, dict[str, Path]]] | None:
    """(classes, {frame name: {"semantic": path, "instance": path}}) from `root/labels.json`, or None
    when the capture has none. A malformed manifest is one PsimapError naming it."""
    path = Path(root) / MANIFEST
    if not path.is_file():
        return None
    try:
        meta = json.loads(path.read_text())
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise ValueError(f"not a psimap labels file (\"format\": \"{FORMAT}\" missing)")
        classes = [ClassInfo(int(c["id"]), str(c["name"]), bool(c.get("isthing", True))) for c in meta["classes"]]
        frames = {str(n): {k: Path(root) / str(v[k]) for k in FOLDERS} for n, v in meta["frames"].items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        raise PsimapError(f"{path}: {e}") from None
    _check_classes(classes)
    return classes, frames


def apply_label_overlay(seq: FrameSequence) -> FrameSequence:
    """`seq` with its labels and class table taken from `seq.root/labels.json`, when that exists.

    Label PNGs must have the frame's depth size (a mask resized by nearest neighbour silently moves
    every boundary, so a mismatch is an error naming the file)."""
    from psimap.data.scene_format import read_label_png

    overlay = read_label_overlay(seq.root) if seq.root else None
    if overlay is None:
        return seq
    classes, frames = overlay
    unknown = sorted(set(frames) - set(seq.names))
    if seq.names and unknown:
        raise PsimapError(f"{Path(seq.root) / MANIFEST}: frames {unknown[:3]} are not frames of this capture "
                          f"(its frames are named like {seq.names[0]!r})")
    inner = seq.loader
    names = list(seq.names)

    def load_frame(i: int):
        f = inner(i)
        paths = frames.get(names[i] if names else f.name)
        if paths is None:
            f.semantic = f.instance = None
            return f
        for key, p in paths.items():
            lab = read_label_png(p)
            if lab.shape != f.depth.shape:
                raise PsimapError(f"label image {p} is {lab.shape[1]}x{lab.shape[0]} but frame {f.name} is "
                                  f"{f.width}x{f.height}")
            setattr(f, key, lab)
        return f

    # replace(): every other field a loader filled (what it read and assumed) is kept
    report = dataclasses.replace(seq.report, skipped=list(seq.report.skipped), assumed=list(seq.report.assumed))
    n_things = sum(c.isthing for c in classes)
    report.labels = (f"{MANIFEST} ({source_of(seq.root)}): {len(frames)} of {seq.count} frames, "
                     f"{len(classes)} classes ({n_things} things); the layout's own labels are not used")
    return dataclasses.replace(seq, loader=load_frame, classes=classes, report=report)


def source_of(root) -> str:
    """The `source` a label manifest names (what wrote it), or "?"."""
    try:
        return str(json.loads((Path(root) / MANIFEST).read_text()).get("source", "?"))
    except (OSError, ValueError, AttributeError):
        return "?"
