"""Settle check of an exported USD scene in Newton (the Warp-based engine that reads UsdPhysics), on CPU.

The same test as `psimap.sim.check.check_mjcf`, in a second engine reading the other file:
1. Load `scene.usda` with `newton.ModelBuilder.add_usd` (rigid bodies from RigidBodyAPI + MassAPI,
   colliders from CollisionAPI prims, convexHull approximations as convex meshes, visual meshes as
   non-colliding shapes); a failed load is a PsimapError.
2. Initial penetration: Newton's collision pipeline at t = 0; the signed separation of every contact
   that involves a body (two static colliders never meet, as in MuJoCo) must be >= -max_penetration.
   Nothing is nudged: the USD is written after the MuJoCo check's nudges, so it already stands where
   the MJCF does; a penetration here is a disagreement between the engines, reported as a failure.
3. Settle: `duration` seconds of XPBD; the verdict (resting bodies' drift <= max_drift, unsupported
   bodies must not fall, no NaN, no explosion) is `check.settle_verdict`, the one the MuJoCo check uses.

Names are the USD prim names (= the MJCF body names). Newton and Warp are the optional extra
`pip install 'psimap[newton]'`; they are imported only here, when a check runs.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from psimap import PsimapError
from psimap.sim.check import settle_verdict

MISSING = "the Newton check needs the optional extra: pip install 'psimap[newton]'"


def require_newton():
    try:
        import warp as wp

        # Warp announces itself, its missing CUDA driver and every kernel it compiles at info and
        # warning level: a check's report is the output here
        wp.config.log_level = max(int(wp.config.log_level), int(wp.LOG_ERROR))
        _init_quietly(wp)
        import newton
        import newton_usd_schemas  # noqa: F401  (newton's USD importer needs it; a clear line if not)
    except ImportError:
        raise PsimapError(MISSING) from None
    return wp, newton


def _init_quietly(wp) -> None:
    """wp.init() with the process's stderr (fd 2) silenced: on a machine without a GPU, Warp's native
    code prints a CUDA-driver warning that is no news to a CPU check. A failed init still raises."""
    import os
    import sys

    sys.stderr.flush()
    saved, devnull = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        wp.init()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def load_usd_newton(path: str | Path):
    """(newton.Model on the CPU, seconds) of the USD scene at `path`; PsimapError when Newton cannot load it."""
    wp, newton = require_newton()
    path = Path(path)
    if not path.is_file():
        raise PsimapError(f"USD file not found: {path}")
    t0 = time.perf_counter()
    builder = newton.ModelBuilder()   # Z-up, like the stage (add_usd turns another up axis onto it)
    try:
        builder.add_usd(str(path))
        model = builder.finalize(device="cpu")
    except PsimapError:
        raise
    except Exception as e:       # pxr / newton raise anything from ValueError to RuntimeError
        raise PsimapError(f"Newton could not load {path}: {' '.join(str(e).split())}") from None
    return model, time.perf_counter() - t0


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate v [N, 3] by Warp quaternions q [N, 4] (x, y, z, w)."""
    u, w = q[:, :3], q[:, 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def contact_separations(model, state, contacts) -> tuple[np.ndarray, np.ndarray]:
    """(signed separation [C] in m, bodies [C, 2]) of the rigid contacts Newton found for `state`,
    only those that involve a body (-1 = the static world); negative = penetration. Newton lists
    pairs up to the shapes' contact gap apart, so positive separations are there too."""
    n = int(contacts.rigid_contact_count.numpy()[0])
    shapes = np.stack([contacts.rigid_contact_shape0.numpy()[:n], contacts.rigid_contact_shape1.numpy()[:n]], 1)
    body_of = model.shape_body.numpy()
    bodies = np.where(shapes >= 0, body_of[np.maximum(shapes, 0)], -1)
    idx = np.flatnonzero((shapes >= 0).all(axis=1) & (bodies >= 0).any(axis=1))
    bodies = bodies[idx]
    body_q = state.body_q.numpy().astype(np.float64)
    world = []
    for k, pts in enumerate((contacts.rigid_contact_point0, contacts.rigid_contact_point1)):
        p = pts.numpy()[idx].astype(np.float64)          # in the frame of the shape's body
        b = bodies[:, k]
        moving = b >= 0
        p[moving] = _rotate(body_q[b[moving], 3:], p[moving]) + body_q[b[moving], :3]
        world.append(p)
    normal = contacts.rigid_contact_normal.numpy()[idx].astype(np.float64)
    thick = (contacts.rigid_contact_margin0.numpy()[idx] + contacts.rigid_contact_margin1.numpy()[idx])
    sep = np.einsum("ij,ij->i", normal, world[1] - world[0]) - thick
    return sep, bodies


def check_usd_newton(path: str | Path, *, duration: float = 2.0, max_penetration: float = 1e-3,
                     max_drift: float = 0.01, max_speed: float = 5.0, support_gap: float = 0.005,
                     dt: float = 0.002, iterations: int = 10, progress: bool = False) -> dict:
    """Load, penetration, settle and stability check of a USD scene in Newton (CPU, XPBD, `dt`
    steps of `iterations` solver iterations). Returns a report of check_mjcf's shape (nudges always
    {}: this check reads, never writes) plus "engine": "newton", "solver", "load_s".
    progress: a tqdm bar over the steps (the first step of a fresh Warp kernel cache compiles the
    kernels: about 30 s on a CPU, once)."""
    from tqdm import tqdm

    wp, newton = require_newton()
    path = Path(path)
    model, load_s = load_usd_newton(path)
    labels = list(model.body_label)
    names = [str(lab).rsplit("/", 1)[-1] for lab in labels]
    shape_body = model.shape_body.numpy()
    collides = (model.shape_flags.numpy() & int(newton.ShapeFlags.COLLIDE_SHAPES)) != 0
    # static objects: colliders of a prim under /World that is no body, not the floor, not the environment
    static_bodies = sorted({str(lab).split("/")[2] for lab, b, c in zip(model.shape_label, shape_body, collides)
                            if c and b < 0 and str(lab).count("/") >= 3
                            and str(lab).split("/")[2] != "environment"})
    with wp.ScopedDevice("cpu"):
        state, nxt = model.state(), model.state()
        control = model.control()
        pipeline = newton.CollisionPipeline(model, deterministic=True)
        contacts = pipeline.contacts()
        pipeline.collide(state, contacts)
        sep, pair_bodies = contact_separations(model, state, contacts)
        min_dist = float(min(0.0, sep.min())) if len(sep) else 0.0
        touching = set(pair_bodies[sep <= support_gap].ravel().tolist())
        resting = [b in touching for b in range(model.body_count)]
        solver = newton.solvers.SolverXPBD(model, iterations=iterations)
        start = state.body_q.numpy()[:, :3].astype(np.float64).copy()
        steps = int(round(duration / dt))
        t0 = time.perf_counter()
        for _ in tqdm(range(steps), desc="Newton settle", unit="step", disable=not progress, leave=False):
            state.clear_forces()
            pipeline.collide(state, contacts)
            solver.step(state, nxt, control, contacts, dt)
            state, nxt = nxt, state
        wall = time.perf_counter() - t0
    end = state.body_q.numpy()[:, :3].astype(np.float64)
    nan = not (np.isfinite(state.body_q.numpy()).all() and np.isfinite(state.body_qd.numpy()).all())
    # body_qd is (linear velocity of the centre of mass in the world, angular): Newton's convention
    speeds = np.linalg.norm(state.body_qd.numpy()[:, :3], axis=1)
    verdict = settle_verdict(names, start, end, resting, min_dist, nan, speeds,
                             max_penetration=max_penetration, max_drift=max_drift, max_speed=max_speed)
    return {
        "engine": "newton",
        "solver": f"XPBD, {iterations} iterations, dt {dt:g} s",
        "loaded": True,
        "file": path.name,
        "bodies": len(names),
        "static_bodies": static_bodies,
        "duration_s": float(steps * dt),
        "min_contact_dist": min_dist,
        "penetrating": bool(min_dist < -max_penetration),
        "nudges": {},
        **verdict,
        "load_s": float(load_s),
        "sim_seconds_per_wall_second": float(steps * dt / max(wall, 1e-9)),
    }
