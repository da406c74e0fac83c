"""Static-world benchmark (issue #16): do things rest, does gravity point down, are masses honest?

Scenes are built from meshes (psimap.scene.scene_from_meshes: exact geometry and hard labels, so
what is measured is the export, not training), seen like a hand-held capture: an arc of views at
1.2-1.6 m height around the area of interest.

  stuff-desk       a desk labelled with the stuff class `table` against a wall, on the floor, with a
                   box, a hollow mug (a wall around air, with a handle), a flat foam block and a ball
  unlabelled-desk  the same desk with semantic 0 (void): an unlabelled support
  y-up, z-down, colmap   stuff-desk turned into the frame of a phone (Y up), a robot base (z down)
                   and an arbitrary SfM frame: they must export the same objects with the same roles
  unseen-top       the desk's things on a counter whose top is not in the map (what a black, glossy
                   top leaves of a depth capture), seen by a robot's camera 2 cm below its edge, so
                   no view looks into the open counter either: they stand on nothing observed
  ycb-table        the six real YCB scans (../shared/data/ycb, skipped when absent) upright on a
                   stuff table, classes named after them; their xml files give the real masses
  room             a generated room (psimap.data.synthetic.generate, seed 0): its ground-truth
                   objects as things, its ground-truth mesh split into stuff by face label, the
                   generator's cameras; furniture, shelves, bottles, a chair

Per scene `export_scene(load_scene(ckpt), out, "all", completion="auto")`, timed (wall and CPU),
and from report.json: things found, dynamic / pinned / too little evidence / skipped / static
furniture (report["outcome"]), what moved or fell in the settle check, whether the check passed,
the static world's collider error (report["environment"]), faces per object, the up direction found,
the YCB masses against the real ones, and for the turned scenes whether they match stuff-desk.

    python benchmarks/static_world.py                       # all scenes, writes RESULTS.md + plot
    python benchmarks/static_world.py --quick               # smaller images, print only
    python benchmarks/static_world.py --scenes y-up room    # a subset (print only)
"""
from __future__ import annotations

import argparse
import logging
import re
import resource
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import markdown_table, save_plot, write_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
YCB = ROOT.parent / "shared" / "data" / "ycb"
YCB_NAMES = ("banana", "bowl", "cracker_box", "mug", "mustard_bottle", "power_drill")
SCENES = ("stuff-desk", "unlabelled-desk", "y-up", "z-down", "colmap", "unseen-top", "ycb-table", "room")
KEY = "static-world"

# The capture frames of the turned scenes: R takes the Z-up world to the capture's (R @ [0,0,1] is
# the capture's up). colmap: any rotation; this one tilts up by 64 degrees and turns it about z.
FRAMES = {"y-up": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
          "z-down": np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])}
COLMAP_EULER_DEG = (38.0, -57.0, 121.0)     # scipy "xyz"

DESK_TOP = 0.74
WALL_Y = 0.62            # front face of the wall behind the desk
TABLE_TOP = 0.74         # the YCB table

# image size and views: full run / --quick
FULL = dict(width=160, height=120, views=14)
QUICK = dict(width=96, height=72, views=10)


@dataclass
class Built:
    """A benchmark scene: the psimap Scene, how many things it holds, the real masses known
    {class: kg}, each such object's true mesh file {class: path}, and R [3, 3] taking the Z-up
    original to the capture's frame (identity if not turned). The true mesh is weighed on its own
    and its size compared with the export's: that tells an error of the capture (an inflated
    object) from one of the mass model."""

    scene: object
    things: int
    real_mass: dict = field(default_factory=dict)
    true_mesh: dict = field(default_factory=dict)
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))


# ---- cameras -----------------------------------------------------------------------------------
def arc_cameras(target, radius: float, angles, width: int, height: int) -> dict:
    """A hand-held capture: views on an arc of `angles` (radians about +z, 0 = from -y) at `radius`
    (m, horizontal) around target [3], their height wandering between 1.2 and 1.6 m, all looking
    at the target; a 62 degree horizontal field of view."""
    from psimap.camera import look_at

    target = np.asarray(target, np.float64)
    angles = np.asarray(angles, np.float64)
    n = len(angles)
    z = 1.4 + 0.2 * np.sin(np.linspace(0.0, 3.0 * np.pi, n))     # up and down as a hand moves
    f = 0.83 * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    c2w = [look_at(np.array([target[0] + radius * np.sin(a), target[1] - radius * np.cos(a), zi]), target)
           for a, zi in zip(angles, z)]
    return {"K": np.stack([K] * n), "c2w": np.stack(c2w), "width": int(width), "height": int(height),
            "names": [f"view_{i:02d}" for i in range(n)]}


# ---- scene builders ----------------------------------------------------------------------------
def desk_classes():
    from psimap.data.frames import ClassInfo

    return [ClassInfo(1, "floor", False), ClassInfo(2, "wall", False), ClassInfo(3, "table", False),
            ClassInfo(4, "box", True), ClassInfo(5, "mug", True), ClassInfo(6, "foam block", True),
            ClassInfo(7, "ball", True)]


def hollow_mug(radius: float = 0.042, height: float = 0.1, wall: float = 0.005):
    """A mug as a real container: an outer cylinder with a torus handle, minus the inner cylinder
    (open at the top, a floor `wall` thick). Watertight, base at z = 0."""
    import trimesh

    outer = trimesh.creation.cylinder(radius=radius, height=height, sections=48)
    outer.apply_translation([0, 0, height / 2])
    handle = trimesh.creation.torus(0.026, 0.006, major_sections=32, minor_sections=12)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    handle.apply_translation([radius + 0.008, 0, height / 2])
    inner = trimesh.creation.cylinder(radius=radius - wall, height=height, sections=48)
    inner.apply_translation([0, 0, height / 2 + wall])
    return trimesh.boolean.difference([trimesh.boolean.union([outer, handle], engine="manifold"), inner],
                                      engine="manifold")


def desk_meshes(labelled: bool = True):
    """(meshes, instance ids, semantic ids, colours) of the desk scene, world Z-up: floor, the wall
    behind the desk, the desk (top and four legs, stuff `table` or void), four things on the top."""
    import trimesh

    def box(extents, centre):
        return trimesh.creation.box(extents=extents).apply_translation(centre)

    floor = box([3.0, 2.6, 0.02], [0, 0, -0.01])
    wall = box([3.0, 0.04, 1.6], [0, WALL_Y + 0.02, 0.8])
    legs = [box([0.05, 0.05, DESK_TOP - 0.04], [x, y, (DESK_TOP - 0.04) / 2])
            for x in (-0.55, 0.55) for y in (0.05, 0.55)]
    desk = trimesh.util.concatenate([box([1.2, 0.6, 0.04], [0, 0.3, DESK_TOP - 0.02]), *legs])
    things = [
        box([0.12, 0.08, 0.07], [-0.32, 0.22, DESK_TOP + 0.035]),                     # box
        hollow_mug().apply_translation([-0.05, 0.36, DESK_TOP]),                      # mug
        box([0.16, 0.11, 0.035], [0.22, 0.18, DESK_TOP + 0.0175]),                    # foam block
        trimesh.creation.icosphere(3, radius=0.035).apply_translation([0.36, 0.42, DESK_TOP + 0.035]),
    ]
    meshes = [floor, wall, desk, *things]
    iids = [0, 0, 0, 11, 12, 13, 14]
    sids = [1, 2, 3 if labelled else 0, 4, 5, 6, 7]
    colors = [(0.45, 0.45, 0.42), (0.82, 0.8, 0.74), (0.55, 0.36, 0.2), (0.85, 0.2, 0.1),
              (0.12, 0.3, 0.85), (0.92, 0.88, 0.2), (0.2, 0.7, 0.3)]
    return meshes, iids, sids, colors


def unseen_top_scene(width: int, height: int, views: int):
    """The desk's four things on a counter (stuff `table`, the desk's footprint, floor to top) whose
    top face is not in the map, seen from an arc of views 2 cm below the top's edge."""
    import trimesh

    from psimap.camera import look_at
    from psimap.scene import scene_from_meshes

    meshes, iids, sids, colors = desk_meshes(True)
    counter = trimesh.creation.box(extents=[1.2, 0.6, DESK_TOP]).apply_translation([0, 0.3, DESK_TOP / 2])
    counter.update_faces(counter.face_normals[:, 2] < 0.9)
    counter.remove_unreferenced_vertices()
    meshes[2] = counter
    eye = DESK_TOP - 0.02
    f = 0.83 * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    angles = np.linspace(-0.9, 0.9, views)
    c2w = [look_at([1.3 * np.sin(a), 0.3 - 1.3 * np.cos(a), eye], [0.0, 0.3, eye - 0.05]) for a in angles]
    cams = {"K": np.stack([K] * views), "c2w": np.stack(c2w), "width": int(width), "height": int(height),
            "names": [f"view_{i:02d}" for i in range(views)]}
    return scene_from_meshes(meshes, iids, sids, desk_classes(), cams, colors=colors)


def desk_scene(labelled: bool, width: int, height: int, views: int):
    """The desk seen from an arc in front of it (the wall closes the back)."""
    from psimap.scene import scene_from_meshes

    meshes, iids, sids, colors = desk_meshes(labelled)
    cams = arc_cameras([0.0, 0.3, DESK_TOP], 0.9, np.linspace(-1.25, 1.25, views), width, height)
    return scene_from_meshes(meshes, iids, sids, desk_classes(), cams, colors=colors)


def colmap_rotation() -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", COLMAP_EULER_DEG, degrees=True).as_matrix()


def real_mass(name: str) -> float:
    """The mass (kg) in the YCB object's MuJoCo xml."""
    text = (YCB / f"{name}.xml").read_text()
    return float(re.search(r'<inertial[^>]*\bmass="([0-9.eE+-]+)"', text).group(1))


def ycb_placements(meshes, top: float, cells=(3, 2), cell=(0.36, 0.3), gap: float = 0.03):
    """Each mesh [k] translated onto the table top: centred (plan view) in its cell of a grid
    cells[0] x cells[1] of cell (m) around the origin, its lowest point on z = top. Raises when two
    footprints come closer than `gap` (m): the scans must not overlap."""
    placed = []
    for k, m in enumerate(meshes):
        i, j = k % cells[0], k // cells[0]
        c = np.array([(i - (cells[0] - 1) / 2) * cell[0], (j - (cells[1] - 1) / 2) * cell[1]])
        lo, hi = m.bounds
        placed.append(m.copy().apply_translation([*(c - (lo[:2] + hi[:2]) / 2), top - lo[2]]))
    for a in range(len(placed)):
        for b in range(a + 1, len(placed)):
            la, ha = placed[a].bounds[:, :2]
            lb, hb = placed[b].bounds[:, :2]
            if np.all(la - gap < hb) and np.all(lb - gap < ha):
                raise ValueError(f"YCB scans {a} and {b} overlap on the table")
    return placed


def ycb_scene(width: int, height: int, views: int):
    """The six YCB scans upright on a free-standing stuff table, seen from a 270 degree arc."""
    import trimesh

    from psimap.data.frames import ClassInfo
    from psimap.scene import scene_from_meshes

    def box(extents, centre):
        return trimesh.creation.box(extents=extents).apply_translation(centre)

    scans = [trimesh.load(YCB / n / "textured.obj", force="mesh", process=False) for n in YCB_NAMES]
    scans = ycb_placements(scans, TABLE_TOP)
    floor = box([3.2, 3.2, 0.02], [0, 0, -0.01])
    legs = [box([0.05, 0.05, TABLE_TOP - 0.04], [x, y, (TABLE_TOP - 0.04) / 2])
            for x in (-0.6, 0.6) for y in (-0.35, 0.35)]
    table = trimesh.util.concatenate([box([1.3, 0.8, 0.04], [0, 0, TABLE_TOP - 0.02]), *legs])
    classes = [ClassInfo(1, "floor", False), ClassInfo(2, "table", False)] + [
        ClassInfo(3 + k, n, True) for k, n in enumerate(YCB_NAMES)]
    meshes = [floor, table, *scans]
    iids = [0, 0] + [21 + k for k in range(len(scans))]
    sids = [1, 2] + [3 + k for k in range(len(scans))]
    colors = [(0.45, 0.45, 0.42), (0.55, 0.36, 0.2)] + [None] * len(scans)   # scans: their texture
    cams = arc_cameras([0.0, 0.0, TABLE_TOP], 0.95, np.linspace(-2.35, 2.35, views), width, height)
    return scene_from_meshes(meshes, iids, sids, classes, cams, colors=colors)


def room_scene(work: Path, width: int, height: int, views: int):
    """(scene, number of things) of the generated room, seed 0: its ground-truth objects as things
    (instance id and class from gt/instances.json), the rest of its ground-truth mesh split into stuff
    by face class, seen by the generator's own cameras."""
    import trimesh

    from psimap.data.scene_format import read_gt, read_scene
    from psimap.data.synthetic import classes, generate
    from psimap.scene import scene_from_meshes

    root = work / "room-capture"          # the generated frames; the export goes to work / "room"
    generate(root, seed=0, frames=views, width=width, height=height, progress=False)
    gt = read_gt(root)
    frames = read_scene(root)
    semantic = {r["id"]: r["semantic"] for r in gt.instances}
    meshes, iids, sids = [], [], []
    stuff = np.asarray(gt.face_instance) == 0
    for sid in np.unique(np.asarray(gt.face_semantic)[stuff]):
        faces = np.flatnonzero(stuff & (np.asarray(gt.face_semantic) == sid))
        meshes.append(gt.mesh.submesh([faces], append=True))
        iids.append(0)
        sids.append(int(sid))
    for oid, path in sorted(gt.objects.items()):
        meshes.append(trimesh.load(path, force="mesh", process=False))
        iids.append(int(oid))
        sids.append(int(semantic[oid]))
    Ks = [frames[i].K for i in range(len(frames))]
    c2ws = [frames[i].c2w for i in range(len(frames))]
    cams = {"K": np.stack(Ks), "c2w": np.stack(c2ws), "width": int(width), "height": int(height),
            "names": list(frames.names)}
    # a colour per class, so that neighbouring surfaces differ in the textures
    palette = np.random.default_rng(0).uniform(0.2, 0.9, (max(c.id for c in classes()) + 1, 3))
    colors = [tuple(palette[s]) for s in sids]
    return scene_from_meshes(meshes, iids, sids, classes(), cams, colors=colors), len(gt.objects)


def build(name: str, work: Path, *, width: int, height: int, views: int, cache: dict | None = None) -> Built:
    """Scene `name` of SCENES. cache: built scenes by name (the turned scenes turn stuff-desk's)."""
    cache = {} if cache is None else cache
    if name in cache:
        return cache[name]
    if name in ("stuff-desk", "unlabelled-desk"):
        built = Built(desk_scene(name == "stuff-desk", width, height, views), 4)
    elif name in ("y-up", "z-down", "colmap"):
        R = colmap_rotation() if name == "colmap" else FRAMES[name]
        ref = build("stuff-desk", work, width=width, height=height, views=views, cache=cache)
        built = Built(ref.scene.rotated(R), ref.things, rotation=R)
    elif name == "unseen-top":
        built = Built(unseen_top_scene(width, height, views), 4)
    elif name == "ycb-table":
        built = Built(ycb_scene(width, height, views), len(YCB_NAMES), {n: real_mass(n) for n in YCB_NAMES},
                      {n: YCB / n / "textured.obj" for n in YCB_NAMES})
    elif name == "room":
        built = Built(*room_scene(work, width, height, views))
    else:
        raise ValueError(f"unknown scene {name!r} (choose from {', '.join(SCENES)})")
    cache[name] = built
    return built


# ---- export and measure ------------------------------------------------------------------------
def cpu_seconds() -> float:
    """CPU time of this process (all its threads) and of its finished child processes."""
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


def export(built: Built, work: Path, name: str) -> tuple[dict, float, float]:
    """(report, wall s, CPU s) of exporting the scene's checkpoint in every format."""
    from psimap.exporters.pipeline import export_scene
    from psimap.scene import load_scene

    ckpt = work / f"{name}.ckpt"
    built.scene.save(ckpt)
    t, c = time.perf_counter(), cpu_seconds()
    report = export_scene(load_scene(ckpt), work / name, "all", completion="auto")
    return report, time.perf_counter() - t, cpu_seconds() - c


def up_error_deg(report: dict, R: np.ndarray) -> float:
    """Angle (degrees) between the up the export found and the capture's true up R @ +z."""
    return angle_deg(report["gravity"]["input_up"], R @ np.array([0.0, 0.0, 1.0]))


def angle_deg(a, b) -> float:
    """Angle (degrees) between vectors a [3] and b [3]; atan2, not arccos: exact near 0."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)))


def measure(name: str, built: Built, report: dict, out_dir: Path, wall: float, cpu: float) -> dict:
    """One scene's figures from its report.json (out_dir: the export folder)."""
    import trimesh

    from psimap.exporters.objects import object_from_scan

    out, chk, env = report["outcome"], report["check"], report["environment"] or {}
    objs = report["objects"]
    moved = sorted(set(chk["pinned"]) | set(chk["unstable"]))
    faces = [o["faces_after"] for o in objs] or [0]
    row = {"scene": name, "in_scene": built.things, "found": out["things"], "dynamic": out["dynamic"],
           "pinned": out["pinned"], "little_evidence": out["little_evidence"], "skipped": out["skipped"],
           "static_class": out["static_class"], "movable": out["movable"], "passed": out["passed"],
           "check_passed": chk["passed"], "moved": moved, "not_dynamic": out["not_dynamic"],
           "up_error_deg": up_error_deg(report, built.rotation),
           "env_error_mm": 1000 * env.get("error_m", float("nan")),
           "env_mean_mm": 1000 * env.get("mean_error_m", float("nan")),
           "env_coverage": env.get("coverage", float("nan")), "env_budget_mm": 1000 * env.get("budget_m", float("nan")),
           "colliders": env.get("colliders", {}), "floor_z": env.get("floor_z"),
           "faces_mean": float(np.mean(faces)), "faces_max": int(np.max(faces)),
           "faces_dynamic_max": max([o["faces_after"] for o in objs if not o["static"]] or [0]),
           "wall_s": wall, "cpu_s": cpu, "masses": [],
           "unseen": sorted(u["thing"] for u in env.get("unseen_supports", []))}
    for o in objs:
        real = built.real_mass.get(o["class"])
        if real is None:
            continue
        p = o["physics"]
        lo, hi = p["mass_range_kg"]
        mesh = trimesh.load(out_dir / o["files"]["mesh"], force="mesh", process=False)
        true = built.true_mesh[o["class"]]
        exact = object_from_scan(true, o["class"], o["instance_id"]).physics    # the same models, no capture
        row["masses"].append({"object": o["class"], "model": p["mass_model"], "key": p["density_key"],
                              "real": real, "est": p["mass_kg"], "err": p["mass_kg"] / real - 1,
                              "lo": lo, "hi": hi, "in_range": lo <= real <= hi,
                              "hull_ratio": float(mesh.convex_hull.volume /
                                                  trimesh.load(true, force="mesh", process=False).convex_hull.volume),
                              "scan_est": exact.mass, "scan_model": exact.model})
    missing = sorted(set(built.real_mass) - {m["object"] for m in row["masses"]})
    row["masses_missing"] = missing
    return row


def compare(ref: dict, rep: dict, R: np.ndarray) -> dict:
    """How a turned scene's export matches the Z-up original's. The export turns the capture by the
    smallest rotation that brings its up to +z, so the two exported worlds differ by a turn about z
    (M = rotation @ R, a yaw when up was found exactly): object centres are compared through M."""
    M = np.asarray(rep["gravity"]["rotation"], np.float64) @ R
    a = {o["name"]: o for o in ref["objects"]}
    b = {o["name"]: o for o in rep["objects"]}
    same_roles = [(n, a[n]["static"]) for n in sorted(a)] == [(n, b[n]["static"]) for n in sorted(b)]
    shared = sorted(set(a) & set(b))

    def centre(o):
        return np.asarray(o["bounds"], np.float64).mean(0)

    offsets = [float(np.linalg.norm(centre(b[n]) - M @ centre(a[n]))) for n in shared]
    masses = [abs(b[n]["physics"]["mass_kg"] / a[n]["physics"]["mass_kg"] - 1) for n in shared]
    return {"same_objects": set(a) == set(b), "same_roles": same_roles,
            "same_outcome": ref["outcome"]["dynamic"] == rep["outcome"]["dynamic"],
            "tilt_deg": angle_deg(M[:, 2], [0.0, 0.0, 1.0]),
            "yaw_deg": float(np.degrees(np.arctan2(M[1, 0], M[0, 0]))),
            "max_offset_mm": 1000 * max(offsets, default=float("nan")),
            "max_mass_diff": max(masses, default=float("nan"))}


# ---- results -----------------------------------------------------------------------------------
def _colliders(c: dict) -> str:
    return ", ".join(f"{v} {k}" for k, v in sorted(c.items())) or "-"


def tables(rows: list[dict], comparisons: dict) -> str:
    scene_rows = [[r["scene"], f"{r['found']} / {r['in_scene']}", f"{r['dynamic']} / {r['movable']}", r["pinned"],
                   r["little_evidence"], r["skipped"], r["static_class"],
                   ", ".join(r["moved"]) or "-", ", ".join(r["unseen"]) or "-",
                   "passed" if r["check_passed"] else "FAILED",
                   "passed" if r["passed"] else "FAILED", f"{r['up_error_deg']:.1f}"]
                  for r in rows]
    world_rows = [[r["scene"], f"{r['env_error_mm']:.1f}", f"{r['env_mean_mm']:.1f}", f"{r['env_budget_mm']:.0f}",
                   f"{100 * r['env_coverage']:.0f} %", _colliders(r["colliders"]),
                   "-" if r["floor_z"] is None else f"{r['floor_z']:.3f}", f"{r['faces_mean']:.0f}",
                   r["faces_max"], r["faces_dynamic_max"], f"{r['wall_s']:.1f}", f"{r['cpu_s']:.1f}"]
                  for r in rows]
    parts = ["Things (found / in the scene), dynamic (of those not static by class), and what came "
             "of the others:", "",
             markdown_table(["scene", "found", "dynamic", "pinned", "little evidence", "skipped",
                             "static furniture", "moved or fell in the check",
                             "on a slab no camera saw (environment.unseen_supports)", "check", "outcome",
                             "up error °"], scene_rows), "",
             "The static world (p95 / mean distance of the observed background to its colliders, the "
             "share within the budget, the colliders by role), faces of the exported visual meshes "
             "(mean and max over all objects; max over the dynamic ones), export time (all formats):", "",
             markdown_table(["scene", "world error p95 mm", "mean mm", "budget mm", "within budget",
                             "colliders", "floor z m", "faces mean", "faces max", "dynamic faces max",
                             "wall s", "CPU s"], world_rows)]
    if comparisons:
        parts += ["", "Turned captures against `stuff-desk` (up found, the residual tilt of the two "
                  "exported worlds, object centres compared through that turn, masses):", "",
                  markdown_table(["scene", "up error °", "same objects", "same roles", "same dynamic count",
                                  "residual tilt °", "turn about z °", "max centre offset mm",
                                  "max mass change %"],
                                 [[n, f"{next(r['up_error_deg'] for r in rows if r['scene'] == n):.2f}",
                                   _yes(c["same_objects"]), _yes(c["same_roles"]), _yes(c["same_outcome"]),
                                   f"{c['tilt_deg']:.2f}", f"{c['yaw_deg']:.0f}", f"{c['max_offset_mm']:.1f}",
                                   f"{100 * c['max_mass_diff']:.1f}"] for n, c in comparisons.items()])]
    masses = [m for r in rows for m in r["masses"]]
    if masses:
        parts += ["", f"YCB masses (real: the xml next to each scan; estimate: report.json), median |error| "
                  f"{100 * median_error(masses):.0f} %, real mass inside the reported range for "
                  f"{sum(m['in_range'] for m in masses)} of {len(masses)}. Beside it the same mass models on "
                  f"the exact scan (`object_from_scan`, no capture): median |error| "
                  f"{100 * median_error(masses, 'scan_est'):.0f} %; and the convex hull volume of the exported "
                  "mesh over the scan's (how much the capture inflated the object):", "",
                  markdown_table(["object", "mass model", "density key", "real kg", "estimate kg", "error %",
                                  "range kg", "real in range", "hull volume / scan's", "exact scan kg",
                                  "exact scan error %"],
                                 [[m["object"], m["model"], m["key"], f"{m['real']:.3f}", f"{m['est']:.3f}",
                                   f"{100 * m['err']:+.0f}", f"{m['lo']:.3f}-{m['hi']:.3f}", _yes(m["in_range"]),
                                   f"{m['hull_ratio']:.2f}", f"{m['scan_est']:.3f} ({m['scan_model']})",
                                   f"{100 * (m['scan_est'] / m['real'] - 1):+.0f}"]
                                  for m in masses])]
    missing = [f"{r['scene']}: {', '.join(r['masses_missing'])}" for r in rows if r["masses_missing"]]
    if missing:
        parts += ["", "Not exported, so not weighed: " + "; ".join(missing) + "."]
    why = [f"- {r['scene']}: " + "; ".join(f"{n}: {w}" for n, w in sorted(r["not_dynamic"].items()))
           for r in rows if r["not_dynamic"]]
    if why:
        parts += ["", "Things not dynamic, and why (report.json `outcome.not_dynamic`):", "", *why]
    return "\n".join(parts)


def median_error(masses: list[dict], key: str = "est") -> float:
    """Median |estimate / real - 1| of the mass entries (`key`: the export's or the exact scan's)."""
    return float(np.median([abs(m[key] / m["real"] - 1) for m in masses]))


def _yes(v: bool) -> str:
    return "yes" if v else "NO"


def plot(rows: list[dict]):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    masses = [m for r in rows for m in r["masses"]]
    fig, axes = plt.subplots(1, 2 if masses else 1, figsize=(11 if masses else 6, 4.2), squeeze=False)
    ax = axes[0, 0]
    x = np.arange(len(rows))
    bottom = np.zeros(len(rows))
    for key, label, colour in (("dynamic", "dynamic", "C2"), ("pinned", "pinned (moved in the check)", "C3"),
                               ("little_evidence", "static: too little evidence", "C1"),
                               ("skipped", "skipped", "0.5")):
        v = np.array([r[key] for r in rows], np.float64)
        ax.bar(x, v, bottom=bottom, color=colour, label=label)
        bottom += v
    ax.plot(x, [r["movable"] for r in rows], "k_", markersize=22, label="things to move")
    ax.set_xticks(x, [r["scene"] for r in rows], rotation=30, ha="right")
    ax.set_ylabel("things (static furniture left out)")
    ax.set_title("What came of the things")
    ax.legend(fontsize=7, loc="upper left")
    if masses:
        ax = axes[0, 1]
        real = np.array([m["real"] for m in masses])
        est = np.array([m["est"] for m in masses])
        err = np.array([[m["est"] - m["lo"] for m in masses], [m["hi"] - m["est"] for m in masses]])
        ax.errorbar(real, est, yerr=err, fmt="o", capsize=3, label="exported, its reported range")
        ax.plot(real, [m["scan_est"] for m in masses], "o", mfc="none", color="C1",
                label="same models on the exact scan")
        span = [0.7 * min(real.min(), est.min()), 1.3 * max(real.max(), (est + err[1]).max())]
        ax.plot(span, span, ":", color="grey", label="exact")
        ax.fill_between(span, np.multiply(span, 0.7), np.multiply(span, 1.3), color="grey", alpha=0.15,
                        label="±30 %")
        for m in masses:
            ax.annotate(m["object"], (m["real"], m["est"]), fontsize=7, xytext=(4, 2), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("real mass (kg, YCB xml)")
        ax.set_ylabel("exported mass (kg)")
        ax.set_title("YCB scans on a table: mass")
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    return fig


def headlines(rows: list[dict]) -> list[tuple[str, str]]:
    dyn, movable = sum(r["dynamic"] for r in rows), sum(r["movable"] for r in rows)
    worst = max(rows, key=lambda r: r["env_error_mm"])
    out = [(f"things dynamic over {len(rows)} scenes", f"{dyn} of {movable} ({100 * dyn / max(movable, 1):.0f} %)"),
           ("things pinned (moved in the settle check)", str(sum(r["pinned"] for r in rows)))]
    masses = [m for r in rows for m in r["masses"]]
    if masses:
        out.append(("YCB median |mass error| (real mass in range; same models on the exact scans)",
                    f"{100 * median_error(masses):.0f} % ({sum(m['in_range'] for m in masses)} of {len(masses)}; "
                    f"{100 * median_error(masses, 'scan_est'):.0f} %)"))
    out.append(("static-world collider error p95, worst scene",
                f"{worst['env_error_mm']:.0f} mm ({worst['scene']}; median over scenes "
                f"{np.median([r['env_error_mm'] for r in rows]):.0f} mm)"))
    return out


def print_row(r: dict) -> None:
    print(f"{r['scene']}: {r['dynamic']}/{r['movable']} dynamic, pinned {r['pinned']}, little evidence "
          f"{r['little_evidence']}, skipped {r['skipped']}, furniture {r['static_class']}; check "
          f"{'passed' if r['check_passed'] else 'FAILED'}, moved {r['moved'] or '-'}, on unseen supports "
          f"{r['unseen'] or '-'}; up error "
          f"{r['up_error_deg']:.1f} deg; world error {r['env_error_mm']:.1f} mm ({_colliders(r['colliders'])}); "
          f"faces mean {r['faces_mean']:.0f} max {r['faces_max']}; {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU",
          flush=True)
    for m in r["masses"]:
        print(f"    {m['object']}: {m['est']:.3f} kg ({m['model']}) vs real {m['real']:.3f} "
              f"({100 * m['err']:+.0f} %), range {m['lo']:.3f}-{m['hi']:.3f}; exact scan {m['scan_est']:.3f}",
              flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", nargs="+", choices=SCENES, default=list(SCENES),
                    help="run these scenes only (print only, RESULTS.md is written by a full run)")
    ap.add_argument("--quick", action="store_true", help="smaller images, fewer views; print only")
    ap.add_argument("--keep", type=Path, help="keep the checkpoints and export folders in this new folder")
    args = ap.parse_args(argv)
    # trimesh logs every even-sampling shortfall (scene_from_meshes tops those up on purpose)
    logging.getLogger("trimesh").setLevel(logging.ERROR)
    size = QUICK if args.quick else FULL
    names = [n for n in SCENES if n in args.scenes]
    if "ycb-table" in names and not YCB.is_dir():
        print(f"ycb-table: skipped, {YCB} not found (the shared YCB scans)")
        names.remove("ycb-table")
    write = not args.quick and set(args.scenes) == set(SCENES)
    with tempfile.TemporaryDirectory(prefix="psimap-static-world-") as tmp:
        work = Path(tmp) if args.keep is None else args.keep
        work.mkdir(parents=True, exist_ok=args.keep is None)
        cache, reports, rows, comparisons = {}, {}, [], {}
        for name in names:
            t = time.perf_counter()
            built = build(name, work, cache=cache, **size)
            print(f"{name}: {len(built.scene)} surfels built in {time.perf_counter() - t:.1f} s", flush=True)
            reports[name], wall, cpu = export(built, work, name)
            rows.append(measure(name, built, reports[name], work / name, wall, cpu))
            print_row(rows[-1])
            if not np.allclose(built.rotation, np.eye(3)):
                if "stuff-desk" not in reports:     # the original, to compare with
                    reports["stuff-desk"] = export(build("stuff-desk", work, cache=cache, **size), work,
                                                   "stuff-desk")[0]
                comparisons[name] = compare(reports["stuff-desk"], reports[name], built.rotation)
                print("    vs stuff-desk: " + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                                      for k, v in comparisons[name].items()), flush=True)
    body = (f"Scenes from meshes (exact geometry, hard labels), {size['width']}x{size['height']} pixels, "
            f"{size['views']} views on a hand-held arc at 1.2-1.6 m (the room: the generator's "
            f"{size['views']} views); `export_scene(load_scene(ckpt), out, \"all\", completion=\"auto\")` "
            "per scene.\n\n" + tables(rows, comparisons))
    if not write:
        print(body)
        return 0
    write_section(KEY, "Static world: things that rest, gravity, masses (issue #16)", body,
                  headlines=headlines(rows), plot=save_plot(plot(rows), KEY))
    return 0


if __name__ == "__main__":
    sys.exit(main())
