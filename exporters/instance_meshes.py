"""Step 1: per-instance meshes from a trained scene.

Every training camera is rendered (colour, median depth, and the per-pixel instance id: the surfels'
hard ids one-hot encoded as features, blended over the top-K surfels, argmax). Each thing instance is
fused alone by TSDF with the depth masked to its pixels (psimap.geometry.tsdf); the pixels of stuff
classes (floor, walls) and of no instance are fused into one static background mesh.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psimap.data.frames import evenly_spaced
from psimap.transforms import quat_to_rotmat, scale_intrinsics, transform_points

# pixels seen by less than this much surfel coverage are unknown, not free space
MIN_ALPHA = 0.5
# an instance seen on fewer pixels than this in a view adds nothing but noise to its fusion
MIN_PIXELS = 16
# the finest object voxel is its bounding-box diagonal over this (a 10 cm thing: 0.4 mm, a 40 cm
# ball: 2.8 mm): detail below it is under the 1 cm scale anyone scores or simulates objects at
MAX_VOXELS_PER_DIAGONAL = 250
# views an instance is fused from, evenly spaced over those that see it: a 150-frame chess capture
# (5 s at 30 fps, ~1 deg between frames) fused each thing from ~90 renders of nearly one viewpoint,
# 31 of its 196 s export; the surface comes from the spread of the views, not their number
MAX_FUSION_VIEWS = 30


@dataclass
class InstanceMesh:
    instance_id: int
    semantic_id: int
    label: str
    mesh: object            # trimesh.Trimesh or None
    support_z: float | None = None   # height of the up-facing stuff surface under it (world z)
    dropped_surfels: int = 0         # surfels of this label away from its main body (not fused)
    why_empty: str = ""              # why no surface was fused (mesh None or empty), for the report
    members: np.ndarray | None = None  # [N] bool: the surfels of its main body


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

    s = scene.surfels
    for t in things:
        seen = [k for k, m in enumerate(maps) if int((m == t.instance_id).sum()) >= MIN_PIXELS]
        seen = [seen[k] for k in evenly_spaced(len(seen), MAX_FUSION_VIEWS)]
        if not seen:
            most = max((int((m == t.instance_id).sum()) for m in maps), default=0)
            t.why_empty = (f"its {int((iid == t.instance_id).sum())} surfels win at most {most} pixels of a "
                           f"view (< {MIN_PIXELS}): hidden behind other labels")
            continue
        sel = main_body(s["means"], s["scales"], iid == t.instance_id)
        t.dropped_surfels = int((iid == t.instance_id).sum() - sel.sum())
        t.members = sel
        try:
            t.mesh = fuse_instance({k: s[k][torch.as_tensor(sel)] for k in ("means", "quats", "scales",
                                                                            "opacities", "colors")},
                                   [views[k] for k in seen], depth_max=params.depth_max)
        except RuntimeError as e:    # Open3D aborts when the masked depth touches no voxel block
            t.mesh, t.why_empty = None, f"TSDF fusion failed: {str(e).strip().splitlines()[-1][:120]}"
        if t.mesh is None and not t.why_empty:
            t.why_empty = (f"rendered alone, its {int(sel.sum())} surfels cover fewer than {MIN_PIXELS} pixels "
                           f"at opacity >= {MIN_ALPHA} in every view")
        elif t.mesh is not None and len(t.mesh.faces) == 0:
            t.why_empty = "the TSDF of its renders holds no surface"
    # support-aware bottoms: the discs of the sides hang below the support; cut every object at the
    # up-facing stuff surface under it (floor, table) and cap it there, so it rests on its support
    up = surfel_normals(s["quats"])[:, 2] > 0.9
    means = s["means"].detach().numpy()
    for t in things:
        if t.mesh is not None and len(t.mesh.faces):
            support_pts = means[up & (iid != t.instance_id)]
            t.support_z = support_height(t.mesh, support_pts)
            t.mesh = _tightest_sound(t.mesh, s, t.members if t.members is not None else iid == t.instance_id,
                                     support_pts)
    obj_voxel = min([getattr(t.mesh, "voxel_size", obj_voxel) for t in things if t.mesh is not None] or [obj_voxel])
    bg_masks = [np.isin(m, list(stuff_ids)) & (m >= 0) for m in maps]
    background = None
    if sum(int(m.sum()) for m in bg_masks) >= 16:
        background = fuse_tsdf(depths, Ks, c2ws, colors=colors, masks=bg_masks, voxel_size=params.voxel_size,
                               depth_max=params.depth_max)
    return InstanceMeshes(things, background, views, maps, obj_voxel)


def main_body(means, scales, sel: np.ndarray, link: float = 4.0) -> np.ndarray:
    """[N] bool: the surfels of `sel` [N] bool in its largest spatially connected cluster.

    means [N, 3], scales [N, 2]. An imperfect panoptic field gives one label to pieces of other
    objects across the room (a table's id on a far bottle): fused together they make one
    room-spanning "object". Surfels closer than `link` x the label's median surfel radius are
    connected (a surface's surfels overlap); the cluster with the most surfel area is the object.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    idx = np.flatnonzero(sel)
    if len(idx) < 3:
        return sel
    m = np.asarray(means.detach() if hasattr(means, "detach") else means, np.float64)[idx]
    sc = np.asarray(scales.detach() if hasattr(scales, "detach") else scales, np.float64)[idx]
    r = link * float(np.median(sc.max(axis=1)))
    pairs = cKDTree(m).query_pairs(r, output_type="ndarray")
    if len(pairs) == 0:
        return sel
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(idx), len(idx)))
    n, lab = connected_components(g, directed=False)
    if n == 1:
        return sel
    area = np.bincount(lab, weights=sc[:, 0] * sc[:, 1], minlength=n)
    out = np.zeros_like(sel)
    out[idx[lab == int(area.argmax())]] = True
    return out


def fuse_instance(surfels: dict, views, *, depth_max: float, px_per_voxel: float = 1.5,
                  max_side: int = 640):
    """TSDF mesh of one instance from its own surfels rendered alone in each view that sees it.

    surfels: the instance's "means" [n,3], "quats" [n,4], "scales" [n,2], "opacities" [n],
    "colors" [n,3]. Rendering the instance alone gives its exact silhouette (no blending with what
    lies behind it at the border, which fattens a masked full render by a pixel all round), and
    the render is supersampled so the pixel footprint falls under the voxel, which is tied to the
    surfel size (the finest detail the map holds). Returns trimesh with `.voxel_size` set.
    """
    import torch

    from psimap.geometry.tsdf import fuse_tsdf
    from psimap.render import rasterize

    means = surfels["means"].detach().to(torch.float32)
    footprints = []         # (view, metres per pixel at the instance's median depth)
    for v in views:
        pc = transform_points(means.numpy().astype(np.float64), np.linalg.inv(v.c2w))
        z = pc[:, 2][pc[:, 2] > 1e-3]
        if len(z):
            footprints.append((v, float(np.median(z)) / float(v.K[0, 0])))
    if not footprints:
        return None
    # voxel: 3/4 of the median surfel radius (the finest detail the map holds), but never finer than
    # the supersampled renders resolve (finer voxels only fuse holes and noise) nor than
    # MAX_VOXELS_PER_DIAGONAL across the instance (a 40 cm ball of 2 mm surfels would otherwise fuse
    # a million faces for minutes and can exhaust the voxel hash map)
    voxel = float(torch.median(surfels["scales"].detach().max(dim=1).values)) * 0.75
    finest_render = min(f * max(v.depth.shape) / max_side for v, f in footprints)
    diagonal = float(np.linalg.norm(np.ptp(means.numpy(), axis=0))) if len(means) > 1 else 0.0
    voxel = max(voxel, px_per_voxel * finest_render, diagonal / MAX_VOXELS_PER_DIAGONAL)
    depths, Ks, c2ws, cols = [], [], [], []
    for v, footprint in footprints:
        h, w = v.depth.shape
        cam = np.linalg.inv(v.c2w)
        scale = min(max(1.0, px_per_voxel * footprint / voxel), max_side / max(h, w))
        K = scale_intrinsics(v.K, scale)
        W, H = int(round(w * scale)), int(round(h * scale))
        with torch.no_grad():
            out = rasterize(means, surfels["quats"], surfels["scales"], surfels["opacities"], surfels["colors"],
                            torch.as_tensor(cam, dtype=torch.float32), torch.as_tensor(K, dtype=torch.float32),
                            W, H, backend="auto")
        alpha = out.alpha.numpy()
        d = out.median_depth.numpy()
        ok = (alpha >= MIN_ALPHA) & np.isfinite(d) & (d > 0)
        if int(ok.sum()) < MIN_PIXELS:
            continue
        depths.append(np.where(ok, d, 0).astype(np.float32))
        Ks.append(K)
        c2ws.append(v.c2w)
        cols.append(np.clip(out.rgb.numpy() / np.maximum(alpha, 1e-6)[..., None], 0, 1).astype(np.float32))
    if not depths:
        return None
    # the renders are clean (no sensor noise at range): the scene's depth cap must not cut a far
    # instance away (a box 5 m off was lost whole: "no block touched")
    far = max(float(d[d > 0].max()) for d in depths)
    mesh = fuse_tsdf(depths, Ks, c2ws, colors=cols, voxel_size=voxel, trunc=4 * voxel,
                     depth_max=max(float(depth_max), far + 4 * voxel), keep_fraction=0.2,
                     block_count=instance_blocks(means.numpy(), voxel))
    mesh.voxel_size = voxel
    return mesh


def instance_blocks(means: np.ndarray, voxel: float, block: int = 8) -> int:
    """Voxel blocks to reserve for fusing one instance with surfel centres means [n, 3] at `voxel`:
    its bounding box's surface in blocks, twice (the truncation band spans two), 256..20000. The
    scene-sized default (20,000 blocks, ~200 MB zeroed per call) made TSDF fusion of a 7 cm thing
    spend more system than user time; the hash map still grows if this is short."""
    ext = np.ptp(np.asarray(means, np.float64).reshape(-1, 3), axis=0) + 8 * voxel if len(means) else np.zeros(3)
    side = np.maximum(ext / (block * voxel), 1.0)
    area = 2.0 * (side[0] * side[1] + side[1] * side[2] + side[0] * side[2])
    return int(np.clip(2.0 * area, 256, 20000))


def surfel_normals(quats) -> np.ndarray:
    """[n, 3] unit normals (local z axis) of surfels with quaternions quats [n, 4] (w, x, y, z)."""
    return quat_to_rotmat(quats.detach() if hasattr(quats, "detach") else quats)[:, :, 2]


def project_to_surfels(mesh, centres: np.ndarray, normals: np.ndarray, k: int = 6):
    """Move every vertex of `mesh` onto the local plane of its nearest surfels (moving least squares).

    centres [n, 3], normals [n, 3]. Surfel centres lie on the surface but their discs overhang
    edges by up to a radius, so a silhouette-fused mesh is fat by that much; the planes through the
    centres are where the surface is. Each vertex moves along the weighted mean normal only (so
    faces become flat where they belong and the mesh keeps its connectivity).
    """
    import trimesh
    from scipy.spatial import cKDTree

    if len(centres) < 3:
        return mesh
    v = np.asarray(mesh.vertices, np.float64)
    k = min(k, len(centres))
    dist, idx = cKDTree(centres).query(v, k=k)
    h = np.maximum(dist[:, -1:], 1e-9)
    wts = np.exp(-(dist / h) ** 2)
    n = normals[idx]
    # normals of neighbours agree in sign with the nearest one (a plane, not a sheet pair)
    n *= np.sign(np.einsum("ijk,ik->ij", n, n[:, 0]))[..., None]
    off = np.einsum("ijk,ijk->ij", v[:, None] - centres[idx], n)
    dn = (wts[..., None] * n).sum(1)
    dn /= np.linalg.norm(dn, axis=1, keepdims=True).clip(1e-12)
    step = (wts * off).sum(1) / wts.sum(1)
    # at edges and corners the neighbours' planes disagree: moving there folds the mesh, so the
    # move fades out as the normals spread
    agree = np.clip((np.einsum("ijk,ik->ij", n, dn).min(axis=1) - 0.7) / 0.25, 0.0, 1.0)
    step *= agree
    out = trimesh.Trimesh(v - step[:, None] * dn, np.asarray(mesh.faces), process=False,
                          vertex_colors=getattr(mesh.visual, "vertex_colors", None))
    return out


def support_height(mesh, support_points: np.ndarray, margin: float = 0.05, sink: float = 0.02,
                   tol: float = 0.01, min_count: int = 3, max_gap: float = np.radians(200)) -> float | None:
    """z of the surface `mesh` rests on, or None when there is none.

    support_points [n, 3]: up-facing surfel centres of everything else (floor, table tops). Those
    inside the footprint grown by `margin` and below the object's mid-height are candidates, as
    levels (points within `tol`, at least `min_count`). The highest level that surrounds the object
    (no angular gap wider than `max_gap` around its centre) is its support: a fused bottom can sink
    centimetres into a table top, and the top of a shorter neighbour beside it lies on one side
    only. Without a surrounding level, the highest one no more than `sink` above its lowest point.
    """
    if len(support_points) == 0:
        return None
    lo, hi = np.asarray(mesh.bounds)
    p = support_points
    inside = ((p[:, 0] > lo[0] - margin) & (p[:, 0] < hi[0] + margin) & (p[:, 1] > lo[1] - margin)
              & (p[:, 1] < hi[1] + margin) & (p[:, 2] < 0.5 * (lo[2] + hi[2])))
    if inside.sum() < min_count:
        return None
    q = p[inside]
    q = q[np.argsort(-q[:, 2])]
    centre = 0.5 * (lo[:2] + hi[:2])
    fallback = None
    done = np.zeros(len(q), bool)
    for i in range(len(q)):
        if done[i]:
            continue
        near = np.abs(q[:, 2] - q[i, 2]) <= tol
        done |= near
        if near.sum() < min_count:
            continue
        z = float(np.median(q[near, 2]))
        ang = np.sort(np.arctan2(q[near, 1] - centre[1], q[near, 0] - centre[0]))
        gaps = np.diff(np.concatenate([ang, ang[:1] + 2 * np.pi]))
        if gaps.max() <= max_gap:
            return z
        if fallback is None and z <= lo[2] + sink:
            fallback = z
    return fallback


def clip_to_support(mesh, z: float):
    """`mesh` cut at height z (world Z-up) with the cut capped: what hangs below its support goes."""
    if float(mesh.bounds[0, 2]) >= z:
        return mesh
    import trimesh
    from trimesh.intersections import slice_faces_plane

    # open cut (Trimesh.slice_plane needs shapely); the repair step closes it flat at z
    v, f = slice_faces_plane(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces),
                             plane_normal=np.array([0.0, 0.0, 1.0]), plane_origin=np.array([0.0, 0.0, z]))[:2]
    if len(f) == 0:
        return mesh
    m = trimesh.Trimesh(v, f, process=True)
    return _cap_plane_holes(m, z)


def _cap_plane_holes(mesh, z: float, tol: float = 1e-6):
    """Close every boundary loop lying in the plane height z with a fan from its centroid (the cut's
    footprint is star-shaped for the objects that rest on a support; repair re-checks the result)."""
    import networkx as nx
    import trimesh

    f = np.asarray(mesh.faces)
    v = np.asarray(mesh.vertices, np.float64)
    e = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)      # directed edges in winding order
    key = np.sort(e, axis=1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    bnd = e[cnt[inv.ravel()] == 1]
    on = (np.abs(v[bnd[:, 0], 2] - z) < tol) & (np.abs(v[bnd[:, 1], 2] - z) < tol)
    bnd = bnd[on]
    if len(bnd) < 3:
        return mesh
    g = nx.Graph()
    g.add_edges_from(map(tuple, bnd))
    new_v, new_f = [v], [f]
    n = len(v)
    for comp in nx.connected_components(g):
        loop = bnd[np.isin(bnd[:, 0], list(comp))]
        if len(loop) < 3:
            continue
        new_v.append(v[list(comp)].mean(axis=0, keepdims=True))
        # reversed edge + centre keeps the winding consistent with the side faces
        new_f.append(np.column_stack([loop[:, 1], loop[:, 0], np.full(len(loop), n)]))
        n += 1
    return trimesh.Trimesh(np.concatenate(new_v), np.concatenate(new_f), process=True)


def _tightest_sound(raw, surfels: dict, sel: np.ndarray, support_points: np.ndarray):
    """The surfel-projected mesh cut at its support when that still repairs to a watertight solid,
    else the unprojected one cut at its support, else `raw` (projection can fold thin corners)."""
    from psimap.exporters.repair import repair_mesh

    z = support_height(raw, support_points)
    voxel = getattr(raw, "voxel_size", None)
    means = surfels["means"].detach().numpy()[sel]
    cands = [project_to_surfels(raw, means, surfel_normals(surfels["quats"][sel])), raw]
    for c in cands:
        c = clip_to_support(c, z) if z is not None else c
        if repair_mesh(c, need_volume=True).ok:
            c.voxel_size = voxel
            return c
    return raw
