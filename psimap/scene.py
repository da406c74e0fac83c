"""A trained scene: surfels + class table + cameras, as loaded from `scene.ckpt` (`load_scene`).

Every stage from training on passes this value around; the users' `psimap.load` returns the
subclass `psimap.api.Scene`, which adds the export stage's `objects()`.

Also `scene_from_meshes`: surfels sampled on given meshes with hard labels, so later stages (export,
completion, sim) can be tested on exact geometry independently of training quality.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from psimap import PsimapError
from psimap.transforms import rotmat_to_quat

# Rays per pixel side when meshing the rendered views. Measured on the demo scene (seed 0, 450
# steps): ss 1 / 2 / 3 -> Chamfer-L1 1.66 / 1.30 / 1.20 cm, F1@5cm 0.958 / 0.965 / 0.965, rendering +
# fusion 6 / 9 / 14 s; 2 takes most of the gain (RESULTS.md, "rays per pixel when meshing").
MESH_SUPERSAMPLE = 2


class Scene:
    """Surfel map with labels and cameras.

    surfels: dict of CPU tensors (checkpoint contract): means [N,3], quats [N,4] wxyz, scales [N,2],
    opacities [N], colors [N,3], semantic [N,S], instance [N,F], optional instance_id / semantic_id [N].
    queries: feature [Q,F], mean [Q,3], cov [Q,3,3]. classes: list of {"id","name","isthing"}.
    cameras: K [M,3,3], c2w [M,4,4] OpenCV, width, height, names.
    """

    def __init__(self, surfels: dict, *, classes=(), cameras: dict | None = None,
                 queries: dict | None = None, config: dict | None = None, metrics: dict | None = None,
                 path: str | None = None):
        from psimap.checkpoint import build_state

        state = build_state(surfels, classes=classes, cameras=cameras, queries=queries, config=config,
                            metrics=metrics)
        self._set_state(state)
        self.path = path

    @classmethod
    def load(cls, path) -> "Scene":
        """Read `scene.ckpt` (never unpickles code); PsimapError for a bad file."""
        from psimap.checkpoint import load_checkpoint

        return cls.from_state(load_checkpoint(path), path=str(path))

    @classmethod
    def from_state(cls, state: dict, path: str | None = None) -> "Scene":
        self = cls.__new__(cls)
        self._set_state(state)
        self.path = path
        return self

    def _set_state(self, state: dict) -> None:
        self.surfels = state["surfels"]
        self.queries = state["queries"]
        self.classes = state["classes"]
        self.cameras = state["cameras"]
        self.config = state["config"]
        self.metrics = state["metrics"]

    def state(self) -> dict:
        """Checkpoint dict of this scene (validated)."""
        from psimap.checkpoint import build_state

        return build_state(self.surfels, classes=self.classes, cameras=self.cameras,
                           queries=self.queries, config=self.config, metrics=self.metrics)

    def save(self, path, *, overwrite: bool = False) -> Path:
        """Write the checkpoint (an existing file is replaced only if it is a psimap checkpoint, or
        with `overwrite`)."""
        from psimap.checkpoint import save_checkpoint

        return save_checkpoint(path, self.state(), overwrite=overwrite)

    def __len__(self) -> int:
        return int(self.surfels["means"].shape[0])

    def __repr__(self) -> str:
        return (f"Scene({len(self)} surfels, {len(self.classes)} classes, "
                f"{len(self.cameras['names'])} cameras)")

    # ---- frame ---------------------------------------------------------------------------------
    def up_evidence(self) -> tuple:
        """(points [N, 3], normals [N, 3], weights [N], c2w [M, 4, 4]) for
        `psimap.geometry.gravity.estimate_up`: surfel centres, normals (third rotation column),
        areas x opacities, and the training cameras."""
        from psimap.transforms import quat_to_rotmat

        s = self.surfels
        means = s["means"].detach().cpu().double().numpy()
        normals = quat_to_rotmat(s["quats"].detach().cpu().double().numpy())[:, :, 2]
        sc = s["scales"].detach().cpu().double().numpy()
        weights = np.abs(sc[:, 0] * sc[:, 1]) * s["opacities"].detach().cpu().double().numpy().clip(0, 1)
        return means, normals, weights, self.cameras["c2w"].detach().cpu().double().numpy()

    def rotated(self, R) -> "Scene":
        """A copy of the scene turned by the rotation R [3, 3] about the world origin: surfel centres
        and orientations, query Gaussians and cameras. The rotation is recorded in
        config["world_rotation"] (composed with any earlier one: it takes the input capture's frame
        to this scene's)."""
        import torch

        from psimap.transforms import quat_to_rotmat, rotmat_to_quat

        R = np.asarray(R, np.float64)
        s = {k: v.clone() for k, v in self.surfels.items()}
        s["means"] = torch.as_tensor(s["means"].double().numpy() @ R.T, dtype=torch.float32)
        rot = R[None] @ quat_to_rotmat(s["quats"].double().numpy())
        s["quats"] = torch.as_tensor(rotmat_to_quat(rot), dtype=torch.float32)
        q = {k: v.clone() for k, v in self.queries.items()}
        q["mean"] = torch.as_tensor(q["mean"].double().numpy() @ R.T, dtype=torch.float32)
        q["cov"] = torch.as_tensor(R[None] @ q["cov"].double().numpy() @ R.T[None], dtype=torch.float32)
        cams = dict(self.cameras)
        T = np.eye(4)
        T[:3, :3] = R
        cams["c2w"] = torch.as_tensor(T[None] @ self.cameras["c2w"].double().numpy(), dtype=torch.float64)
        config = dict(self.config)
        before = np.asarray(config.get("world_rotation", np.eye(3).tolist()), np.float64)
        config["world_rotation"] = (R @ before).tolist()
        out = type(self)(s, classes=self.classes, cameras=cams, queries=q, config=config, metrics=self.metrics)
        out.path = self.path
        return out

    # ---- labels -------------------------------------------------------------------------------
    def instance_ids(self, min_affinity: float = 0.5):
        """[N] int64 instance id per surfel (0 = none).

        Hard labels when the checkpoint has them; otherwise the query of largest affinity
        A = sigmoid(f_q . f_g) * exp(-d_M^2 / 2) (paper §4: feature similarity times the query
        Gaussian's density ratio phi(p_g)/phi(p_q)), id = query index + 1, 0 below `min_affinity`.
        """
        import torch

        s = self.surfels
        if "instance_id" in s:
            return s["instance_id"].clone()
        n = len(self)
        q = self.queries
        if n == 0 or q["feature"].shape[0] == 0 or s["instance"].shape[1] == 0:
            return torch.zeros(n, dtype=torch.int64)
        sim = torch.sigmoid(s["instance"] @ q["feature"].T)                     # [N, Q]
        cov = q["cov"].double() + 1e-9 * torch.eye(3, dtype=torch.float64)
        prec = torch.linalg.inv(cov)                                             # [Q, 3, 3]
        diff = s["means"].double()[:, None, :] - q["mean"].double()[None]        # [N, Q, 3]
        d2 = torch.einsum("nqi,qij,nqj->nq", diff, prec, diff)
        aff = sim.double() * torch.exp(-0.5 * d2)
        best, idx = aff.max(1)
        return torch.where(best >= min_affinity, idx + 1, torch.zeros_like(idx)).to(torch.int64)

    def semantic_ids(self):
        """[N] int64 class id per surfel (0 = void): hard labels, else argmax of the logits."""
        import torch

        s = self.surfels
        if "semantic_id" in s:
            return s["semantic_id"].clone()
        n = len(self)
        S = int(s["semantic"].shape[1])
        if n == 0 or S == 0:
            return torch.zeros(n, dtype=torch.int64)
        # Logit column j is the j-th class of the table (ids need not be contiguous)
        ids = torch.tensor([int(c["id"]) for c in self.classes][:S] + [0] * max(0, S - len(self.classes)),
                           dtype=torch.int64)
        return ids[s["semantic"].argmax(1)]

    # ---- rendering ----------------------------------------------------------------------------
    def camera(self, i: int):
        """(K [3,3] float64 numpy, c2w [4,4] float64 numpy, width, height) of training camera i."""
        m = len(self.cameras["names"])
        if not 0 <= i < m:
            raise PsimapError(f"camera index {i} out of range (scene has {m} cameras)")
        return (self.cameras["K"][i].numpy(), self.cameras["c2w"][i].numpy(),
                int(self.cameras["width"]), int(self.cameras["height"]))

    def render(self, i_or_K, c2w=None, width: int | None = None, height: int | None = None,
               features: str | None = None, device=None, **kw):
        """Render training camera i, or a camera (K [3,3], c2w [4,4] OpenCV, width, height).

        features: None, "semantic" or "instance" (rendered into `.features`). device: where to render
        (default: where the surfels are, the CPU); "cuda" copies them there for this call and renders
        with the CUDA kernel where it covers the request (docs/renderer.md), the outputs staying on
        the device. Other keyword arguments go to `psimap.render.rasterize` (backend="auto" unless
        given). Returns its RenderOutput.
        """
        import torch

        from psimap.render import rasterize

        if c2w is None:
            K, c2w, width, height = self.camera(int(i_or_K))
        else:
            K = np.asarray(i_or_K, dtype=np.float64)
            if width is None or height is None:
                raise PsimapError("Scene.render: width and height are required with an explicit camera")
        s = self.surfels
        dev = s["means"].device if device is None else torch.device(device)
        viewmat = torch.as_tensor(np.linalg.inv(np.asarray(c2w, dtype=np.float64)), dtype=torch.float32)
        feats = s[features].to(dev) if features else None
        kw.setdefault("backend", "auto")
        with torch.no_grad():
            return rasterize(*(s[k].to(dev) for k in ("means", "quats", "scales", "opacities", "colors")),
                             viewmat.to(dev), torch.as_tensor(K, dtype=torch.float32, device=dev), int(width),
                             int(height), features=feats, **kw)

    def rendered_depths(self, cameras: Sequence[int] | None = None, depth: str = "median",
                        min_alpha: float = 0.5, progress: bool = False, supersample: int = 1):
        """Rendered depth, colour and camera of each training view, for TSDF fusion.

        Returns (depths [H*ss, W*ss] list, colors [H*ss, W*ss, 3] list, Ks, c2ws), rendered with
        ss = `supersample` rays per pixel side (Ks are those of the fine images); depth is 0 where
        alpha < min_alpha (pixels the surfels do not cover are unknown, not free space).
        """
        from tqdm import tqdm

        import torch

        from psimap.camera import supersample_intrinsics

        idx = range(len(self.cameras["names"])) if cameras is None else cameras
        depths, colors, Ks, c2ws = [], [], [], []
        threads = torch.get_num_threads()
        # the per-view tensors are small: torch's thread pool only adds spin-waiting on a busy CPU
        torch.set_num_threads(1)
        try:
            outs = []
            for i in tqdm(list(idx), desc="render", disable=not progress, leave=False):
                K, c2w, w, h = self.camera(int(i))
                K = supersample_intrinsics(K, supersample)
                outs.append((K, c2w, self.render(K, c2w, w * int(supersample), h * int(supersample))))
        finally:
            torch.set_num_threads(threads)
        for K, c2w, out in outs:
            d = (out.median_depth if depth == "median" else out.depth).numpy()
            a = out.alpha.numpy()
            depths.append(np.where((a >= min_alpha) & np.isfinite(d), d, 0).astype(np.float32))
            colors.append(np.clip(out.rgb.numpy(), 0, 1).astype(np.float32))
            Ks.append(K)
            c2ws.append(c2w)
        return depths, colors, Ks, c2ws

    def mesh(self, *, cameras: Sequence[int] | None = None, voxel_size: float | None = None,
             depth: str = "median", keep_fraction: float | None = None,
             min_component_voxels: float | None = None, supersample: int = MESH_SUPERSAMPLE,
             progress: bool = False):
        """Whole-scene mesh: TSDF fusion of the rendered depth + colour of the training views.

        The views are rendered with `supersample` rays per pixel side (the map is continuous: finer
        rays halve the ~1 px silhouette bleed of the splats' low-pass filter); the voxel size still
        follows the views' own pixel footprint. Cleaning (None = the whole-scene defaults
        `SCENE_KEEP_FRACTION` / `SCENE_MIN_COMPONENT_VOXELS` of psimap.geometry.tsdf): components
        below keep_fraction of the largest or below min_component_voxels voxel faces of area are
        dropped. Returns trimesh.Trimesh in metres, world frame, with vertex colours.
        """
        from psimap.geometry.tsdf import (SCENE_KEEP_FRACTION, SCENE_MIN_COMPONENT_VOXELS, derive_params,
                                          fuse_tsdf)

        if len(self.cameras["names"]) == 0:
            raise PsimapError("scene has no cameras to render for meshing")
        if len(self) == 0:
            raise PsimapError("scene has no surfels to mesh")
        depths, colors, Ks, c2ws = self.rendered_depths(cameras, depth=depth, progress=progress,
                                                        supersample=supersample)
        if voxel_size is None:      # footprint of the views' pixels, not of the finer rays
            ss = int(supersample)
            coarse = [d[ss // 2::ss, ss // 2::ss] for d in depths]
            idx = range(len(self.cameras["names"])) if cameras is None else cameras
            voxel_size = derive_params(coarse, [self.camera(int(i))[0] for i in idx], c2ws).voxel_size
        return fuse_tsdf(depths, Ks, c2ws, colors=colors, voxel_size=voxel_size,
                         keep_fraction=SCENE_KEEP_FRACTION if keep_fraction is None else keep_fraction,
                         min_component_voxels=(SCENE_MIN_COMPONENT_VOXELS if min_component_voxels is None
                                               else min_component_voxels), progress=progress)


def load_scene(path) -> Scene:
    """Read `scene.ckpt` (never unpickles code); PsimapError for a bad file."""
    return Scene.load(path)


def frame_from_normal(normals):
    """Rotations [N,3,3] whose third column is the unit normal [N,3] (tangents any orthonormal pair)."""
    n = np.asarray(normals, dtype=np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    # Helper axis least aligned with n keeps the cross product well conditioned
    helper = np.zeros_like(n)
    helper[np.arange(len(n)), np.argmin(np.abs(n), axis=1)] = 1.0
    t1 = np.cross(helper, n)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2, n], axis=2)


def _pixel_spacing(meshes, cameras) -> float | None:
    """Size of two pixels at the median camera-to-surface distance (what the views can resolve)."""
    if not cameras or len(cameras.get("names", [])) == 0:
        return None
    K = np.asarray(cameras["K"], dtype=np.float64)
    c2w = np.asarray(cameras["c2w"], dtype=np.float64)
    pts = np.concatenate([np.asarray(m.vertices) for m in meshes if len(m.vertices)])
    pts = pts[:: max(1, len(pts) // 2000)]
    dist = np.linalg.norm(pts[None] - c2w[:, None, :3, 3], axis=2)            # [M, P]
    focal = 0.5 * (K[:, 0, 0] + K[:, 1, 1])
    return float(2.0 * np.median(dist.min(0)) / np.median(focal))


def scene_from_meshes(meshes: Sequence, instance_ids: Sequence[int], semantic_ids: Sequence[int],
                      classes, cameras: dict | None = None, *, spacing: float | None = None,
                      colors: Sequence | None = None, opacity: float = 0.95, seed: int = 0) -> Scene:
    """Surfels sampled evenly on each mesh, carrying that mesh's hard instance / semantic id.

    meshes: trimesh.Trimesh list; instance_ids, semantic_ids: one int per mesh (0 = none);
    classes: ClassInfo or dicts; cameras: {"K" [M,3,3], "c2w" [M,4,4], "width", "height", "names"}.
    spacing: metres between surfels; default two pixels at the median viewing distance when cameras
    are given (finer is invisible to them), else sqrt(total area / 50 000).
    colors: per mesh an RGB in [0,1] (or None = the mesh's own vertex / face colours, else grey).
    """
    import trimesh

    if not (len(meshes) == len(instance_ids) == len(semantic_ids)):
        raise PsimapError(f"scene_from_meshes: {len(meshes)} meshes, {len(instance_ids)} instance ids, "
                          f"{len(semantic_ids)} semantic ids")
    meshes = [m for m in meshes]
    area = float(sum(m.area for m in meshes))
    if not meshes or area <= 0:
        raise PsimapError("scene_from_meshes: meshes have no surface area")
    if spacing is None:
        spacing = _pixel_spacing(meshes, cameras) or float(np.sqrt(area / 50_000))
    if not spacing > 0:
        raise PsimapError(f"scene_from_meshes: spacing must be > 0 (got {spacing})")
    rng = np.random.default_rng(seed)
    parts = {k: [] for k in ("means", "normals", "colors", "iid", "sid")}
    for j, m in enumerate(meshes):
        if m.area <= 0:
            continue
        count = max(4, int(np.ceil(m.area / spacing**2)))
        # Rejection sampling at radius ~ spacing gives the even coverage random sampling lacks;
        # top up with uniform samples if it returns too few for small, thin parts.
        pts, fidx = trimesh.sample.sample_surface_even(m, count, radius=0.8 * spacing,
                                                      seed=int(rng.integers(2**31)))
        if len(pts) < 0.5 * count:
            p2, f2 = trimesh.sample.sample_surface(m, count - len(pts), seed=int(rng.integers(2**31)))
            pts, fidx = np.concatenate([pts, p2]), np.concatenate([fidx, f2])
        parts["means"].append(pts)
        parts["normals"].append(np.asarray(m.face_normals)[fidx])
        if colors is not None and colors[j] is not None:
            c = np.broadcast_to(np.asarray(colors[j], dtype=np.float64)[:3], (len(pts), 3))
        else:
            c = _mesh_colors(m, fidx)
        parts["colors"].append(c)
        parts["iid"].append(np.full(len(pts), int(instance_ids[j])))
        parts["sid"].append(np.full(len(pts), int(semantic_ids[j])))
    means = np.concatenate(parts["means"])
    quats = rotmat_to_quat(frame_from_normal(np.concatenate(parts["normals"])))
    n = len(means)
    # Gaussian sigma ~ 0.6 spacing: neighbours overlap enough that the rendered surface has no holes
    scales = np.full((n, 2), 0.6 * spacing)
    surfels = {"means": means, "quats": quats, "scales": scales,
               "opacities": np.full(n, float(opacity)), "colors": np.clip(np.concatenate(parts["colors"]), 0, 1),
               "instance_id": np.concatenate(parts["iid"]), "semantic_id": np.concatenate(parts["sid"])}
    return Scene(surfels, classes=classes, cameras=cameras,
                 config={"source": "scene_from_meshes", "spacing": float(spacing)})


def _mesh_colors(mesh, fidx):
    """RGB in [0,1] [P,3] of sampled faces from a mesh's face / vertex colours (grey if none)."""
    vis = getattr(mesh, "visual", None)
    try:
        if vis is not None and vis.kind == "face":
            return np.asarray(vis.face_colors)[fidx, :3] / 255.0
        if vis is not None and vis.kind == "vertex":
            vc = np.asarray(vis.vertex_colors)[:, :3] / 255.0
            return vc[np.asarray(mesh.faces)[fidx]].mean(1)
        if vis is not None and vis.kind == "texture":
            vc = np.asarray(vis.to_color().vertex_colors)[:, :3] / 255.0
            return vc[np.asarray(mesh.faces)[fidx]].mean(1)
    except Exception:  # a broken material falls back to grey rather than failing the scene
        pass
    return np.full((len(fidx), 3), 0.5)
