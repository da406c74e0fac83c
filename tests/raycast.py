"""Exact depth and label maps of a labelled triangle scene (imported by tests; not a test module)."""
from __future__ import annotations

import numpy as np


def labelled_depth(rc, K, c2w, width: int, height: int, face_instance, face_semantic):
    """(depth [H, W] float32, instance [H, W] uint16, semantic [H, W] uint16) seen by the camera
    (K [3, 3], OpenCV c2w [4, 4]) in Open3D RaycastingScene `rc`; per-face labels [F]; 0 = no hit."""
    from psimap.metrics.geometry import camera_rays

    hit = rc.cast_rays(camera_rays(K, c2w, width, height))
    ids = hit["primitive_ids"].numpy().astype(np.int64).reshape(height, width)
    ok = ids != 0xFFFFFFFF
    depth = np.where(ok, hit["t_hit"].numpy().reshape(height, width), 0).astype(np.float32)
    face = np.where(ok, ids, 0)
    inst = np.where(ok, np.asarray(face_instance)[face], 0).astype(np.uint16)
    sem = np.where(ok, np.asarray(face_semantic)[face], 0).astype(np.uint16)
    return depth, inst, sem
