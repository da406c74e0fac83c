"""Step 1: per-instance meshes from a trained scene.

Every training camera is rendered (colour, median depth, and the per-pixel instance id: the surfels'
hard ids one-hot encoded as features, blended over the top-K surfels, argmax). Each thing instance is
fused alone by TSDF with the depth masked to its pixels (psimap.geometry.tsdf); the pixels of stuff
classes (floor, walls) and of no instance are fused into one static background mesh.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# pixels seen by less than this much surfel coverage are unknown, not free space
MIN_ALPHA = 0.5
# an instance seen on fewer pixels than this in a view adds nothing but noise to its fusion
MIN_PIXELS = 16


@dataclass
class InstanceMesh:
    instance_id: int
    semantic_id: int
    label: str
    mesh: object            # trimesh.Trimesh or None


@dataclass
class InstanceMeshes:
    things: list[InstanceMesh]
    background: object | None                   # trimesh.Trimesh or None
    views: list = field(default_factory=list)   # texture.View of every camera
    id_maps: list = field(default_factory=list)  # [H, W] int64 rendered instance id per camera
    voxel_size: float | None = None             # TSDF voxel used for the objects (metres)

    def views_for(self, instance_id: int, min_pixels: int = 16):
        """Views in which the instance is visible (colour bake candidates)."""
        return [v for v, ids in zip(self.views, self.id_maps) if int((ids == instance_id).sum()) >= min_pixels]


def render_id_views(scene, cameras=None, progress: bool = False):
    """(views [texture.View], instance id maps [H, W] int64) of the scene's training cameras."""
    import torch
    from tqdm import tqdm

    from psimap.exporters.texture import View

    iid = scene.instance_ids().to(torch.int64)
    ids = torch.unique(iid)
    lut = {int(v): k for k, v in enumerate(ids.tolist())}
    onehot = torch.zeros(len(iid), len(ids), dtype=torch.float32)
    onehot[torch.arange(len(iid)), torch.tensor([lut[int(v)] for v in iid.tolist()], dtype=torch.int64)] = 1.0
    idx = range(len(scene.cameras["names"])) if cameras is None else cameras
    views, maps = [], []
    for i in tqdm(list(idx), desc="render views", disable=not progress, leave=False):
        K, c2w, w, h = scene.camera(int(i))
        from psimap.render import rasterize

        s = scene.surfels
        viewmat = torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32)
        with torch.no_grad():
            out = rasterize(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], viewmat,
                            torch.as_tensor(K, dtype=torch.float32), int(w), int(h), features=onehot,
                            topk=4, backend="auto")
        alpha = out.alpha.numpy()
        depth = out.median_depth.numpy()
        valid = (alpha >= MIN_ALPHA) & np.isfinite(depth) & (depth > 0)
        id_map = ids.numpy()[out.features.numpy().argmax(axis=2)].astype(np.int64)
        id_map[~valid] = -1
        views.append(View(np.clip(out.rgb.numpy(), 0, 1).astype(np.float32),
                          np.where(valid, depth, 0).astype(np.float32), K, c2w))
        maps.append(id_map)
    return views, maps


def instance_meshes(scene, *, cameras=None, voxel_size: float | None = None,
                    progress: bool = False) -> InstanceMeshes:
    """Per-thing-instance meshes and the background mesh of `scene` (psimap.scene.Scene)."""
    import torch

    from psimap.geometry.tsdf import fuse_tsdf

    views, maps = render_id_views(scene, cameras, progress)
    classes = {int(c["id"]): c for c in scene.classes}
    iid = scene.instance_ids().to(torch.int64).numpy()
    sid = scene.semantic_ids().to(torch.int64).numpy()
    things, stuff_ids = [], {-1, 0}
    for inst in sorted(set(iid.tolist()) - {0}):
        sem = np.bincount(sid[iid == inst]).argmax()
        cls = classes.get(int(sem), {"name": f"class_{int(sem)}", "isthing": True})
        if not cls.get("isthing", True):
            stuff_ids.add(inst)
            continue
        things.append(InstanceMesh(int(inst), int(sem), str(cls["name"]), None))
    if not views:
        return InstanceMeshes(things, None, views, maps)
    depths = [v.depth for v in views]
    colors = [v.rgb for v in views]
    Ks = [v.K for v in views]
    c2ws = [v.c2w for v in views]
    from psimap.geometry.tsdf import derive_params

    params = derive_params(depths, Ks, c2ws, voxel_size=voxel_size)
    obj_voxel = params.voxel_size * 0.5
    from scipy.ndimage import binary_erosion

    for t in things:
        # one-pixel erosion: boundary pixels blend the object's splats over what lies behind, and
        # fusing them grows a skirt around the silhouette
        masks = [binary_erosion(m == t.instance_id) for m in maps]
        seen = [k for k, m in enumerate(masks) if int(m.sum()) >= MIN_PIXELS]
        if not seen:
            continue
        try:
            t.mesh = fuse_tsdf([depths[k] for k in seen], [Ks[k] for k in seen], [c2ws[k] for k in seen],
                               colors=[colors[k] for k in seen], masks=[masks[k] for k in seen],
                               voxel_size=obj_voxel, depth_max=params.depth_max, keep_fraction=0.2)
        except RuntimeError:    # Open3D aborts when the masked depth touches no voxel block
            t.mesh = None
    bg_masks = [np.isin(m, list(stuff_ids)) & (m >= 0) for m in maps]
    background = None
    if sum(int(m.sum()) for m in bg_masks) >= 16:
        background = fuse_tsdf(depths, Ks, c2ws, colors=colors, masks=bg_masks, voxel_size=params.voxel_size,
                               depth_max=params.depth_max)
    return InstanceMeshes(things, background, views, maps, obj_voxel)
