"""OpenUSD writer (`scene.usda` + `assets/`) and its validation with `pxr.UsdValidation`.

Stage: Z-up, metersPerUnit 1, kilogramsPerUnit 1, defaultPrim /World, a PhysicsScene. Per object an
Xform (RigidBodyAPI, MassAPI with mass / centre of mass / principal inertia) holding a visual Mesh
(UsdPreviewSurface with the baked texture through the `st` primvar, MaterialBindingAPI) and its
colliders (CollisionAPI; convex parts with MeshCollisionAPI approximation convexHull, primitives as
UsdGeom Sphere / Cube / Cylinder). The class goes on the object through UsdSemantics.LabelsAPI
("class" taxonomy, what Isaac Sim's labelling reads) and the instance id as `psimap:instanceId`.
The background is visual only; the static world collides through /World/environment: one convex
Mesh per collider of exporters.environment (CollisionAPI, MeshCollisionAPI convexHull, purpose guide,
`psimap:role` support / wall / ceiling / clutter), the same set the MJCF has, and the floor box, both
with the MJCF's static-world friction (a UsdPhysics material). A
static object (furniture, barely seen or pinned things) has colliders without RigidBodyAPI / MassAPI.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from psimap.transforms import rotmat_to_quat

# friction of the floor and the static world's colliders (the MJCF's floor and env_* geoms: 0.8)
STATIC_FRICTION = 0.8


def _vt():
    from pxr import Gf, Vt

    return Gf, Vt


def _mesh_prim(stage, path: str, vertices: np.ndarray, faces: np.ndarray):
    from pxr import UsdGeom, Vt

    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(vertices, np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces, np.int32).ravel()))
    mesh.CreateSubdivisionSchemeAttr("none")
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([lo, hi]).astype(np.float32)))
    return mesh


def _material(stage, path: str, texture_file: str | None, rgb):
    from pxr import Sdf, UsdShade

    mat = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/PreviewSurface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.9)
    shader.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    mat.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    if texture_file is None:
        from pxr import Gf

        shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*[float(c) for c in rgb]))
        return mat
    reader = UsdShade.Shader.Define(stage, f"{path}/stReader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    st_input = mat.CreateInput("frame:stPrimvarName", Sdf.ValueTypeNames.String)
    st_input.Set("st")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).ConnectToSource(st_input)
    tex = UsdShade.Shader.Define(stage, f"{path}/diffuseTexture")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(texture_file)
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
    tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
    tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("clamp")
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
    tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(tex.ConnectableAPI(), "rgb")
    return mat


def _physics_material(stage, path: str, friction: float):
    """A UsdShade Material with UsdPhysics.MaterialAPI (static = dynamic friction, restitution 0),
    bound to colliders for the "physics" purpose."""
    from pxr import UsdPhysics, UsdShade

    mat = UsdShade.Material.Define(stage, path)
    phys = UsdPhysics.MaterialAPI.Apply(mat.GetPrim())
    phys.CreateStaticFrictionAttr(float(friction))
    phys.CreateDynamicFrictionAttr(float(friction))
    phys.CreateRestitutionAttr(0.0)
    return mat


def _bind_physics(prim, mat) -> None:
    from pxr import UsdShade

    UsdShade.MaterialBindingAPI.Apply(prim).Bind(mat, UsdShade.Tokens.weakerThanDescendants, "physics")


def _visual(stage, parent: str, obj, origin: np.ndarray, assets: Path, rel_assets: str):
    from pxr import Sdf, UsdGeom, UsdShade, Vt

    from psimap.exporters.objfile import texture_png

    v = np.asarray(obj.visual.vertices, np.float64) - origin
    mesh = _mesh_prim(stage, f"{parent}/visual", v, np.asarray(obj.visual.faces))
    tex_file = None
    if obj.uv is not None and obj.texture is not None:
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                     UsdGeom.Tokens.vertex)
        st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(obj.uv, np.float32)))
        (assets / f"{obj.name}.png").write_bytes(texture_png(obj.texture))
        tex_file = f"./{rel_assets}/{obj.name}.png"
    rgb = np.asarray(obj.vertex_rgb).mean(axis=0) if obj.vertex_rgb is not None else (0.6, 0.6, 0.6)
    mat = _material(stage, f"{parent}/Looks/{obj.name}_material", tex_file, rgb)
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)
    return mesh


def write_usd(scene, out_dir: str | Path) -> Path:
    """Write `out_dir/scene.usda` (+ textures in `out_dir/assets/`) of `scene`
    (exporters.formats.ExportScene); returns its path."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics, UsdSemantics, Vt

    from psimap.exporters.roles import Role

    objects, background, floor_z = scene.objects, scene.background, scene.floor_z
    out = Path(out_dir)
    assets = out / "assets"
    assets.mkdir(parents=True, exist_ok=True)
    path = out / "scene.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    physics = UsdPhysics.Scene.Define(stage, "/World/PhysicsScene")
    physics.CreateGravityDirectionAttr(Gf.Vec3f(0, 0, -1))
    physics.CreateGravityMagnitudeAttr(9.81)

    # floor: a static thin box collider (a plane has no extent validators accept everywhere)
    floor = UsdGeom.Cube.Define(stage, "/World/floor")
    floor.CreateSizeAttr(1.0)
    floor.AddTranslateOp().Set(Gf.Vec3d(0, 0, floor_z - 0.05))
    floor.AddScaleOp().Set(Gf.Vec3f(100.0, 100.0, 0.1))
    UsdPhysics.CollisionAPI.Apply(floor.GetPrim())
    # the MJCF floor's friction: without a material each engine takes its own default (Newton 1.0,
    # PhysX 0.5)
    _bind_physics(floor.GetPrim(), _physics_material(stage, "/World/Looks/FloorPhysicsMaterial", STATIC_FRICTION))

    def label(prim, obj):
        sem = UsdSemantics.LabelsAPI.Apply(prim, "class")
        sem.CreateLabelsAttr(Vt.TokenArray([obj.label]))
        prim.CreateAttribute("psimap:instanceId", Sdf.ValueTypeNames.Int).Set(int(obj.instance_id))
        prim.CreateAttribute("psimap:semanticId", Sdf.ValueTypeNames.Int).Set(int(obj.semantic_id))

    if background is not None:
        bg = UsdGeom.Xform.Define(stage, f"/World/{background.name}")
        _visual(stage, bg.GetPath().pathString, background, np.zeros(3), assets, "assets")
        label(bg.GetPrim(), background)
    if scene.environment is not None and scene.environment.colliders:
        UsdGeom.Xform.Define(stage, "/World/environment")
        env_mat = _physics_material(stage, "/World/environment/Looks/PhysicsMaterial", STATIC_FRICTION)
        for c in scene.environment.colliders:
            pm = _mesh_prim(stage, f"/World/environment/{c.name}", np.asarray(c.mesh.vertices, np.float64),
                            np.asarray(c.mesh.faces))
            UsdGeom.Imageable(pm).CreatePurposeAttr(UsdGeom.Tokens.guide)
            UsdPhysics.CollisionAPI.Apply(pm.GetPrim())
            UsdPhysics.MeshCollisionAPI.Apply(pm.GetPrim()).CreateApproximationAttr(UsdPhysics.Tokens.convexHull)
            pm.GetPrim().CreateAttribute("psimap:role", Sdf.ValueTypeNames.Token).Set(c.role)
            _bind_physics(pm.GetPrim(), env_mat)

    for o in objects:
        ph = o.physics
        com = np.asarray(ph.com, np.float64) + scene.offset(o)
        x = UsdGeom.Xform.Define(stage, f"/World/{o.name}")
        x.AddTranslateOp().Set(Gf.Vec3d(*com))
        prim = x.GetPrim()
        if o.role is Role.DYNAMIC:     # a static object is a collider: CollisionAPI only, like the background
            UsdPhysics.RigidBodyAPI.Apply(prim)
            mass = UsdPhysics.MassAPI.Apply(prim)
            mass.CreateMassAttr(float(ph.mass))
            mass.CreateCenterOfMassAttr(Gf.Vec3f(0, 0, 0))
            mass.CreateDiagonalInertiaAttr(Gf.Vec3f(*[float(v) for v in ph.principal_inertia]))
            q = rotmat_to_quat(ph.principal_axes)
            mass.CreatePrincipalAxesAttr(Gf.Quatf(float(q[0]), float(q[1]), float(q[2]), float(q[3])))
        label(prim, o)
        base = f"/World/{o.name}"
        _visual(stage, base, o, np.asarray(ph.com, np.float64), assets, "assets")
        c = o.collision
        if c.is_primitive:
            T = np.asarray(c.transform, np.float64)
            local = T[:3, 3] - np.asarray(ph.com, np.float64)
            qc = rotmat_to_quat(T[:3, :3])
            if c.kind == "sphere":
                g = UsdGeom.Sphere.Define(stage, f"{base}/collision_0")
                g.CreateRadiusAttr(float(c.size[0]))
            elif c.kind == "box":
                g = UsdGeom.Cube.Define(stage, f"{base}/collision_0")
                g.CreateSizeAttr(2.0)
            else:
                g = UsdGeom.Cylinder.Define(stage, f"{base}/collision_0")
                g.CreateRadiusAttr(float(c.size[0]))
                g.CreateHeightAttr(float(2 * c.size[1]))
                g.CreateAxisAttr(UsdGeom.Tokens.z)
            g.AddTranslateOp().Set(Gf.Vec3d(*local))
            g.AddOrientOp().Set(Gf.Quatf(float(qc[0]), float(qc[1]), float(qc[2]), float(qc[3])))
            if c.kind == "box":
                g.AddScaleOp().Set(Gf.Vec3f(*[float(s) for s in c.size]))
            UsdGeom.Imageable(g).CreatePurposeAttr(UsdGeom.Tokens.guide)
            UsdPhysics.CollisionAPI.Apply(g.GetPrim())
        else:
            for k, part in enumerate(c.parts):
                pm = _mesh_prim(stage, f"{base}/collision_{k}",
                                np.asarray(part.vertices, np.float64) - np.asarray(ph.com, np.float64),
                                np.asarray(part.faces))
                UsdGeom.Imageable(pm).CreatePurposeAttr(UsdGeom.Tokens.guide)
                UsdPhysics.CollisionAPI.Apply(pm.GetPrim())
                UsdPhysics.MeshCollisionAPI.Apply(pm.GetPrim()).CreateApproximationAttr(
                    UsdPhysics.Tokens.convexHull)
        pmat = _physics_material(stage, f"{base}/Looks/PhysicsMaterial", ph.friction)
        for child in prim.GetChildren():
            if child.HasAPI(UsdPhysics.CollisionAPI):
                _bind_physics(child, pmat)
    stage.GetRootLayer().Save()
    return path


def validate_usd(path: str | Path) -> dict:
    """Run every registered pxr.UsdValidation validator on the stage.

    Returns {"validators": n, "errors": [str], "warnings": [str]}.
    """
    from pxr import Usd, UsdValidation

    stage = Usd.Stage.Open(str(path))
    reg = UsdValidation.ValidationRegistry()
    validators = reg.GetOrLoadAllValidators()
    ctx = UsdValidation.ValidationContext(validators)
    errors, warnings = [], []
    for e in ctx.Validate(stage):
        if e.HasNoError():
            continue
        msg = f"{e.GetName()}: {e.GetMessage()}"
        if e.GetType() == UsdValidation.ValidationErrorType.Error:
            errors.append(msg)
        else:
            warnings.append(msg)
    return {"validators": len(validators), "errors": sorted(errors), "warnings": sorted(warnings)}
