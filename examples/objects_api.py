"""The Python API: every object of a trained scene with its mesh, collider, mass and class, one saved
as OBJ, and a table of them all.

    python examples/objects_api.py scene.ckpt                       # table + the first dynamic object
    python examples/objects_api.py scene.ckpt --save mug_11 --out my_objects

What it shows (psimap.load(ckpt).objects(), docs/examples.md "Python API"): each object is a
`SceneObject` with
- `name` (`<class>_<instance id>`, as every export names it), `label` (its class), `instance_id`;
- `mesh`: the watertight trimesh.Trimesh, metres, gravity-aligned world frame (Z-up); `visual`,
  `uv` and `texture`: the textured copy the exporters draw;
- `collision`: `kind` (sphere / box / cylinder / hull / decomposition), `parts` (convex trimesh
  pieces, world frame; primitives too), `error` (m, Hausdorff to the mesh), `size` / `transform`
  for a primitive;
- `physics`: `mass` (kg), `model` (solid or shell), `mass_range`, `density`, `com`, `inertia`,
  `friction`;
- `role` (dynamic / static / skipped) and `why`: the class decides static furniture here; the
  export's settle check may pin more (its report.json says which).
The files are written the way psimap writes (a fresh or psimap-written folder, built aside and
renamed: psimap.io_utils), so the example never replaces a file of yours.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def table(objects) -> str:
    """One row per object: name, class, role, mass (and its model), size, collider (kind, parts,
    error), visual faces."""
    rows = [f"{'object':<16}{'class':<10}{'role':<9}{'mass kg':>9} {'model':<6}{'size cm':>18}  "
            f"{'collider':<14}{'parts':>5}{'err mm':>7}{'faces':>7}"]
    for o in objects:
        ph, c = o.physics, o.collision
        size = "x".join(f"{v * 100:.1f}" for v in o.mesh.extents) if o.mesh is not None else "-"
        rows.append(f"{o.name:<16}{o.label:<10}{o.role.value:<9}"
                    f"{(f'{ph.mass:.3f}' if ph else '-'):>9} {(ph.model if ph else '-'):<6}{size:>18}  "
                    f"{(c.kind if c else '-'):<14}{(len(c.parts) if c else 0):>5}"
                    f"{(f'{c.error * 1000:.1f}' if c else '-'):>7}{len(o.visual.faces) if o.mesh is not None else 0:>7}")
    return "\n".join(rows)


def save(obj, out: Path) -> list[str]:
    """Write `obj` into the folder `out`: its textured visual mesh (<name>.obj + .mtl + .png), its
    collider as one OBJ of its convex parts (<name>_collider.obj) and its physics (<name>.json).
    Returns the files written."""
    import json

    import numpy as np
    import trimesh

    from psimap.exporters.objfile import write_textured_obj
    from psimap.io_utils import atomic_dir, export_mesh_file

    with atomic_dir(out, "export") as tmp:     # psimap's rules for an export folder (docs/outputs.md)
        files = write_textured_obj(np.asarray(obj.visual.vertices, np.float64), obj.visual.faces, obj.uv,
                                   obj.texture, tmp / f"{obj.name}.obj", obj.name, vertex_rgb=obj.vertex_rgb)
        export_mesh_file(trimesh.util.concatenate(obj.collision.parts), tmp / f"{obj.name}_collider.obj")
        ph = obj.physics
        (tmp / f"{obj.name}.json").write_text(json.dumps({
            "name": obj.name, "class": obj.label, "role": obj.role.value, "why": obj.why,
            "mass_kg": ph.mass, "mass_model": ph.model, "mass_range_kg": list(ph.mass_range),
            "density_kg_m3": ph.density, "friction": ph.friction, "com": np.asarray(ph.com).tolist(),
            "inertia": np.asarray(ph.inertia).tolist(), "collider": obj.collision.kind,
            "collider_error_m": obj.collision.error}, indent=2) + "\n")
        return sorted([*files, f"{obj.name}_collider.obj", f"{obj.name}.json"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", help="a trained scene.ckpt")
    ap.add_argument("--save", help="object to save as OBJ (default: the first dynamic one)")
    ap.add_argument("--out", default="objects_api_out", help="folder for the saved object")
    ap.add_argument("--completion", default="auto", help="completion method for partly seen objects")
    ap.add_argument("--up", default="auto", help="the capture's up direction (auto: estimated)")
    args = ap.parse_args(argv)

    import psimap

    from psimap.io_utils import check_output_dir

    t0 = time.perf_counter()
    try:
        check_output_dir(args.out, "export")          # before the work: a refusal costs nothing
        scene = psimap.load(args.checkpoint)
        objects = scene.objects(up=args.up, completion=args.completion)
    except psimap.PsimapError as e:
        sys.exit(f"objects_api: {e}")
    print(f"{len(objects)} objects of {args.checkpoint} in {time.perf_counter() - t0:.1f} s\n")
    print(table(objects))
    if not objects:
        return 0
    by_name = {o.name: o for o in objects}
    if args.save is not None and args.save not in by_name:
        sys.exit(f"objects_api: no object {args.save!r} (have: {', '.join(by_name)})")
    dynamic = [o for o in objects if o.role.value == "dynamic"]
    obj = by_name[args.save] if args.save else (dynamic or objects)[0]
    try:
        files = save(obj, Path(args.out))
    except psimap.PsimapError as e:
        sys.exit(f"objects_api: {e}")
    print(f"\nsaved {obj.name} to {args.out}: {', '.join(files)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
