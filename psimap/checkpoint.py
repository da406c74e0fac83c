"""The `scene.ckpt` file: a versioned schema of plain tensors and containers (docs/checkpoint.md).

Written atomically (temp file, then rename) and read with ``torch.load(weights_only=True)``, so
loading never unpickles code. Every problem with a file (truncated, not a checkpoint, written by a
newer psimap, inconsistent shapes, NaN) is one :class:`psimap.PsimapError` naming the file.
"""
from __future__ import annotations

import os
from pathlib import Path

from psimap import PsimapError

FORMAT = "psimap.scene"
VERSION = 1

# name -> (trailing shape; None = free width, dtype kind) for the per-surfel tensors
_SURFEL_FIELDS = {
    "means": ((3,), "float"),
    "quats": ((4,), "float"),
    "scales": ((2,), "float"),
    "opacities": ((), "float"),
    "colors": ((3,), "float"),
    "semantic": ((None,), "float"),
    "instance": ((None,), "float"),
}
_OPTIONAL_SURFEL_FIELDS = {"instance_id": ((), "int"), "semantic_id": ((), "int")}


def empty_queries(feature_dim: int = 0) -> dict:
    """Queries block with Q = 0: feature [0, F], mean [0, 3], cov [0, 3, 3]."""
    import torch

    return {"feature": torch.zeros(0, feature_dim), "mean": torch.zeros(0, 3),
            "cov": torch.zeros(0, 3, 3)}


def _plain(value):
    """Config / metrics values as plain python (weights_only loading accepts only these)."""
    import numpy as np

    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if hasattr(value, "item") and getattr(value, "numel", lambda: 2)() == 1:
        return value.item()
    return str(value)


def _as_tensor(x, dtype):
    import numpy as np
    import torch

    if isinstance(x, torch.Tensor):
        return x.detach().to("cpu", dtype).contiguous().clone()
    return torch.as_tensor(np.asarray(x), dtype=dtype).contiguous().clone()


def _check_finite(name: str, t, where: str) -> None:
    import torch

    if t.is_floating_point() and t.numel() and not bool(torch.isfinite(t).all()):
        bad = int((~torch.isfinite(t)).sum())
        raise PsimapError(f"{where}: {name} contains {bad} NaN/inf values")


def _class_list(classes) -> list[dict]:
    out = []
    for c in classes or []:
        if isinstance(c, dict):
            out.append({"id": int(c["id"]), "name": str(c["name"]), "isthing": bool(c["isthing"])})
        else:
            out.append({"id": int(c.id), "name": str(c.name), "isthing": bool(c.isthing)})
    return out


def build_state(surfels: dict, *, classes=(), cameras: dict | None = None, queries: dict | None = None,
                config: dict | None = None, metrics: dict | None = None) -> dict:
    """Assemble and validate a checkpoint dict (tensors on CPU, float32 / int64 / float64 cameras).

    surfels: means [N,3], quats [N,4] wxyz, scales [N,2], opacities [N], colors [N,3], optional
    semantic [N,S], instance [N,F] (missing -> width 0), instance_id [N], semantic_id [N].
    cameras: K [M,3,3], c2w [M,4,4] OpenCV, width, height, names (missing -> no cameras).
    """
    import torch

    where = "checkpoint"
    n = int(len(surfels["means"]))
    s = {}
    for name, (_, kind) in {**_SURFEL_FIELDS, **_OPTIONAL_SURFEL_FIELDS}.items():
        if name not in surfels or surfels[name] is None:
            if name in ("semantic", "instance"):
                s[name] = torch.zeros(n, 0)
            continue
        s[name] = _as_tensor(surfels[name], torch.float32 if kind == "float" else torch.int64)
    if queries is None:
        queries = empty_queries(int(s["instance"].shape[1]))
    q = {k: _as_tensor(queries[k], torch.float32) for k in ("feature", "mean", "cov")}
    cams = cameras or {}
    m = len(cams.get("names", [])) if cams else 0
    cam = {
        "K": _as_tensor(cams["K"], torch.float64) if m else torch.zeros(0, 3, 3, dtype=torch.float64),
        "c2w": _as_tensor(cams["c2w"], torch.float64) if m else torch.zeros(0, 4, 4, dtype=torch.float64),
        "width": int(cams.get("width", 0)), "height": int(cams.get("height", 0)),
        "names": [str(x) for x in cams.get("names", [])],
    }
    state = {"format": FORMAT, "version": VERSION, "surfels": s, "queries": q,
             "classes": _class_list(classes), "cameras": cam,
             "config": _plain(dict(config or {})), "metrics": _plain(dict(metrics or {}))}
    validate_state(state, where)
    return state


def validate_state(state, where: str) -> None:
    """Check the schema, shapes and finiteness of a checkpoint dict; PsimapError on any problem."""
    import torch

    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise PsimapError(f"{where}: not a psimap scene checkpoint (no '{FORMAT}' format tag)")
    version = state.get("version")
    if not isinstance(version, int):
        raise PsimapError(f"{where}: checkpoint has no integer version")
    if version > VERSION:
        raise PsimapError(f"{where}: checkpoint version {version} is newer than this psimap supports "
                          f"({VERSION}); upgrade psimap")
    if version < 1:
        raise PsimapError(f"{where}: invalid checkpoint version {version}")
    for key in ("surfels", "queries", "classes", "cameras", "config", "metrics"):
        if key not in state:
            raise PsimapError(f"{where}: checkpoint is missing '{key}'")
    s = state["surfels"]
    if not isinstance(s, dict) or "means" not in s:
        raise PsimapError(f"{where}: checkpoint surfels are missing 'means'")
    n = None
    for name, (trail, kind) in {**_SURFEL_FIELDS, **_OPTIONAL_SURFEL_FIELDS}.items():
        if name not in s:
            if name in _SURFEL_FIELDS:
                raise PsimapError(f"{where}: checkpoint surfels are missing '{name}'")
            continue
        t = s[name]
        if not isinstance(t, torch.Tensor):
            raise PsimapError(f"{where}: surfels['{name}'] is not a tensor")
        if n is None:
            n = int(t.shape[0]) if t.dim() else -1
        ok = t.dim() == 1 + len(trail) and int(t.shape[0]) == n and all(
            w is None or int(d) == w for d, w in zip(t.shape[1:], trail))
        if not ok:
            want = "[" + ", ".join(["N"] + ["*" if w is None else str(w) for w in trail]) + "]"
            raise PsimapError(f"{where}: surfels['{name}'] has shape {list(t.shape)}, expected {want} "
                              f"with N = {n}")
        if kind == "float" and not t.is_floating_point():
            raise PsimapError(f"{where}: surfels['{name}'] must be floating point")
        if kind == "int" and t.is_floating_point():
            raise PsimapError(f"{where}: surfels['{name}'] must be integer")
        _check_finite(f"surfels['{name}']", t, where)
    if n and bool((s["scales"] <= 0).any()):
        raise PsimapError(f"{where}: surfels['scales'] must be > 0")
    q = state["queries"]
    if not isinstance(q, dict) or any(k not in q for k in ("feature", "mean", "cov")):
        raise PsimapError(f"{where}: checkpoint queries need 'feature', 'mean' and 'cov'")
    nq = int(q["feature"].shape[0])
    if (q["mean"].shape != (nq, 3) or q["cov"].shape != (nq, 3, 3) or q["feature"].dim() != 2):
        raise PsimapError(f"{where}: inconsistent query shapes {list(q['feature'].shape)}, "
                          f"{list(q['mean'].shape)}, {list(q['cov'].shape)}")
    for k in ("feature", "mean", "cov"):
        _check_finite(f"queries['{k}']", q[k], where)
    cam = state["cameras"]
    if not isinstance(cam, dict) or any(k not in cam for k in ("K", "c2w", "width", "height", "names")):
        raise PsimapError(f"{where}: checkpoint cameras need K, c2w, width, height, names")
    m = len(cam["names"])
    if tuple(cam["K"].shape) != (m, 3, 3) or tuple(cam["c2w"].shape) != (m, 4, 4):
        raise PsimapError(f"{where}: camera shapes K {list(cam['K'].shape)}, c2w "
                          f"{list(cam['c2w'].shape)} do not match {m} names")
    _check_finite("cameras['K']", cam["K"], where)
    _check_finite("cameras['c2w']", cam["c2w"], where)
    if not isinstance(state["classes"], list):
        raise PsimapError(f"{where}: checkpoint classes must be a list")


def save_checkpoint(path, state: dict, *, overwrite: bool = False) -> Path:
    """Validate `state` (refusing NaN) and write it atomically to `path`. An existing file there is
    replaced only if it is a psimap checkpoint, or with `overwrite`."""
    import torch

    path = Path(path)
    validate_state(state, f"refusing to save {path}")
    from psimap.io_utils import atomic_path, check_output_file

    check_output_file(path, overwrite=overwrite, what="checkpoint")

    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    return path


def save_scene_checkpoint(path, surfels: dict, **kw) -> Path:
    """`build_state(surfels, **kw)` then `save_checkpoint`."""
    try:
        state = build_state(surfels, **kw)
    except PsimapError as e:
        raise PsimapError(f"refusing to save {path}: {str(e).split(': ', 1)[-1]}") from None
    return save_checkpoint(path, state)


def load_checkpoint(path) -> dict:
    """Read and validate a checkpoint; PsimapError with one clear line for any bad file."""
    import pickle
    import zipfile

    import torch

    path = Path(path)
    if not path.exists():
        raise PsimapError(f"{path}: no such checkpoint file")
    if path.is_dir():
        raise PsimapError(f"{path}: is a folder, expected a scene.ckpt file")
    size = os.path.getsize(path)
    if size == 0:
        raise PsimapError(f"{path}: empty file (truncated checkpoint?)")
    with open(path, "rb") as f:
        head = f.read(4)
    if head[:2] != b"PK":
        # torch.save writes a zip archive; anything else was never a psimap checkpoint
        raise PsimapError(f"{path}: not a psimap scene checkpoint (not a torch zip archive)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        msg = str(e).splitlines()[0] if str(e) else ""
        raise PsimapError(f"{path}: not a psimap scene checkpoint (unsafe or foreign content: "
                          f"{msg[:120]})") from None
    except (RuntimeError, EOFError, zipfile.BadZipFile, OSError, ValueError, KeyError) as e:
        raise PsimapError(f"{path}: truncated or corrupt checkpoint ({type(e).__name__})") from None
    validate_state(state, str(path))
    return state
