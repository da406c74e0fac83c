"""COCO panoptic output: `panoptic.json` + one RGB PNG per frame (segment id = R + 256 G + 256^2 B).

Thing segments use the 3D instance id, identical in every frame; stuff is one segment per class with
id STUFF_OFFSET + class id, so stuff and thing ids never collide and also agree across frames.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

STUFF_OFFSET = 1 << 20


def segment_map(instance: np.ndarray, semantic: np.ndarray, thing_classes: set[int]) -> np.ndarray:
    """Panoptic segment ids [H, W] int64 from an instance-id map and a class map (0 = void)."""
    seg = np.zeros(instance.shape, dtype=np.int64)
    thing = np.isin(semantic, list(thing_classes)) & (instance > 0)
    seg[thing] = instance[thing]
    stuff = (semantic > 0) & ~np.isin(semantic, list(thing_classes))
    seg[stuff] = STUFF_OFFSET + semantic[stuff]
    return seg


def encode_rgb(seg: np.ndarray) -> np.ndarray:
    """Segment ids [H, W] -> uint8 RGB [H, W, 3] (COCO panoptic encoding)."""
    seg = seg.astype(np.int64)
    return np.stack([seg % 256, (seg // 256) % 256, (seg // 65536) % 256], axis=-1).astype(np.uint8)


def decode_rgb(rgb: np.ndarray) -> np.ndarray:
    rgb = rgb.astype(np.int64)
    return rgb[..., 0] + 256 * rgb[..., 1] + 65536 * rgb[..., 2]


def write_coco_panoptic(out_dir, frames, classes, instance_class: dict[int, int]) -> Path:
    """Write COCO panoptic labels.

    frames: iterable of (stem, instance [H, W] int, semantic [H, W] int); classes: list of ClassInfo
    or dicts with id / name / isthing; instance_class: 3D instance id -> class id (by vote).
    Returns the path of panoptic.json. The folder is written atomically by the caller (atomic_dir).
    """
    from PIL import Image

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cls = [c if isinstance(c, dict) else {"id": c.id, "name": c.name, "isthing": c.isthing} for c in classes]
    things = {int(c["id"]) for c in cls if c["isthing"]}
    categories = [{"id": int(c["id"]), "name": c["name"], "isthing": int(bool(c["isthing"])),
                   "supercategory": "thing" if c["isthing"] else "stuff"} for c in cls]
    images, annotations = [], []
    for image_id, (stem, inst, sem) in enumerate(frames):
        inst = np.asarray(inst).astype(np.int64)
        sem = np.asarray(sem).astype(np.int64)
        # Things take the class voted for their 3D instance, so one id never changes class by frame.
        sem = sem.copy()
        for iid, cid in instance_class.items():
            sem[inst == iid] = cid
        seg = segment_map(inst, sem, things)
        fname = f"{stem}.png"
        Image.fromarray(encode_rgb(seg)).save(out_dir / fname)
        ids, areas = np.unique(seg[seg > 0], return_counts=True)
        segments = []
        for sid, area in zip(ids.tolist(), areas.tolist()):
            ys, xs = np.nonzero(seg == sid)
            cat = sid - STUFF_OFFSET if sid >= STUFF_OFFSET else instance_class.get(sid, int(np.bincount(sem[seg == sid]).argmax()))
            segments.append({"id": int(sid), "category_id": int(cat), "iscrowd": 0, "area": int(area),
                             "bbox": [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1),
                                      int(ys.max() - ys.min() + 1)]})
        h, w = seg.shape
        images.append({"id": image_id, "file_name": fname, "height": int(h), "width": int(w)})
        annotations.append({"image_id": image_id, "file_name": fname, "segments_info": segments})
    path = out_dir / "panoptic.json"
    path.write_text(json.dumps({"images": images, "annotations": annotations, "categories": categories},
                               indent=1, sort_keys=True))
    return path
