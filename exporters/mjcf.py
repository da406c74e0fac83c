"""MJCF writer: `scene.xml` + `assets/` for MuJoCo.

Per object a body at its centre of mass with a freejoint and an explicit <inertial> (principal axes
and moments; neither for a static object: furniture, barely seen or pinned things), a textured
visual mesh geom (group 2, contype/conaffinity 0, density 0: adds no mass and never collides) and
its collision geoms (group 3): a primitive, or convex mesh parts (MuJoCo collides a mesh geom
through its convex hull, so each part is one convex piece). The background is static and visual
only (its convex hull would swallow the room); the static world's colliders (exporters.environment:
support slabs, walls, ceilings, clutter hulls, `env_<name>` geoms) and a floor plane carry its
contacts, the same set the USD has. Objects stand where
the export scene puts them: as reconstructed, moved by the settle check's nudge. Names are
`<label>_<instance id>`: unique and stable between exports.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from psimap.transforms import rotmat_to_quat


def _f(x) -> str:
    """Deterministic compact float text."""
    return " ".join(f"{float(v):.9g}" for v in np.atleast_1d(x))


def write_mjcf(scene, out_dir: str | Path, *, timestep: float = 0.002, model_name: str = "psimap_scene") -> Path:
    """Write `out_dir/scene.xml` and `out_dir/assets/*` of `scene` (exporters.formats.ExportScene);
    returns the scene.xml path. The background is visual only; the floor is a plane at scene.floor_z.
    """
    from psimap.exporters.objfile import write_plain, write_textured_obj
    from psimap.exporters.roles import Role

    objects, background, floor_z = scene.objects, scene.background, scene.floor_z
    out = Path(out_dir)
    assets = out / "assets"
    assets.mkdir(parents=True, exist_ok=True)

    root = ET.Element("mujoco", model=model_name)
    ET.SubElement(root, "compiler", angle="radian", meshdir="assets", texturedir="assets",
                  autolimits="true")
    ET.SubElement(root, "option", timestep=_f(timestep), gravity="0 0 -9.81", integrator="implicitfast")
    vis = ET.SubElement(root, "visual")
    ET.SubElement(vis, "headlight", ambient="0.4 0.4 0.4", diffuse="0.6 0.6 0.6")
    asset = ET.SubElement(root, "asset")
    ET.SubElement(asset, "texture", name="floor_grid", type="2d", builtin="checker", rgb1="0.7 0.7 0.7",
                  rgb2="0.6 0.6 0.6", width="256", height="256")
    ET.SubElement(asset, "material", name="floor_material", texture="floor_grid", texrepeat="8 8")
    world = ET.SubElement(root, "worldbody")
    ET.SubElement(world, "light", name="sun", pos=_f([0, 0, floor_z + 5]), dir="0 0 -1",
                  directional="true")
    ET.SubElement(world, "geom", name="floor", type="plane", size="0 0 0.05", pos=_f([0, 0, floor_z]),
                  material="floor_material", friction="0.8 0.005 0.0001", group="0")
    # the static world's colliders: convex slabs and hulls, welded to the world (the background
    # mesh itself is visual only)
    for c in (scene.environment.colliders if scene.environment is not None else ()):
        fname = f"env_{c.name}.stl"
        write_plain(np.asarray(c.mesh.vertices, np.float64), np.asarray(c.mesh.faces), assets / fname)
        ET.SubElement(asset, "mesh", name=f"env_{c.name}", file=fname)
        ET.SubElement(world, "geom", name=f"env_{c.name}", type="mesh", mesh=f"env_{c.name}", group="3",
                      friction="0.8 0.005 0.0001", rgba="0.5 0.5 0.55 0.35")

    def visual_assets(o, origin: np.ndarray) -> dict:
        name = o.name
        v = np.asarray(o.visual.vertices, np.float64) - origin
        if o.uv is not None and o.texture is not None:
            write_textured_obj(v, o.visual.faces, o.uv, o.texture, assets / f"{name}.obj", f"{name}")
            ET.SubElement(asset, "texture", name=f"{name}_texture", type="2d", file=f"{name}.png")
            ET.SubElement(asset, "material", name=f"{name}_material", texture=f"{name}_texture")
        else:
            write_textured_obj(v, o.visual.faces, None, None, assets / f"{name}.obj", name)
            rgb = np.clip(np.asarray(o.vertex_rgb).mean(axis=0), 0, 1) if o.vertex_rgb is not None \
                else np.array([0.6, 0.6, 0.6])
            ET.SubElement(asset, "material", name=f"{name}_material", rgba=_f([*rgb, 1.0]))
        # 'shell' inertia: the visual mesh's volume is never needed (density 0), and open meshes
        # (background) have none
        ET.SubElement(asset, "mesh", name=f"{name}_visual", file=f"{name}.obj", inertia="shell")
        return {"type": "mesh", "mesh": f"{name}_visual", "material": f"{name}_material"}

    if background is not None:
        bg = ET.SubElement(world, "body", name=background.name, pos=_f(np.zeros(3)))
        attrs = visual_assets(background, np.zeros(3))
        ET.SubElement(bg, "geom", name=f"{background.name}_visual", group="2", contype="0",
                      conaffinity="0", density="0", **attrs)

    for o in objects:
        ph = o.physics
        com = np.asarray(ph.com, np.float64)
        body = ET.SubElement(world, "body", name=o.name, pos=_f(com + scene.offset(o)))
        if o.role is Role.DYNAMIC:     # a static object is welded to the world: no joint, no mass
            ET.SubElement(body, "freejoint", name=f"{o.name}_joint")
            ET.SubElement(body, "inertial", pos="0 0 0", quat=_f(rotmat_to_quat(ph.principal_axes)),
                          mass=_f(ph.mass), diaginertia=_f(_balanced(ph.principal_inertia)))
        attrs = visual_assets(o, com)
        ET.SubElement(body, "geom", name=f"{o.name}_visual", group="2", contype="0", conaffinity="0",
                      density="0", **attrs)
        fr = _f([ph.friction, 0.005, 0.0001])
        c = o.collision
        if c.is_primitive:
            T = np.asarray(c.transform, np.float64)
            size = np.asarray(c.size, np.float64)
            ET.SubElement(body, "geom", name=f"{o.name}_collision_0", type=c.kind, size=_f(size),
                          pos=_f(T[:3, 3] - com), quat=_f(rotmat_to_quat(T[:3, :3])), group="3",
                          density="0", friction=fr, rgba="0.2 0.6 0.9 0.4")
        else:
            for k, part in enumerate(c.parts):
                fname = f"{o.name}_collision_{k}.stl"
                write_plain(np.asarray(part.vertices, np.float64) - com, part.faces, assets / fname)
                ET.SubElement(asset, "mesh", name=f"{o.name}_collision_{k}", file=fname)
                ET.SubElement(body, "geom", name=f"{o.name}_collision_{k}", type="mesh",
                              mesh=f"{o.name}_collision_{k}", group="3", density="0", friction=fr,
                              rgba="0.2 0.6 0.9 0.4")
    ET.indent(root, space="  ")
    path = out / "scene.xml"
    path.write_text(ET.tostring(root, encoding="unicode") + "\n")
    return path


def _balanced(principal: np.ndarray) -> np.ndarray:
    """Principal moments that satisfy the triangle inequality MuJoCo checks (A + B >= C) after
    rounding to text; a tiny relative bump keeps thin plates valid."""
    p = np.maximum(np.asarray(principal, np.float64), 1e-12)
    for i in range(3):
        others = p.sum() - p[i]
        if others < p[i]:
            p[i] = others
    return p * (1 + 1e-6)
