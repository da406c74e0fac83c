"""Simulation check of an exported MJCF scene.

1. Load with `mujoco.MjModel.from_xml_path`: a failed load is an error (PsimapError), never a warning.
2. Initial penetration: after `mj_forward`, the deepest contact (min `contact.dist`) must be
   >= -max_penetration. With `resolve=True`, penetrating free bodies are moved out along the
   contact normal by their depth (up off a support, sideways off a wall; gravity is -z), then
   bodies hovering up to `max_gap` above their support are lowered onto it (the mirror case: a
   reconstruction leaves an object's underside a voxel above the table, and it drops in the
   settle); the file is rewritten atomically and the nudges ([dx, dy, dz] metres) are reported.
3. Settle: simulate `duration` seconds; bodies resting at t = 0 (in contact) must move less than
   `max_drift`; bodies with no support within `support_gap` at t = 0 must not fall (a floating
   object is a broken scene, not a settle); no NaN; no explosion (speed or height beyond reason).
Reports simulated seconds per wall second.
"""
from __future__ import annotations

import time
import xml.etree.ElementTree as ET
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from psimap import PsimapError


def _load(path: Path):
    import mujoco

    try:
        return mujoco.MjModel.from_xml_path(str(path))
    except Exception as e:   # mujoco raises ValueError with the compiler message
        msg = " ".join(str(e).split())
        raise PsimapError(f"MuJoCo could not load {path}: {msg}") from None


def wedged_bodies(model, data, max_penetration: float) -> dict[str, list]:
    """{free body name: [depth m, name of what it is in]} for the free bodies whose deepest contact
    penetrates more than max_penetration: what the nudges could not clear (a small thing squeezed
    between static hulls and the floor goes back and forth between them). What it is in: the other
    body, or the geom when that is the world's (a static collider, the floor)."""
    import mujoco

    free = set(_free_bodies(model))
    out: dict[str, list] = {}
    for i in range(data.ncon):
        c = data.contact[i]
        depth = -float(c.dist)
        if depth <= max_penetration:
            continue
        pair = ((c.geom1, c.geom2), (c.geom2, c.geom1))
        for g, h in pair:
            b, other = int(model.geom_bodyid[g]), int(model.geom_bodyid[h])
            if b not in free:
                continue
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b)
            into = (mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, h) if other == 0 else
                    mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, other)) or f"geom {h}"
            if depth > out.get(name, [0.0])[0]:
                out[name] = [depth, into]
    return dict(sorted(out.items()))


def _free_bodies(model) -> list[int]:
    import mujoco

    out = []
    for j in range(model.njnt):
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            out.append(int(model.jnt_bodyid[j]))
    return out


def _penetrations(model, data) -> tuple[float, dict[int, float], set[int]]:
    """(min contact dist, {free body: deepest penetration (>0)}, bodies in contact)."""
    min_dist = np.inf
    per_body: dict[int, float] = {}
    touching: set[int] = set()
    for i in range(data.ncon):
        c = data.contact[i]
        min_dist = min(min_dist, float(c.dist))
        bodies = (int(model.geom_bodyid[c.geom1]), int(model.geom_bodyid[c.geom2]))
        for b in bodies:
            touching.add(b)
            if c.dist < 0:
                per_body[b] = max(per_body.get(b, 0.0), -float(c.dist))
    return (float(min_dist) if np.isfinite(min_dist) else 0.0), per_body, touching


def resolve_penetration(path: str | Path, max_penetration: float = 1e-3, max_rounds: int = 20,
                        margin: float = 2e-4, max_gap: float = 0.02) -> dict[str, list[float]]:
    """Move penetrating free bodies out along the contact normal until min contact.dist >=
    -max_penetration (`_push_out`), then lower free bodies that hover more than max_penetration and
    at most `max_gap` above their support onto it (`lower_onto_supports`).

    Rewrites `path` atomically (body `pos` attributes). Returns {body name: [dx, dy, dz], its total
    nudge in metres}.
    """
    import mujoco

    from psimap.io_utils import atomic_path

    path = Path(path)
    tree = ET.parse(path)
    bodies = {b.get("name"): b for b in tree.getroot().iter("body") if b.get("name")}
    nudges: dict[str, np.ndarray] = {}
    _push_out(tree, bodies, path, nudges, max_penetration, margin, max_rounds)
    if max_gap > 0:
        lower_onto_supports(tree, bodies, path, nudges, max_gap, min_gap=max_penetration, margin=margin,
                            max_rounds=max_rounds)
        # rays find the first contact from the body's own points; a support's corner poking up into
        # a face (an unlabelled ramp's hull under a box) is met earlier: push out of that again
        _push_out(tree, bodies, path, nudges, max_penetration, margin, max_rounds)
    nudges = {k: v for k, v in nudges.items() if float(np.abs(v).max()) > 1e-9}
    if nudges:
        with atomic_path(path) as tmp:
            tree.write(tmp, encoding="unicode")
            with open(tmp, "a") as f:
                f.write("\n")
    return {k: [float(x) for x in v] for k, v in sorted(nudges.items())}


_COS_45 = float(np.cos(np.pi / 4))


def _push_out(tree, bodies: dict, path: Path, nudges: dict[str, np.ndarray], max_penetration: float,
              margin: float, max_rounds: int) -> None:
    """Move penetrating free bodies out of their contacts until min contact.dist >= -max_penetration:
    per round each such body leaves its deepest contact by its depth + margin along the contact
    normal, or straight up (down) when that normal is within 45 degrees of vertical, so a body on a
    tilted hull face or near a table's edge is never slid sideways. Of two free bodies in contact
    the one the separation moves up leaves (the cup leaves the table under it, never the table the
    cup: lifting the support drops what it carries); side by side (a normal within 30 degrees of
    horizontal) the lighter one. A body sunk into a wall leaves it sideways (lifting it, as this
    once did, never clears a vertical face: a real capture's object touching a wall went up 20 cm
    in 2.8 mm steps and the penetration stayed). Edits `tree`, adds to `nudges`."""
    import mujoco

    for _ in range(max_rounds):
        model = _model_from_tree(tree, path)
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        min_dist, _, _ = _penetrations(model, data)
        if min_dist >= -max_penetration:
            return
        free = set(_free_bodies(model))
        moves: dict[int, tuple[float, np.ndarray]] = {}
        for i in range(data.ncon):
            c = data.contact[i]
            depth = -float(c.dist)
            if depth <= max_penetration:
                continue
            # frame[:3] is the normal from geom1 to geom2: geom2's body leaves along it
            n = np.asarray(c.frame[:3], np.float64)
            b1, b2 = int(model.geom_bodyid[c.geom1]), int(model.geom_bodyid[c.geom2])
            cands = [(b, d) for b, d in ((b1, -n), (b2, n)) if b in free]
            if not cands:
                continue
            if len(cands) == 2:
                if abs(n[2]) >= 0.5:
                    b, d = max(cands, key=lambda bd: bd[1][2])
                else:
                    b, d = min(cands, key=lambda bd: float(model.body_subtreemass[bd[0]]))
            else:
                b, d = cands[0]
            if depth > moves.get(b, (0.0, None))[0]:
                moves[b] = (depth, d)
        if not moves:
            return
        for b, (depth, d) in moves.items():
            if abs(d[2]) >= _COS_45:          # on (under) a support: clear the contact plane vertically
                d = np.array([0.0, 0.0, (1.0 if d[2] > 0 else -1.0) / abs(d[2])])
            _shift_body(bodies, mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b), (depth + margin) * d, nudges)


def _shift_body(bodies: dict, name: str, delta: np.ndarray, nudges: dict[str, np.ndarray]) -> None:
    """Move the body element `name` by delta [3] (m) and add it to its nudge."""
    el = bodies[name]
    pos = np.array([float(x) for x in el.get("pos", "0 0 0").split()]) + delta
    el.set("pos", " ".join(f"{v:.9g}" for v in pos))
    nudges[name] = nudges.get(name, np.zeros(3)) + delta


@contextmanager
def _contacts_within(model, data, gap: float):
    """mj_forward with every geom margin raised to `gap`, so `data.contact` lists the pairs closer
    than that (dist > 0 for the ones apart); the margins and the state are restored after.
    The mid-phase (a body's tree of geom boxes, built without the runtime margin) is off meanwhile:
    with it, a can whose six hulls all cleared the floor by 6 mm had no contact at a 2 cm margin."""
    import mujoco

    margin0 = model.geom_margin.copy()
    flags0 = int(model.opt.disableflags)
    model.geom_margin[:] = np.maximum(margin0, gap)
    model.opt.disableflags = flags0 | int(mujoco.mjtDisableBit.mjDSBL_MIDPHASE)
    try:
        mujoco.mj_forward(model, data)
        yield data
    finally:
        model.geom_margin[:] = margin0
        model.opt.disableflags = flags0
        mujoco.mj_forward(model, data)


def _bottom_points(model, data, g: int) -> np.ndarray:
    """World points [P, 3] on collision geom g from which a downward ray finds what is under it:
    a mesh's vertices and down-facing face centres, a primitive's corners and face/rim points."""
    import mujoco

    R, t = data.geom_xmat[g].reshape(3, 3), data.geom_xpos[g]
    size = model.geom_size[g]
    kind = model.geom_type[g]
    if kind == mujoco.mjtGeom.mjGEOM_MESH:
        mid = model.geom_dataid[g]
        va, vn = model.mesh_vertadr[mid], model.mesh_vertnum[mid]
        fa, fn = model.mesh_faceadr[mid], model.mesh_facenum[mid]
        v = model.mesh_vert[va:va + vn].astype(np.float64) @ R.T + t
        tri = v[model.mesh_face[fa:fa + fn]]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        return np.concatenate([v, tri[n[:, 2] < 0].mean(axis=1)])
    grid = np.stack(np.meshgrid(*[np.array([-1.0, 0.0, 1.0])] * 3, indexing="ij"), -1).reshape(-1, 3)
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        local = grid * size[:3]
    elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        d = grid[np.linalg.norm(grid, axis=1) > 0]
        local = size[0] * d / np.linalg.norm(d, axis=1, keepdims=True)
    elif kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
        a = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        rim = np.stack([np.cos(a), np.sin(a)], 1) * size[0]
        local = np.concatenate([np.column_stack([rim, np.full(16, z)]) for z in (-size[1], size[1])]
                               + [[[0, 0, -size[1]], [0, 0, size[1]]]])
    else:
        local = np.zeros((1, 3))
    return local @ R.T + t


def _support_gaps(model, data, free: set[int], max_gap: float) -> dict[int, list[tuple[float, int]]]:
    """{free body: [(vertical gap, body under it)]}: rays cast straight down (+z is up) from the
    lowest points of the body's colliders find what lies under it within max_gap. Rays measure
    the vertical gap exactly (MuJoCo's contact distance with an enlarged margin is approximate for
    separated convex meshes: a box lowered by its reported 18 mm gap still had 23 mm to fall)."""
    import mujoco

    mujoco.mj_forward(model, data)
    collides = (model.geom_contype != 0) | (model.geom_conaffinity != 0)
    groups = np.ones(6, np.uint8)
    groups[2] = 0           # the writers' visual meshes (no contact): a ray must see past them
    down = np.array([0.0, 0.0, -1.0])
    hit = np.zeros(1, np.int32)
    gaps: dict[int, list[tuple[float, int]]] = {}
    for b in free:
        geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == b and collides[g]]
        if not geoms:
            continue
        pts = np.concatenate([_bottom_points(model, data, g) for g in geoms])
        pts = pts[pts[:, 2] <= pts[:, 2].min() + max_gap]
        for p in pts:
            dist = mujoco.mj_ray(model, data, p, down, groups, True, b, hit)
            if 0 <= dist <= max_gap and collides[hit[0]]:
                gaps.setdefault(b, []).append((float(dist), int(model.geom_bodyid[hit[0]])))
    return gaps


def lower_onto_supports(tree, bodies: dict, path: Path, nudges: dict[str, np.ndarray], max_gap: float, *,
                        min_gap: float = 1e-3, margin: float = 2e-4, max_rounds: int = 5) -> None:
    """Lower free bodies hovering min_gap..max_gap above their support onto it (to `margin` above),
    editing `tree` and accumulating into `nudges`. A body resting on one that comes down comes down
    with it: drop(b) = min over its supports s of (own gap to s + drop(s)), static supports drop 0."""
    import mujoco

    for _ in range(max_rounds):
        model = _model_from_tree(tree, path)
        data = mujoco.MjData(model)
        free = set(_free_bodies(model))
        gaps = _support_gaps(model, data, free, max_gap)
        own = {b: [(g - margin if g > min_gap else 0.0, o) for g, o in lst] for b, lst in gaps.items()}
        drop = {b: 0.0 for b in own}
        for _ in range(len(own) + 1):       # relax along supports (an acyclic stack converges)
            new = {b: max(0.0, min(g + (drop.get(o, 0.0) if o in free else 0.0) for g, o in lst))
                   for b, lst in own.items()}
            if new == drop:
                break
            drop = new
        drop = {b: d for b, d in drop.items() if d > 1e-6}
        if not drop:
            return
        for b, d in drop.items():
            _shift_body(bodies, mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b), np.array([0.0, 0.0, -d]), nudges)


def _model_from_tree(tree, path: Path):
    import mujoco

    # write next to the original so relative asset paths resolve
    tmp = path.with_name(f".{path.stem}.resolve.xml")
    try:
        tree.write(tmp, encoding="unicode")
        return mujoco.MjModel.from_xml_path(str(tmp))
    except Exception as e:
        raise PsimapError(f"MuJoCo could not load {path} after nudging: {' '.join(str(e).split())}") from None
    finally:
        tmp.unlink(missing_ok=True)


def check_mjcf(path: str | Path, *, duration: float = 2.0, max_penetration: float = 1e-3,
               max_drift: float = 0.01, resolve: bool = True, max_speed: float = 5.0,
               support_gap: float = 0.005, max_gap: float = 0.02, settled: dict | None = None) -> dict:
    """Load, penetration, settle and stability check of an MJCF scene. Returns a plain dict report:

    loaded, bodies (free), static_bodies (names of world-welded bodies with colliders), min_contact_dist
    (m), nudges {body: [dx, dy, dz] m: out of a penetration along its contact normal, down onto a
    support up to max_gap below}, wedged {body: [depth m, what it is in]} (free bodies still
    penetrating after the nudges, `wedged_bodies`), drift {body: m} for resting bodies,
    max_drift, unsupported (bodies not in contact at t=0), fell {body: m dropped} (unsupported
    bodies that fell more than max_drift: a failure), unstable (names of the bodies that moved more
    than max_drift or fell), nan, exploded, sim_seconds_per_wall_second,
    passed, failures [str].
    settled: when given, receives {free body name: [x, y, z, qw, qx, qy, qz]}, its pose (freejoint
    qpos) after the settle (the export's preview draws it; the report keeps its shape).
    """
    import mujoco

    path = Path(path)
    if not path.is_file():
        raise PsimapError(f"MJCF file not found: {path}")
    model = _load(path)
    nudges = resolve_penetration(path, max_penetration, max_gap=max_gap) if resolve else {}
    if nudges:
        model = _load(path)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    min_dist, _, _ = _penetrations(model, data)
    wedged = wedged_bodies(model, data, max_penetration)
    # "resting" = within support_gap of something at t = 0 (a reconstruction leaves mm gaps)
    with _contacts_within(model, data, support_gap):
        _, _, touching = _penetrations(model, data)
    free = _free_bodies(model)
    # static objects (welded to the world, with colliders) are supports, never movers
    static_bodies = sorted({mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[g]))
                            for g in range(model.ngeom)
                            if model.geom_bodyid[g] > 0 and int(model.geom_bodyid[g]) not in set(free)
                            and (model.geom_contype[g] or model.geom_conaffinity[g])})
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in free]
    start = np.array([data.xpos[b].copy() for b in free]).reshape(-1, 3)
    resting = [b in touching for b in free]
    steps = int(round(duration / model.opt.timestep))
    t0 = time.perf_counter()
    for _ in range(steps):
        mujoco.mj_step(model, data)
    wall = time.perf_counter() - t0
    end = np.array([data.xpos[b].copy() for b in free]).reshape(-1, 3)
    if settled is not None:
        settled.clear()
        for n, b in zip(names, free):
            adr = model.jnt_qposadr[model.body_jntadr[b]]
            settled[n] = [float(v) for v in data.qpos[adr:adr + 7]]
    nan = not (np.isfinite(data.qpos).all() and np.isfinite(data.qvel).all())
    speeds = np.array([np.linalg.norm(data.cvel[b][3:]) for b in free]) if free and not nan else np.zeros(0)
    verdict = settle_verdict(names, start, end, resting, min_dist, nan, speeds, max_penetration=max_penetration,
                             max_drift=max_drift, max_speed=max_speed)
    return {
        "loaded": True,
        "file": path.name,
        "bodies": len(free),
        "static_bodies": static_bodies,
        "duration_s": float(steps * model.opt.timestep),
        "min_contact_dist": float(min_dist),
        "penetrating": bool(min_dist < -max_penetration),
        "wedged": wedged,
        "nudges": nudges,
        **verdict,
        "sim_seconds_per_wall_second": float(steps * model.opt.timestep / max(wall, 1e-9)),
    }


def settle_verdict(names: list[str], start: np.ndarray, end: np.ndarray, resting: list[bool], min_dist: float,
                   nan: bool, speeds: np.ndarray, *, max_penetration: float = 1e-3, max_drift: float = 0.01,
                   max_speed: float = 5.0) -> dict:
    """The settle test's criteria, one place for every engine (check_mjcf, newton_check).

    names [B], start / end [B, 3] body positions before and after the settle, resting [B] (within
    the support gap of something at t = 0), min_dist the deepest contact at t = 0 (m, < 0 =
    penetration), speeds [B] (m/s) at the end. Returns the report's drift, max_drift, unsupported,
    fell, unstable, nan, exploded, passed and failures."""
    start, end = np.asarray(start, np.float64).reshape(-1, 3), np.asarray(end, np.float64).reshape(-1, 3)
    exploded = False
    if not nan:
        exploded = bool((np.asarray(speeds) > max_speed).any() or (np.abs(end - start) > 10.0).any())
    drift = {n: float(np.linalg.norm(e - s)) for n, s, e, r in zip(names, start, end, resting) if r}
    # an object with nothing under it within support_gap falls: the scene is not what was scanned
    fell = {n: float(s[2] - e[2]) for n, s, e, r in zip(names, start, end, resting)
            if not r and not (s[2] - e[2] <= max_drift)}
    failures = []
    if fell:
        worst = max(fell, key=lambda n: fell[n])
        failures.append(f"{len(fell)} unsupported object(s) fell (worst {worst}: {fell[worst] * 100:.1f} cm)")
    if min_dist < -max_penetration:
        failures.append(f"initial penetration {-min_dist * 1000:.2f} mm > {max_penetration * 1000:.1f} mm")
    if nan:
        failures.append("NaN in the simulation state")
    if exploded:
        failures.append("simulation exploded (speed or displacement out of range)")
    moved = {n: d for n, d in drift.items() if not np.isfinite(d) or d > max_drift}
    if moved:
        worst = max(moved, key=lambda n: moved[n])
        failures.append(f"{len(moved)} resting object(s) moved more than {max_drift * 100:.1f} cm "
                        f"(worst {worst}: {moved[worst] * 100:.2f} cm)")
    return {
        "drift": dict(sorted(drift.items())),
        "max_drift": float(max(drift.values())) if drift else 0.0,
        "unsupported": sorted(n for n, r in zip(names, resting) if not r),
        "fell": dict(sorted(fell.items())),
        # bodies that did not stay where they were: resting ones that moved, unsupported ones that fell
        "unstable": sorted(set(moved) | set(fell)),
        "nan": bool(nan),
        "exploded": bool(exploded),
        "passed": not failures,
        "failures": failures,
    }
