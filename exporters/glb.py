"""GLB writer (`scene.glb`): every object's textured visual mesh in one binary glTF, for a quick look
in any viewer (glTF is Y-up: the scene is rotated from psimap's Z-up world)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def write_glb(scene, out_dir: str | Path) -> Path:
    """Write `out_dir/scene.glb` of `scene` (exporters.formats.ExportScene); returns its path."""
    import trimesh

    from psimap.exporters.texture import textured_mesh

    glb = trimesh.Scene()
    z_up_to_y_up = trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0])
    for o in ([scene.background] if scene.background is not None else []) + list(scene.objects):
        v = np.asarray(o.visual.vertices, np.float64) + scene.offset(o)
        if o.uv is not None and o.texture is not None:
            m = textured_mesh(v, np.asarray(o.visual.faces), o.uv, o.texture, f"{o.name}_material")
        else:
            rgb = o.vertex_rgb if o.vertex_rgb is not None else np.full((len(v), 3), 0.6)
            m = trimesh.Trimesh(v, o.visual.faces, vertex_colors=(np.clip(rgb, 0, 1) * 255).astype(np.uint8),
                                process=False)
        glb.add_geometry(m, node_name=o.name, geom_name=o.name, transform=z_up_to_y_up)
    path = Path(out_dir) / "scene.glb"
    path.write_bytes(trimesh.exchange.gltf.export_glb(glb))
    return path
