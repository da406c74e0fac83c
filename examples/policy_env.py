"""MJCF for policy training: an exported scene.xml + a free-floating two-finger gripper, as a
Gymnasium-style environment, and a scripted push and grasp that show contacts, friction and masses.

    python examples/policy_env.py EXPORT_DIR              # a `psimap export` folder (scene.xml)
    python examples/policy_env.py                         # builds a small table-top export first (seconds)
    python examples/policy_env.py EXPORT_DIR --object box_7 --steps 400 --image env.png

The scene is loaded with `mujoco.MjSpec` and the gripper added in code (no robot assets, nothing
downloaded): a palm on a free joint, welded to a mocap body that the actions move, and two fingers
on slide joints whose position actuators squeeze with at most `grip_force` newtons. Everything the
export wrote stays as it is (classes, names, masses, frictions, the static world).

`PolicyEnv` follows Gymnasium's API (reset(seed) -> obs, info; step(action) -> obs, reward,
terminated, truncated, info) and works without Gymnasium; when it is importable the env is a
`gymnasium.Env` with proper `action_space` / `observation_space`.
- reset: every dynamic object is put back on its support at its exported place (settle-checked by
  psimap export), turned by a random yaw about its vertical axis through its centre of mass and
  shifted by up to `jitter` metres; an object that then penetrates anything (contacts after
  mj_forward deeper than 1 mm, the export check's tolerance) is drawn again, and left at its
  exported pose after 20 draws. The gripper is parked above the task's object.
- action [5] in -1..1: gripper translation (x, y, z, times max_move metres per step), yaw (times
  max_turn radians), grip (-1 open .. 1 closed).
- observation: object positions [N, 3] and quaternions [N, 4] (w, x, y, z; centres of mass, world
  frame, Z-up), gripper [5] (x, y, z, yaw, finger opening in metres), and with image=True a camera
  image [H, W, 3] (mujoco.Renderer; MUJOCO_GL=egl is chosen below before mujoco is imported).
- task: move `target` to `goal` (the target's reset place pushed `push_distance` along the
  direction with the most free room on its support); reward = progress towards the goal (m) per
  step; terminated when within 2 cm of it, or when the target fell off its support (reward -1);
  truncated after max_steps.
"""
from __future__ import annotations

import os

# Offscreen images need an OpenGL backend, chosen once at mujoco's first import: EGL (headless).
os.environ.setdefault("MUJOCO_GL", "egl")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

try:
    import gymnasium
    from gymnasium import spaces
    _Base = gymnasium.Env
except ImportError:         # the env works without Gymnasium: no spaces, same API
    gymnasium = spaces = None
    _Base = object

# the gripper (metres, kilograms, newtons)
FINGER_HALF = np.array([0.012, 0.005, 0.04])    # finger box half sizes: x wide, y thick, z long
PALM_HALF = np.array([0.02, 0.085, 0.012])
FINGER_GAP = 0.006                               # finger centre from the palm's axis when closed
MAX_OPEN = 0.065                                 # finger travel: inner gap 2*(0.006+0.065-0.005) = 13 cm
FINGER_Z = -(PALM_HALF[2] + FINGER_HALF[2])      # finger centre below the palm centre
REACH = -FINGER_Z + FINGER_HALF[2]               # palm centre to fingertips
FINGER_FRICTION = 1.0                            # rubber pads; MuJoCo takes the larger of two geoms' friction
GRIP_FORCE = 2.5                                 # squeeze per finger: holds 2 * 1.0 * 2.5 / 9.81 = 0.51 kg
MAX_PENETRATION = 1e-3                           # psimap's settle check tolerance (sim/check.py)


def yaw_quat(yaw: float) -> np.ndarray:
    """[4] (w, x, y, z) rotation by `yaw` radians about +z."""
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(a, np.float64), np.asarray(b, np.float64))
    return out


def add_gripper(spec, park: np.ndarray, grip_force: float = GRIP_FORCE) -> None:
    """Add to `spec` a mocap body `gripper_target` and a free-floating two-finger gripper welded to
    it (palm `gripper`, fingers `gripper_finger_left/right` on slide joints with position actuators
    `gripper_left/right` whose force is capped at grip_force). The palm's local x is the pushing
    direction, its local y the closing direction, the fingers hang along -z. Gravity-compensated:
    the weld carries it, never its weight."""
    spec.worldbody.add_body(name="gripper_target", mocap=True, pos=park)
    palm = spec.worldbody.add_body(name="gripper", pos=park, gravcomp=1.0)
    palm.add_freejoint(name="gripper_free")
    # group 1: drawn by default and colliding; the export's visuals are group 2, colliders group 3
    palm.add_geom(name="gripper_palm", type=mujoco.mjtGeom.mjGEOM_BOX, size=PALM_HALF, mass=0.4,
                  rgba=[0.25, 0.25, 0.28, 1], group=1, friction=[FINGER_FRICTION, 0.005, 0.0001])
    palm.add_camera(name="gripper_cam", pos=[0, 0, -0.02], fovy=70)     # looks down between the fingers
    for side, sign in (("left", 1.0), ("right", -1.0)):
        f = palm.add_body(name=f"gripper_finger_{side}", pos=[0, sign * FINGER_GAP, FINGER_Z], gravcomp=1.0)
        f.add_joint(name=f"gripper_{side}_slide", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, sign, 0],
                    range=[0, MAX_OPEN], damping=2.0)
        f.add_geom(name=f"gripper_finger_{side}", type=mujoco.mjtGeom.mjGEOM_BOX, size=FINGER_HALF, mass=0.05,
                   rgba=[0.85, 0.45, 0.1, 1], group=1, friction=[FINGER_FRICTION, 0.005, 0.0001])
        act = spec.add_actuator(name=f"gripper_{side}", target=f"gripper_{side}_slide",
                                trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=400.0, kv=10.0)
        act.ctrlrange = [0, MAX_OPEN]
        act.forcerange = [-grip_force, grip_force]
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
    weld = spec.add_equality(name="gripper_weld", type=mujoco.mjtEq.mjEQ_WELD, name1="gripper_target",
                             name2="gripper", objtype=mujoco.mjtObj.mjOBJ_BODY)
    # anchor at the palm's origin and relpose all zeros (MuJoCo then takes it from the initial,
    # coincident poses), as MJCF's <weld> defaults give: MjSpec's default data puts the anchor 1 m
    # off along y, and the gripper then lagged the target by centimetres and never lifted
    weld.data[:10] = 0.0


def collider_points(model, data, body: int) -> np.ndarray:
    """World points [P, 3] on the colliders of `body`: mesh vertices, box corners, cylinder rims,
    sphere extremes (what the scripted policies measure objects by)."""
    out = []
    for g in range(model.ngeom):
        if model.geom_bodyid[g] != body or not (model.geom_contype[g] or model.geom_conaffinity[g]):
            continue
        R, t, size = data.geom_xmat[g].reshape(3, 3), data.geom_xpos[g], model.geom_size[g]
        kind = model.geom_type[g]
        if kind == mujoco.mjtGeom.mjGEOM_MESH:
            m = model.geom_dataid[g]
            local = model.mesh_vert[model.mesh_vertadr[m]:model.mesh_vertadr[m] + model.mesh_vertnum[m]]
        elif kind == mujoco.mjtGeom.mjGEOM_BOX:
            local = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * size
        elif kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
            a = np.linspace(0, 2 * np.pi, 24, endpoint=False)
            rim = np.stack([np.cos(a), np.sin(a)], 1) * size[0]
            local = np.concatenate([np.column_stack([rim, np.full(24, z)]) for z in (-size[1], size[1])])
        else:
            local = np.concatenate([np.eye(3), -np.eye(3)]) * size[0]
        out.append(np.asarray(local, np.float64) @ R.T + t)
    return np.concatenate(out) if out else data.xipos[body][None].copy()


def penetrations(model, data, bodies) -> dict[int, float]:
    """{body: deepest penetration (m)} over the contacts of the current state (after mj_forward)
    deeper than MAX_PENETRATION that involve one of `bodies`."""
    out: dict[int, float] = {}
    for i in range(data.ncon):
        c = data.contact[i]
        if c.dist >= -MAX_PENETRATION:
            continue
        for b in (int(model.geom_bodyid[c.geom1]), int(model.geom_bodyid[c.geom2])):
            if b in bodies:
                out[b] = max(out.get(b, 0.0), -float(c.dist))
    return out


@dataclass
class Task:
    target: str                 # the object's body name
    direction: np.ndarray       # [2] unit push direction (world xy)
    start: np.ndarray           # [3] its centre of mass at reset
    goal: np.ndarray            # [3] where the task wants it


class PolicyEnv(_Base):
    """A psimap export + a mocap-driven two-finger gripper (module docstring: reset, action,
    observation, task). export_dir: the folder with scene.xml."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}

    def __init__(self, export_dir: str | Path, *, target: str | None = None, image: bool = False,
                 camera: str | None = None, width: int = 160, height: int = 120, control_dt: float = 0.02,
                 max_steps: int = 500, max_move: float = 0.005, max_turn: float = 0.05,
                 grip_force: float = GRIP_FORCE, jitter: float = 0.02, push_distance: float = 0.08):
        xml = Path(export_dir) / "scene.xml"
        if not xml.is_file():
            raise ValueError(f"no scene.xml in {export_dir} (give a `psimap export` folder)")
        spec = mujoco.MjSpec.from_file(str(xml))
        self.home_model = spec.compile()            # the export as written: the object placements
        home = mujoco.MjData(self.home_model)
        mujoco.mj_forward(self.home_model, home)
        free = [int(self.home_model.jnt_bodyid[j]) for j in range(self.home_model.njnt)
                if self.home_model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
        if not free:
            raise ValueError(f"{xml} has no dynamic object (no freejoint)")
        self.objects = [mujoco.mj_id2name(self.home_model, mujoco.mjtObj.mjOBJ_BODY, b) for b in free]
        names = {n: b for n, b in zip(self.objects, free)}
        if target is not None and target not in names:
            raise ValueError(f"no dynamic object {target!r} in {xml} (have: {', '.join(self.objects)})")
        self.target = target or self._central_object(home, names)
        park = self._park(home, names[self.target])
        add_gripper(spec, park, grip_force)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.body = {n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) for n in self.objects}
        self.qadr = {n: int(m.jnt_qposadr[m.body_jntadr[b]]) for n, b in self.body.items()}
        self.home_qpos = {n: home.qpos[int(self.home_model.jnt_qposadr[self.home_model.body_jntadr[b]]):][:7].copy()
                          for n, b in names.items()}
        self.gripper = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "gripper")
        self.gripper_q = int(m.jnt_qposadr[m.body_jntadr[self.gripper]])
        self.fingers = [int(m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"gripper_{s}_slide")])
                        for s in ("left", "right")]
        self.finger_bodies = {mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"gripper_finger_{s}")
                              for s in ("left", "right")} | {self.gripper}
        self.mocap = int(m.body_mocapid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "gripper_target")])
        self.park = park
        self.substeps = max(1, int(round(control_dt / m.opt.timestep)))
        self.max_steps, self.max_move, self.max_turn = max_steps, max_move, max_turn
        self.jitter, self.push_distance = jitter, push_distance
        self.image, self.width, self.height = image, width, height
        self.camera = camera if camera is not None else (
            "overview" if mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, "overview") >= 0 else None)
        self._renderer = None
        self.render_mode = "rgb_array"
        self.yaw = 0.0
        self.steps = 0
        self.task: Task | None = None
        self.np_random = np.random.default_rng()
        if spaces is not None:
            n = len(self.objects)
            obs = {"object_pos": spaces.Box(-np.inf, np.inf, (n, 3), np.float64),
                   "object_quat": spaces.Box(-1.0, 1.0, (n, 4), np.float64),
                   "gripper": spaces.Box(-np.inf, np.inf, (5,), np.float64)}
            if image:
                obs["image"] = spaces.Box(0, 255, (height, width, 3), np.uint8)
            self.observation_space = spaces.Dict(obs)
            self.action_space = spaces.Box(-1.0, 1.0, (5,), np.float32)

    # ------------------------------------------------------------------ set-up helpers
    def _central_object(self, data, names: dict) -> str:
        """The dynamic object nearest the scene's centre (<statistic>): the one a viewer looks at."""
        centre = self.home_model.stat.center
        return min(names, key=lambda n: float(np.linalg.norm(data.xipos[names[n]] - centre)))

    def _park(self, data, body: int) -> np.ndarray:
        """Where the gripper waits: above `body`, its fingertips 15 cm over the object's top."""
        pts = collider_points(self.home_model, data, body)
        return np.array([*data.xipos[body][:2], pts[:, 2].max() + 0.15 + REACH])

    # ------------------------------------------------------------------ Gymnasium API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Objects back on their supports with a random yaw (module docstring), gripper parked and
        open; returns (observation, info). info["redraws"]: objects drawn again for penetrating,
        info["kept_home"]: objects left at their exported pose, info["min_contact_dist"]."""
        if seed is not None:
            self.np_random = np.random.default_rng(seed)
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        self._park_gripper()
        redraws, kept = 0, []
        todo = list(self.objects)
        for _ in range(20):
            for n in todo:
                self._place(n, self.np_random.uniform(-np.pi, np.pi), self.np_random.uniform(-1, 1, 2) * self.jitter)
            mujoco.mj_forward(m, d)
            bad = penetrations(m, d, {self.body[n] for n in self.objects})
            todo = [n for n in self.objects if self.body[n] in bad]
            if not todo:
                break
            redraws += len(todo)
        for n in todo:                      # 20 draws penetrated: the export's own, checked pose
            self._place(n, 0.0, np.zeros(2))
            kept.append(n)
        mujoco.mj_forward(m, d)
        self.steps = 0
        self.task = self._make_task()
        self._last_distance = self._distance()
        info = self._info()
        info.update(redraws=redraws, kept_home=kept)
        return self._obs(), info

    def step(self, action):
        a = np.clip(np.asarray(action, np.float64).reshape(5), -1.0, 1.0)
        m, d = self.model, self.data
        d.mocap_pos[self.mocap] = d.mocap_pos[self.mocap] + a[:3] * self.max_move
        self.yaw += a[3] * self.max_turn
        d.mocap_quat[self.mocap] = yaw_quat(self.yaw)
        d.ctrl[:] = (1.0 - (a[4] + 1.0) / 2.0) * MAX_OPEN
        for _ in range(self.substeps):
            mujoco.mj_step(m, d)
        self.steps += 1
        dist = self._distance()
        reward = self._last_distance - dist
        self._last_distance = dist
        fell = d.xipos[self.body[self.task.target]][2] < self.task.start[2] - 0.05
        terminated = bool(dist < 0.02 or fell)
        if fell:
            reward = -1.0
        truncated = self.steps >= self.max_steps
        info = self._info()
        info["fell"] = bool(fell)
        return self._obs(), float(reward), terminated, bool(truncated), info

    def render(self):
        """The camera image [H, W, 3] uint8 (camera `overview` of the export, else MuJoCo's free
        camera framed by <statistic>)."""
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.model, self.height, self.width)
        self._renderer.update_scene(self.data, camera=self.camera if self.camera is not None else -1)
        return self._renderer.render()

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    # ------------------------------------------------------------------ internals
    def _park_gripper(self) -> None:
        d = self.data
        self.yaw = 0.0
        d.mocap_pos[self.mocap], d.mocap_quat[self.mocap] = self.park, yaw_quat(0.0)
        d.qpos[self.gripper_q:self.gripper_q + 7] = [*self.park, 1, 0, 0, 0]
        d.ctrl[:] = MAX_OPEN
        for q in self.fingers:
            d.qpos[q] = MAX_OPEN

    def _place(self, name: str, yaw: float, shift: np.ndarray) -> None:
        """Object `name` at its exported pose turned by `yaw` about the vertical through its centre
        of mass (so its lowest point stays on the support) and moved by `shift` [2] (m)."""
        q = self.qadr[name]
        home = self.home_qpos[name]
        self.data.qpos[q:q + 3] = home[:3] + [shift[0], shift[1], 0.0]
        self.data.qpos[q + 3:q + 7] = quat_mul(yaw_quat(yaw), home[3:])

    def _make_task(self) -> Task:
        b = self.body[self.target]
        u = self.push_direction(self.target, self.push_distance)
        start = self.data.xipos[b].copy()
        return Task(self.target, u, start, start + np.array([*u * self.push_distance, 0.0]))

    def push_direction(self, name: str, distance: float) -> np.ndarray:
        """[2] unit direction (8 candidates) in which object `name` can be pushed `distance` and
        stay on its support, with the most free room ahead of it and behind it (for the fingers):
        horizontal rays at finger height (2 cm over its bottom) and downward rays along the path."""
        m, d = self.model, self.data
        b = self.body[name]
        pts = collider_points(m, d, b)
        com = d.xipos[b]
        bottom = pts[:, 2].min()
        groups = np.array([1, 1, 0, 1, 0, 0], np.uint8)      # colliders (0, 1, 3), not the visuals (2)
        hit = np.zeros(1, np.int32)
        best, best_score = np.array([1.0, 0.0]), -np.inf
        for a in np.linspace(0, 2 * np.pi, 8, endpoint=False):
            u = np.array([np.cos(a), np.sin(a)])
            half = float(((pts[:, :2] - com[:2]) @ u).max())
            origin = np.array([com[0], com[1], bottom + 0.02])

            def free(v):
                dist = mujoco.mj_ray(m, d, origin, np.array([*v, 0.0]), groups, 1, b, hit)
                return np.inf if dist < 0 else dist
            ahead, behind = free(u) - half - distance, free(-u) - half - 0.05
            supported = all(0 <= mujoco.mj_ray(m, d, np.array([*(com[:2] + u * s), bottom + 0.01]),
                                               np.array([0.0, 0.0, -1.0]), groups, 1, b, hit) <= 0.03
                            for s in np.arange(0.0, distance + 0.01, 0.01))
            score = min(ahead, behind) if supported else -1e6 + min(ahead, behind)
            if score > best_score:
                best, best_score = u, score
        return best

    def _distance(self) -> float:
        return float(np.linalg.norm(self.data.xipos[self.body[self.task.target]][:2] - self.task.goal[:2]))

    def _obs(self) -> dict:
        d = self.data
        obs = {"object_pos": np.array([d.xipos[self.body[n]] for n in self.objects]),
               "object_quat": np.array([d.xquat[self.body[n]] for n in self.objects]),
               "gripper": np.array([*d.xpos[self.gripper], self.yaw,
                                    sum(d.qpos[q] for q in self.fingers) + 2 * FINGER_GAP - 2 * FINGER_HALF[1]])}
        if self.image:
            obs["image"] = self.render()
        return obs

    def _info(self) -> dict:
        m, d = self.model, self.data
        touching = set()
        for i in range(d.ncon):
            c = d.contact[i]
            b1, b2 = int(m.geom_bodyid[c.geom1]), int(m.geom_bodyid[c.geom2])
            if b1 in self.finger_bodies and b2 not in self.finger_bodies:
                touching.add(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b2))
            elif b2 in self.finger_bodies and b1 not in self.finger_bodies:
                touching.add(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b1))
        dists = [float(d.contact[i].dist) for i in range(d.ncon)]
        return {"target": self.task.target, "goal": self.task.goal.copy(), "distance": self._distance(),
                "contacts": int(d.ncon), "min_contact_dist": min(dists) if dists else 0.0,
                "gripper_touches": sorted(touching)}


# ---------------------------------------------------------------------- scripted policies

def move_to(env: PolicyEnv, pos, grip: float, max_steps: int, tol: float = 0.002, yaw: float | None = None,
            settle: int = 0) -> int:
    """Step `env` with actions that bring the mocap target to `pos` [3] (and `yaw`) at most max_move
    per step, holding `grip`; then `settle` more steps. Returns the steps taken."""
    n = 0
    while n < max_steps:
        delta = np.asarray(pos, np.float64) - env.data.mocap_pos[env.mocap]
        turn = 0.0 if yaw is None else float(np.angle(np.exp(1j * (yaw - env.yaw))))
        if np.linalg.norm(delta) < tol and abs(turn) < 1e-3:
            break
        env.step([*np.clip(delta / env.max_move, -1, 1), np.clip(turn / env.max_turn, -1, 1), grip])
        n += 1
    for _ in range(settle):
        env.step([0, 0, 0, 0, grip])
    return n + settle


def scripted_push(env: PolicyEnv, max_steps: int = 400) -> dict:
    """Push the task's target along task.direction by env.push_distance with the closed fingers
    (a 2.4 cm wide pusher, its tips 2 cm over the object's bottom). Returns the target's displacement
    along the push and sideways (m), every other object's displacement, steps and wall time."""
    t0, task = time.perf_counter(), env.task
    m, d = env.model, env.data
    b = env.body[task.target]
    pts = collider_points(m, d, b)
    u = task.direction
    half = float(((pts[:, :2] - d.xipos[b][:2]) @ u).max())
    before = {n: d.xipos[env.body[n]].copy() for n in env.objects}
    z = pts[:, 2].min() + 0.02 + REACH                          # palm height: fingertips 2 cm up
    back = d.xipos[b][:2] - u * (half + 0.03 + FINGER_HALF[0])
    yaw = float(np.arctan2(u[1], u[0]))
    steps = move_to(env, [*back, env.park[2]], 1, max_steps, yaw=yaw)
    steps += move_to(env, [*back, z], 1, max_steps - steps)
    ahead = back + u * (0.03 + env.push_distance)
    steps += move_to(env, [*ahead, z], 1, max_steps - steps, settle=25)
    steps += move_to(env, [*ahead, env.park[2]], 1, max_steps - steps, settle=25)
    moved = d.xipos[b] - before[task.target]
    others = {n: float(np.linalg.norm(d.xipos[env.body[n]] - p)) for n, p in before.items() if n != task.target}
    return {"object": task.target, "along": float(moved[:2] @ u), "sideways": float(abs(moved[0] * u[1] - moved[1] * u[0])),
            "others": others, "steps": steps, "wall_s": time.perf_counter() - t0}


def scripted_grasp(env: PolicyEnv, name: str, lift: float = 0.1, max_steps: int = 400) -> dict:
    """Grasp object `name` across its narrowest horizontal width (the fingers' closing axis along
    the minor axis of its colliders' footprint), squeeze with the gripper's capped force, lift by
    `lift` and hold. Returns how far the object rose (m), its width, steps and wall time."""
    t0 = time.perf_counter()
    m, d = env.model, env.data
    b = env.body[name]
    pts = collider_points(m, d, b)
    xy = pts[:, :2] - pts[:, :2].mean(0)
    w, v = np.linalg.eigh(xy.T @ xy)
    across = v[:, 0]                                    # the footprint's narrow axis
    width = float(np.ptp(xy @ across))
    yaw = float(np.arctan2(across[1], across[0])) - np.pi / 2     # palm's local y (closing) along it
    centre = pts[:, :2].mean(0)
    bottom, top = pts[:, 2].min(), pts[:, 2].max()
    tips = max(bottom + 0.015, top - 2 * FINGER_HALF[2] + 0.01)
    z0 = d.xipos[b][2]
    steps = move_to(env, [*centre, env.park[2]], -1, max_steps, yaw=yaw)
    steps += move_to(env, [*centre, tips + REACH], -1, max_steps - steps)
    steps += move_to(env, [*centre, tips + REACH], 1, max_steps - steps, settle=30)    # close
    steps += move_to(env, [*centre, tips + REACH + lift], 1, max_steps - steps, settle=50)
    return {"object": name, "width": width, "lift": float(d.xipos[b][2] - z0),
            "mass_kg": float(m.body_subtreemass[b]), "steps": steps, "wall_s": time.perf_counter() - t0}


# ---------------------------------------------------------------------- a small export, built here

def tiny_export(out: Path) -> Path:
    """A table-top export made through psimap's API in seconds: a static table with a cracker box,
    a book of the same shape (3.5 times as dense), a can on it and a toy on the floor."""
    import trimesh

    from psimap.exporters.objects import build_object
    from psimap.exporters.pipeline import export_scene

    def box(ext, at):
        return trimesh.creation.box(extents=ext).apply_translation(at)

    items = [(box([0.8, 0.6, 0.4], [0, 0, 0.2]), "table", (150, 110, 70)),
             (box([0.16, 0.07, 0.1], [-0.085, -0.12, 0.45]), "box", (210, 60, 40)),
             (box([0.16, 0.07, 0.1], [0.085, -0.12, 0.45]), "book", (40, 90, 200)),
             (trimesh.creation.cylinder(radius=0.033, height=0.12, sections=32).apply_translation([0.0, 0.15, 0.46]),
              "can", (200, 200, 60)),
             (box([0.1, 0.1, 0.1], [0.7, 0.3, 0.05]), "toy", (60, 180, 90))]
    objs = []
    for i, (mesh, label, rgb) in enumerate(items):
        mesh.visual.vertex_colors = [*rgb, 255]
        objs.append(build_object(mesh, label, i + 1, completion="none"))
    export_scene(objs, out, "mjcf")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("export", nargs="?", help="a `psimap export` folder (default: build a small one)")
    ap.add_argument("--steps", type=int, default=400, help="most control steps per scripted run (50 per second)")
    ap.add_argument("--object", help="the object to push (default: the one nearest the scene's centre)")
    ap.add_argument("--seeds", type=int, default=5, help="resets checked for penetration")
    ap.add_argument("--grasp", help="object to grasp and lift (default, for the built scene: box then book)")
    ap.add_argument("--image", help="save the overview camera's image after the push to this PNG")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    tmp = None
    if args.export is None:
        tmp = tempfile.TemporaryDirectory(prefix="psimap-policy-")
        export = tiny_export(Path(tmp.name) / "export")
        print(f"built a table-top export in {time.perf_counter() - t0:.1f} s: {export}")
    else:
        export = Path(args.export)
    try:
        env = PolicyEnv(export, target=args.object, max_steps=args.steps, image=False)
    except ValueError as e:
        sys.exit(f"policy_env: {e}")
    m = env.model
    print(f"{len(env.objects)} dynamic objects, gripper added; {m.nbody} bodies, {m.ngeom} geoms, "
          f"{m.nu} actuators; gymnasium: {'yes' if spaces is not None else 'no (plain API)'}")
    print(f"{'object':<18}{'mass kg':>9}{'friction':>9}")
    for n in env.objects:
        b = env.body[n]
        fr = max((m.geom_friction[g][0] for g in range(m.ngeom) if m.geom_bodyid[g] == b and m.geom_contype[g]),
                 default=0.0)
        print(f"{n:<18}{m.body_subtreemass[b]:>9.3f}{fr:>9.2f}")
    for s in range(args.seeds):
        _, info = env.reset(seed=s)
        print(f"reset seed {s}: min contact dist {info['min_contact_dist'] * 1000:+.2f} mm, "
              f"{info['redraws']} redraw(s), kept at the exported pose: {info['kept_home'] or 'none'}")
    env.reset(seed=0)
    push = scripted_push(env, args.steps)
    print(f"push {push['object']} {env.push_distance * 100:.0f} cm along ({env.task.direction[0]:+.2f}, "
          f"{env.task.direction[1]:+.2f}): moved {push['along'] * 100:.1f} cm along, {push['sideways'] * 100:.1f} cm "
          f"sideways; others moved at most {max(push['others'].values(), default=0) * 100:.2f} cm "
          f"({push['steps']} steps, {push['wall_s']:.2f} s)")
    if args.image:
        from PIL import Image

        env.close()                         # a renderer of the new size
        env.width, env.height = 640, 480
        try:
            Image.fromarray(env.render()).save(args.image)
            print(f"image: {args.image}")
        except Exception as e:              # no EGL / OSMesa here: the numbers above still stand
            print(f"(no image: {type(e).__name__}: {e})")
    grasps = [args.grasp] if args.grasp else (["box_2", "book_3"] if tmp is not None else [])
    for name in grasps:
        env.reset(seed=0)
        g = scripted_grasp(env, name, max_steps=args.steps)
        print(f"grasp {name} ({g['mass_kg']:.3f} kg, {g['width'] * 100:.1f} cm wide) with {GRIP_FORCE} N per finger: "
              f"lifted {g['lift'] * 100:.1f} cm of 10 ({g['steps']} steps, {g['wall_s']:.2f} s)")
    env.close()
    print(f"done in {time.perf_counter() - t0:.1f} s")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
