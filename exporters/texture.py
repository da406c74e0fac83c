"""Step 5: UV unwrap (xatlas) and texture bake.

Sources, best first: the training views (colour + depth + pose; each texel takes the colour of the
views that see it, found by a depth test, weighted by how squarely they see it), or an already
textured mesh (closest point -> its UV -> its image: used for scans such as YCB), else per-vertex
colours. Texels no view saw keep the vertex-colour fallback, and seams are dilated so mip-mapping
does not bleed background into the object.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class View:
    """A posed colour + depth image. rgb [H, W, 3] float in [0, 1]; depth [H, W] metres (0 = none);
    K [3, 3]; c2w [4, 4] camera-to-world (OpenCV)."""
    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    c2w: np.ndarray


def texture_size(mesh, texel: float = 0.001, lo: int = 64, hi: int = 1024) -> int:
    """Power-of-two atlas side giving about `texel` metres per texel (atlas ~70 % used)."""
    side = np.sqrt(max(float(mesh.area), 1e-12) / 0.7) / texel
    return int(np.clip(2 ** int(np.ceil(np.log2(max(side, 1)))), lo, hi))


def unwrap(mesh):
    """(vertices [V', 3], faces [F, 3], uv [V', 2], vmap [V']) from xatlas; vertices split at seams."""
    import xatlas

    vmap, faces, uv = xatlas.parametrize(np.asarray(mesh.vertices, np.float32),
                                         np.asarray(mesh.faces, np.uint32))
    vmap = vmap.astype(np.int64)
    return np.asarray(mesh.vertices, np.float64)[vmap], faces.astype(np.int64), uv.astype(np.float64), vmap


def rasterize_uv(faces: np.ndarray, uv: np.ndarray, size: int, chunk: int = 1 << 20):
    """Texels covered by UV triangles.

    faces [F, 3], uv [V, 2] in [0, 1] (v up). Returns (rows [P], cols [P], face [P], bary [P, 3]).
    Texel (r, c) has centre uv = ((c + .5)/size, 1 - (r + .5)/size). The candidate texels (each
    face's bounding box) are tested about `chunk` at a time, per coordinate, with the per-face
    terms computed once: a 1024^2 atlas has ~2 million candidates, and whole-atlas [P, 2]
    temporaries cost more in page faults than in arithmetic.
    """
    faces = np.asarray(faces, np.int64)
    t = np.asarray(uv, np.float64)[faces] * size         # [F, 3, 2] in texel units (x right, y up)
    lo = np.floor(t.min(axis=1) - 0.5).astype(np.int64).clip(0, size - 1)
    hi = np.ceil(t.max(axis=1) - 0.5).astype(np.int64).clip(0, size - 1)
    nx, ny = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
    counts = nx * ny
    # per face: the edge vectors from vertex a and the dot products of barycentric coordinates
    ax, ay = t[:, 0, 0], t[:, 0, 1]
    e0x, e0y = t[:, 1, 0] - ax, t[:, 1, 1] - ay
    e1x, e1y = t[:, 2, 0] - ax, t[:, 2, 1] - ay
    d00 = e0x * e0x + e0y * e0y
    d01 = e0x * e1x + e0y * e1y
    d11 = e1x * e1x + e1y * e1y
    den = d00 * d11 - d01 * d01
    ok = np.abs(den) > 1e-12
    den = np.where(ok, den, 1.0)
    eps = 1e-6                                          # a texel centre on an edge is inside
    out = []
    ends = np.cumsum(counts)
    first = 0
    while first < len(faces):
        # faces [first, last) hold about `chunk` candidates (at least one face)
        base = ends[first] - counts[first]
        last = max(first + 1, int(np.searchsorted(ends, base + chunk, side="right")))
        f = np.arange(first, last)
        c = counts[f]
        fid = np.repeat(f, c)
        local = np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
        nxf = nx[fid]
        cx = lo[fid, 0] + local % nxf
        cy = lo[fid, 1] + local // nxf
        v2x, v2y = (cx + 0.5) - ax[fid], (cy + 0.5) - ay[fid]
        d20 = v2x * e0x[fid] + v2y * e0y[fid]
        d21 = v2x * e1x[fid] + v2y * e1y[fid]
        dn = den[fid]
        w1 = (d11[fid] * d20 - d01[fid] * d21) / dn
        w2 = (d00[fid] * d21 - d01[fid] * d20) / dn
        w0 = 1 - w1 - w2
        inside = ok[fid] & (w0 >= -eps) & (w1 >= -eps) & (w2 >= -eps)
        out.append((size - 1 - cy[inside], cx[inside], fid[inside],
                    np.stack([w0[inside], w1[inside], w2[inside]], 1)))
        first = last
    if not out:
        return (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)))
    return tuple(np.concatenate(parts) for parts in zip(*out))


def bake_from_views(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, views: list[View],
                    size: int, fallback_vertex_rgb: np.ndarray | None = None,
                    depth_tolerance: float = 0.02) -> tuple[np.ndarray, float]:
    """Texture image uint8 [size, size, 3] and the fraction of texels some view saw.

    vertices [V, 3] world, faces [F, 3], uv [V, 2]. A view colours a texel when the texel projects
    inside it, faces it, and its depth agrees with the view's depth within
    max(depth_tolerance, 2 % of depth) (occluded texels fail the test).
    """
    rows, cols, fid, bary = rasterize_uv(faces, uv, size)
    pos = np.einsum("pk,pkd->pd", bary, vertices[faces[fid]])          # [P, 3]
    fn = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-20)
    nrm = fn[fid]
    acc = np.zeros((len(pos), 3))
    wsum = np.zeros(len(pos))
    for v in views:
        xi, yi, z, vis = _depth_tested_pixels(pos, v, depth_tolerance)
        # only the texels this view sees are weighed (the others add 0: most of an atlas is out of
        # any one view's sight)
        idx = np.flatnonzero(vis)
        ray = pos[idx] - v.c2w[:3, 3]
        ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-20)
        cos = -(ray * nrm[idx]).sum(1)
        facing = cos > 0.1
        idx, cos = idx[facing], cos[facing]
        w = cos ** 4 / np.maximum(z[idx], 1e-3) ** 2                     # grazing / far views count less
        acc[idx] += w[:, None] * v.rgb[yi[idx], xi[idx], :3]
        wsum[idx] += w
    img = np.zeros((size, size, 3))
    filled = np.zeros((size, size), bool)
    if fallback_vertex_rgb is not None:
        img[rows, cols] = np.einsum("pk,pkd->pd", bary, fallback_vertex_rgb[faces[fid]])
        filled[rows, cols] = True
    seen = wsum > 0
    img[rows[seen], cols[seen]] = acc[seen] / wsum[seen, None]
    filled[rows[seen], cols[seen]] = True
    coverage = float(seen.mean()) if len(seen) else 0.0
    return _to_uint8(_dilate(img, filled)), coverage


def bake_from_mesh(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, source, size: int) -> np.ndarray:
    """Transfer a textured source mesh's colour onto a new UV atlas: uint8 [size, size, 3].

    source: trimesh.Trimesh with TextureVisuals (uv + image) or vertex colours.
    """
    import trimesh

    rows, cols, fid, bary = rasterize_uv(faces, uv, size)
    pos = np.einsum("pk,pkd->pd", bary, vertices[faces[fid]])
    closest, _, tri = trimesh.proximity.closest_point(source, pos)
    src_bary = trimesh.triangles.points_to_barycentric(source.triangles[tri], closest)
    vis = source.visual
    src_uv = getattr(vis, "uv", None)
    image = getattr(getattr(vis, "material", None), "image", None)
    if image is None and hasattr(vis, "material") and hasattr(vis.material, "baseColorTexture"):
        image = vis.material.baseColorTexture
    if src_uv is not None and image is not None:
        tex = np.asarray(image.convert("RGB"), np.float64) / 255.0
        suv = np.einsum("pk,pkd->pd", src_bary, np.asarray(src_uv)[source.faces[tri]])
        colors = _sample_bilinear(tex, suv)
    else:
        vc = np.asarray(source.visual.to_color().vertex_colors, np.float64)[:, :3] / 255.0
        colors = np.einsum("pk,pkd->pd", src_bary, vc[source.faces[tri]])
    return texel_image(rows, cols, colors, size)


def texel_image(rows: np.ndarray, cols: np.ndarray, colors: np.ndarray, size: int) -> np.ndarray:
    """uint8 [size, size, 3] atlas holding colors [P, 3] (float in [0, 1]) at texels (rows [P],
    cols [P]), with the seams dilated into the empty texels."""
    img = np.zeros((size, size, 3))
    filled = np.zeros((size, size), bool)
    img[rows, cols] = colors
    filled[rows, cols] = True
    return _to_uint8(_dilate(img, filled))


def _depth_tested_pixels(points: np.ndarray, view: View, depth_tolerance: float):
    """Nearest pixel of points [P, 3] in `view`: (x [P], y [P] int64 clipped to the image, z [P] camera
    depth, seen [P] bool). Seen: in front, inside the image, and within max(depth_tolerance, 2 % of
    depth) of the view's valid depth there (an occluded point fails)."""
    from psimap.camera import nearest_pixels

    H, W = view.depth.shape
    xi, yi, z, inb = nearest_pixels(points, view.K, view.c2w, W, H)
    d = view.depth[yi, xi]
    seen = inb & (d > 0) & (np.abs(d - z) <= np.maximum(depth_tolerance, 0.02 * z))
    return xi, yi, z, seen


def vertex_colors_from_views(vertices: np.ndarray, views: list[View], depth_tolerance: float = 0.02,
                             default=(0.6, 0.6, 0.6)) -> np.ndarray:
    """[V, 3] float colours: mean of the views that see each vertex (depth test); default if none."""
    acc = np.zeros((len(vertices), 3))
    n = np.zeros(len(vertices))
    for v in views:
        xi, yi, _, ok = _depth_tested_pixels(vertices, v, depth_tolerance)
        acc[ok] += v.rgb[yi[ok], xi[ok], :3]
        n[ok] += 1
    out = np.tile(np.asarray(default, np.float64), (len(vertices), 1))
    out[n > 0] = acc[n > 0] / n[n > 0, None]
    return out


def textured_mesh(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, image: np.ndarray, name: str):
    """trimesh.Trimesh with a PBR material whose base colour is `image` (uint8 [S, S, 3])."""
    import trimesh
    from PIL import Image

    mat = trimesh.visual.material.PBRMaterial(name=name, baseColorTexture=Image.fromarray(image),
                                              metallicFactor=0.0, roughnessFactor=0.9)
    vis = trimesh.visual.TextureVisuals(uv=uv, material=mat)
    return trimesh.Trimesh(vertices, faces, visual=vis, process=False)


def _sample_bilinear(tex: np.ndarray, uv: np.ndarray) -> np.ndarray:
    H, W = tex.shape[:2]
    x = (uv[:, 0] % 1.0) * W - 0.5
    y = (1.0 - uv[:, 1] % 1.0) * H - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0c, x1c = x0.clip(0, W - 1), (x0 + 1).clip(0, W - 1)
    y0c, y1c = y0.clip(0, H - 1), (y0 + 1).clip(0, H - 1)
    return ((1 - fx) * (1 - fy) * tex[y0c, x0c] + fx * (1 - fy) * tex[y0c, x1c]
            + (1 - fx) * fy * tex[y1c, x0c] + fx * fy * tex[y1c, x1c])


def _dilate(img: np.ndarray, filled: np.ndarray, iterations: int = 4) -> np.ndarray:
    """Grow filled texels into empty neighbours (seam padding) by repeated 3x3 averaging."""
    from scipy import ndimage

    img = img.copy()
    filled = filled.copy()
    k = np.ones((3, 3))
    for _ in range(iterations):
        cnt = ndimage.convolve(filled.astype(np.float64), k, mode="constant")
        grow = (~filled) & (cnt > 0)
        if not grow.any():
            break
        for ch in range(3):
            s = ndimage.convolve(img[..., ch] * filled, k, mode="constant")
            img[..., ch][grow] = s[grow] / cnt[grow]
        filled |= grow
    return img


def _to_uint8(img: np.ndarray) -> np.ndarray:
    return (np.clip(np.nan_to_num(img), 0, 1) * 255 + 0.5).astype(np.uint8)
