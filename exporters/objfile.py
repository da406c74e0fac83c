"""Textured OBJ (+ MTL + PNG) and plain STL/OBJ writing shared by the writers (trimesh's exporter,
with deterministic names and a white diffuse factor so the texture shows at its true colour)."""
from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

# PNG encodings of textures by content: every writer (meshes/, the check's and the final MJCF's
# assets/, USD) writes the same texture, and each PIL encode of it took ~25 ms (a room export
# encoded each texture six times: 2.3 s); the newest TEXTURE_CACHE_SIZE are kept
TEXTURE_CACHE_SIZE = 64
_PNG_CACHE: OrderedDict = OrderedDict()
_PNG_LOCK = threading.Lock()           # exports may write from several threads (psimap batch)


def png_bytes(image) -> bytes:
    """A PIL image's PNG file (PIL's encoder with its default settings)."""
    from io import BytesIO

    buf = BytesIO()
    image.save(buf, format="PNG")
    return buf.getvalue()


def texture_png(image: np.ndarray) -> bytes:
    """The PNG file of a texture, image uint8 [S, S, 3] (PIL's encoder with its default settings,
    the bytes trimesh's exporter and PIL's save wrote), encoded once per content."""
    from PIL import Image

    a = np.ascontiguousarray(image)
    key = (a.shape, str(a.dtype), hashlib.blake2b(a.data, digest_size=16).digest())
    with _PNG_LOCK:
        png = _PNG_CACHE.get(key)
        if png is not None:
            _PNG_CACHE.move_to_end(key)
            return png
    png = png_bytes(Image.fromarray(a))
    with _PNG_LOCK:
        _PNG_CACHE[key] = png
        while len(_PNG_CACHE) > TEXTURE_CACHE_SIZE:
            _PNG_CACHE.popitem(last=False)
    return png


def write_textured_obj(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray | None,
                       image: np.ndarray | None, path: Path, name: str,
                       vertex_rgb: np.ndarray | None = None) -> list[str]:
    """Write `path` (.obj) with `name`.mtl and `name`.png beside it. Returns the file names written.

    vertices [V, 3] (frame chosen by the caller), faces [F, 3], uv [V, 2] or None, image uint8
    [S, S, 3] or None; without a texture, vertex colours (float [V, 3]) are written when given.
    """
    import trimesh

    path = Path(path)
    textured = uv is not None and image is not None
    if textured:
        # no image on the material: trimesh writes the OBJ's uv and the MTL, the texture's PNG
        # (texture_png, encoded once) and its map_Kd line are added here, as trimesh wrote them
        mat = trimesh.visual.material.SimpleMaterial(image=None, name=name,
                                                     diffuse=[255, 255, 255, 255],
                                                     ambient=[255, 255, 255, 255],
                                                     specular=[0, 0, 0, 255], glossiness=1.0)
        mesh = trimesh.Trimesh(vertices, faces, visual=trimesh.visual.TextureVisuals(uv=uv, material=mat),
                               process=False)
    else:
        colors = None if vertex_rgb is None else (np.clip(vertex_rgb, 0, 1) * 255).astype(np.uint8)
        mesh = trimesh.Trimesh(vertices, faces, vertex_colors=colors, process=False)
    text, files = trimesh.exchange.obj.export_obj(mesh, include_normals=False, include_texture=True,
                                                  return_texture=True, mtl_name=f"{name}.mtl",
                                                  header=None, digits=7)
    if textured:
        files[f"{name}.mtl"] += f"\nmap_Kd {name}.png".encode()
        files[f"{name}.png"] = texture_png(image)
    path.write_text(text)
    written = [path.name]
    for fname, data in sorted(files.items()):
        (path.parent / fname).write_bytes(data)
        written.append(fname)
    return written


def write_plain(vertices: np.ndarray, faces: np.ndarray, path: Path) -> None:
    """Geometry only (.stl binary or .obj), for collision parts."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    path = Path(path)
    if path.suffix == ".obj":
        path.write_text(trimesh.exchange.obj.export_obj(mesh, include_normals=False, include_color=False,
                                                        include_texture=False, header=None, digits=7))
    else:
        path.write_bytes(trimesh.exchange.stl.export_stl(mesh))
