"""MJCF writer: `scene.xml` + `assets/` for MuJoCo.

Per object a body at its centre of mass with a freejoint and an explicit <inertial> (principal axes
and moments; neither for a static object: furniture, barely seen or pinned things), a textured
visual mesh geom and its collision geoms: a primitive, or convex mesh parts (MuJoCo collides a mesh
geom through its convex hull, so each part is one convex piece). The background is static and visual
only (its convex hull would swallow the room); the static world's colliders (exporters.environment:
support slabs, walls, ceilings, clutter hulls, `env_<name>` geoms) and a floor plane carry its
contacts, the same set the USD has. Objects stand where the export scene puts them: as
reconstructed, moved by the settle check's nudge.

Conventions users know from obj2mjcf and MuJoCo Menagerie (docs/outputs.md, "The MJCF scene"):
- two <default> classes hold what a geom's role means, so it is changed in one place: `visual`
  (group 2, contype / conaffinity 0, density 0: drawn, adds no mass, never collides) and
  `collision` (group 3, density 0: the <inertial> carries the mass; friction; translucent blue);
  every geom but the floor names its class (`class="visual"` / `class="collision"`);
- stable names: body `<label>_<instance id>`, geoms `<body>_visual` and `<body>_collision_<k>`,
  assets after them, `env_<name>` for the static world: unique, and the same on every export;
- every mesh and texture under `meshdir` / `texturedir` (`assets/`), which MuJoCo resolves against
  the file's own folder: the scene loads from any working directory;
- `python -m mujoco.viewer --mjcf=scene.xml` opens framed on the objects: <statistic> centre and
  extent are those of the objects (not of the room around them), the free camera looks down from
  <visual><global> azimuth / elevation, and a fixed camera `overview` gives the same view to
  offscreen renderers (`mujoco.Renderer.update_scene(data, camera="overview")`).
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from psimap.transforms import rotmat_to_quat


def _f(x) -> str:
    """Deterministic compact float text."""
    return " ".join(f"{float(v):.9g}" for v in np.atleast_1d(x))


# The free camera's view of the scene (degrees): from the south-east, looking down at 35 degrees
# (MuJoCo's default, 90 / -45, looks along +y from straight above a table and hides heights).
CAMERA_AZIMUTH = 135.0
CAMERA_ELEVATION = -35.0
FOVY = 45.0           # MuJoCo's default, for both cameras
# object friction is the class's (exporters.physics); the static world's, the floor's and the
# collision class's default: torsional and rolling friction as MuJoCo's defaults
WORLD_FRICTION = (0.8, 0.005, 0.0001)
COLLISION_RGBA = "0.2 0.6 0.9 0.4"
ENVIRONMENT_RGBA = "0.5 0.5 0.55 0.35"


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
    centre, extent = framing(scene)
    ET.SubElement(root, "statistic", center=_f(centre), extent=_f(extent))
    vis = ET.SubElement(root, "visual")
    ET.SubElement(vis, "global", azimuth=_f(CAMERA_AZIMUTH), elevation=_f(CAMERA_ELEVATION))
    ET.SubElement(vis, "headlight", ambient="0.4 0.4 0.4", diffuse="0.6 0.6 0.6")
    defaults = ET.SubElement(root, "default")
    visual_class = ET.SubElement(defaults, "default", {"class": "visual"})
    ET.SubElement(visual_class, "geom", type="mesh", group="2", contype="0", conaffinity="0", density="0")
    # a visual mesh's volume is never needed (density 0), and open meshes (background) have none
    ET.SubElement(visual_class, "mesh", inertia="shell")
    collision_class = ET.SubElement(defaults, "default", {"class": "collision"})
    ET.SubElement(collision_class, "geom", group="3", density="0", friction=_f(WORLD_FRICTION),
                  rgba=COLLISION_RGBA)
    asset = ET.SubElement(root, "asset")
    ET.SubElement(asset, "texture", name="floor_grid", type="2d", builtin="checker", rgb1="0.7 0.7 0.7",
                  rgb2="0.6 0.6 0.6", width="256", height="256")
    ET.SubElement(asset, "material", name="floor_material", texture="floor_grid", texrepeat="8 8")
    world = ET.SubElement(root, "worldbody")
    ET.SubElement(world, "light", name="sun", pos=_f([0, 0, floor_z + 5]), dir="0 0 -1",
                  directional="true")
    ET.SubElement(world, "camera", name="overview", **overview_camera(centre, extent))
    # the floor is seen and collides: group 0 (shown with the visuals and the colliders hidden)
    ET.SubElement(world, "geom", name="floor", type="plane", size="0 0 0.05", pos=_f([0, 0, floor_z]),
                  material="floor_material", friction=_f(WORLD_FRICTION), group="0")
    # the static world's colliders: convex slabs and hulls, welded to the world (the background
    # mesh itself is visual only)
    for c in (scene.environment.colliders if scene.environment is not None else ()):
        fname = f"env_{c.name}.stl"
        write_plain(np.asarray(c.mesh.vertices, np.float64), np.asarray(c.mesh.faces), assets / fname)
        ET.SubElement(asset, "mesh", name=f"env_{c.name}", file=fname)
        ET.SubElement(world, "geom", {"name": f"env_{c.name}", "class": "collision", "type": "mesh",
                                      "mesh": f"env_{c.name}", "rgba": ENVIRONMENT_RGBA})

    def visual_geom(parent, o, origin: np.ndarray) -> None:
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
        ET.SubElement(asset, "mesh", {"name": f"{name}_visual", "class": "visual", "file": f"{name}.obj"})
        ET.SubElement(parent, "geom", {"name": f"{name}_visual", "class": "visual", "mesh": f"{name}_visual",
                                       "material": f"{name}_material"})

    if background is not None:
        bg = ET.SubElement(world, "body", name=background.name, pos=_f(np.zeros(3)))
        visual_geom(bg, background, np.zeros(3))

    for o in objects:
        ph = o.physics
        com = np.asarray(ph.com, np.float64)
        body = ET.SubElement(world, "body", name=o.name, pos=_f(com + scene.offset(o)))
        if o.role is Role.DYNAMIC:     # a static object is welded to the world: no joint, no mass
            ET.SubElement(body, "freejoint", name=f"{o.name}_joint")
            ET.SubElement(body, "inertial", pos="0 0 0", quat=_f(rotmat_to_quat(ph.principal_axes)),
                          mass=_f(ph.mass), diaginertia=_f(_balanced(ph.principal_inertia)))
        visual_geom(body, o, com)
        fr = _f([ph.friction, 0.005, 0.0001])
        c = o.collision
        if c.is_primitive:
            T = np.asarray(c.transform, np.float64)
            size = np.asarray(c.size, np.float64)
            ET.SubElement(body, "geom", {"name": f"{o.name}_collision_0", "class": "collision", "type": c.kind,
                                         "size": _f(size), "pos": _f(T[:3, 3] - com),
                                         "quat": _f(rotmat_to_quat(T[:3, :3])), "friction": fr})
        else:
            for k, part in enumerate(c.parts):
                fname = f"{o.name}_collision_{k}.stl"
                write_plain(np.asarray(part.vertices, np.float64) - com, part.faces, assets / fname)
                ET.SubElement(asset, "mesh", name=f"{o.name}_collision_{k}", file=fname)
                ET.SubElement(body, "geom", {"name": f"{o.name}_collision_{k}", "class": "collision",
                                             "type": "mesh", "mesh": f"{o.name}_collision_{k}", "friction": fr})
    ET.indent(root, space="  ")
    path = out / "scene.xml"
    path.write_text(ET.tostring(root, encoding="unicode") + "\n")
    return path


def framing(scene) -> tuple[np.ndarray, float]:
    """(centre [3], extent) of what a viewer should frame: the objects' bounds as exported (nudges
    included), else the static world's colliders, else the background. MuJoCo's free camera stands
    1.5 extents from the centre, at CAMERA_AZIMUTH / CAMERA_ELEVATION, with a 45 degree vertical
    field of view: the extent is the least at which every corner of the bounds is in a 4:3 picture
    with a 10 % margin (a near corner needs more room than the bounds' radius suggests); at least
    0.25 m."""
    boxes = [np.asarray(o.visual.bounds, np.float64) + scene.offset(o) for o in scene.objects]
    if not boxes and scene.environment is not None:
        boxes = [np.asarray(c.mesh.bounds, np.float64) for c in scene.environment.colliders]
    if not boxes and scene.background is not None:
        boxes = [np.asarray(scene.background.visual.bounds, np.float64)]
    if not boxes:
        return np.array([0.0, 0.0, float(scene.floor_z)]), 1.0
    lo = np.min([b[0] for b in boxes], axis=0)
    hi = np.max([b[1] for b in boxes], axis=0)
    centre = (lo + hi) / 2
    forward, right, up = _camera_axes()
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]) - centre
    tan_half = 0.9 * np.tan(np.radians(FOVY) / 2)
    # a corner p is in the picture from distance D when |p.up| <= tan_half (D + p.forward), and the
    # same for p.right with the 4:3 width
    need = np.maximum(np.abs(corners @ up) / tan_half, np.abs(corners @ right) / (tan_half * 4 / 3)) - corners @ forward
    return centre, max(float(need.max()) / 1.5, 0.25)


def _camera_axes() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The free camera's forward, right and up unit vectors [3] (world frame)."""
    az, el = np.radians(CAMERA_AZIMUTH), np.radians(CAMERA_ELEVATION)
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return forward, right, np.cross(right, forward)


def overview_camera(centre: np.ndarray, extent: float) -> dict:
    """Attributes of a fixed <camera> where the viewer's free camera starts: 1.5 extents from
    `centre`, looking at it (xyaxes: the image's right and up)."""
    forward, right, up = _camera_axes()
    pos = np.asarray(centre, np.float64) - 1.5 * extent * forward
    return {"pos": _f(pos), "xyaxes": _f(np.concatenate([right, up])), "fovy": _f(FOVY)}


def _balanced(principal: np.ndarray) -> np.ndarray:
    """Principal moments that satisfy the triangle inequality MuJoCo checks (A + B >= C) after
    rounding to text; a tiny relative bump keeps thin plates valid."""
    p = np.maximum(np.asarray(principal, np.float64), 1e-12)
    for i in range(3):
        others = p.sum() - p[i]
        if others < p[i]:
            p[i] = others
    return p * (1 + 1e-6)
