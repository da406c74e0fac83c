"""Offscreen pictures of an MJCF scene in MuJoCo (`mujoco.Renderer`), drawn in a child process.

Why a child process: MuJoCo picks its OpenGL backend (MUJOCO_GL: glfw, egl, osmesa) once, when
mujoco is first imported, and the export's settle check has imported it already (with the default,
glfw, which needs a display; setting MUJOCO_GL for the whole process would also decide PyOpenGL's
platform for the user's own code). A child started with MUJOCO_GL=egl, or osmesa when EGL fails,
renders whatever the parent did, and a GL driver that crashes costs the picture, never the export.
Measured on the demo export (14 objects, 2 busy CPU cores, Mesa's llvmpipe): the child costs about
1.0 s of CPU (0.15 s importing mujoco, 0.3 s loading the model, 0.5 s drawing), overlapped with the
writers (exporters/pipeline.py).

    start_render(xml, job, out_npz) -> PendingRender;  .result() -> (arrays | None, backend or why not)

The job (plain JSON): `tint` {body name: [r, g, b]} (the bodies pictured: their visual geoms,
group 2, drawn flat in that colour in the scene views), `sink` {geom name: metres} (drawn that much
lower: a floor plane under a reconstructed floor lying on it would show through in patches),
`views` [{name, poses: {body: [x, y, z, qw, qx, qy, qz]} of free bodies, or null: as the file has
them}], `width` / `height` of a view, `thumb_px` (side of each body's own picture; 0 = none),
`azimuth` / `elevation` (degrees), `labels` (bool). The camera frames the tinted bodies' box as
they stand in the first view. The arrays (.npz): per view `<name>` [H, W, 3] uint8 (and, with
`labels`, `<name>_body` [H, W] int16: index into `bodies`, -1 for anything else), per body
`thumb_<i>` [S, S, 3] uint8 (that body alone, in its own materials) and `thumb_<i>_mask` [S, S]
bool, and `bodies` (names).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

BACKENDS = ("egl", "osmesa")
# MUJOCO_GL values that mean "no OpenGL at all"
OFF = ("disable", "disabled", "off", "false", "0")
# a child that fails for want of GL says so on this exit code (anything else is a crash)
NO_GL_EXIT = 3


def backends() -> list[str]:
    """The backends to try, in order: the user's MUJOCO_GL first when it names one, then EGL, then
    OSMesa; none when MUJOCO_GL turns OpenGL off."""
    own = os.environ.get("MUJOCO_GL", "").lower().strip()
    if own in OFF:
        return []
    return list(dict.fromkeys([own] * bool(own) + list(BACKENDS)))


class PendingRender:
    """A render running in a child process (started by `start_render`); `result()` waits for it and
    tries the next backend when one has no OpenGL here."""

    def __init__(self, job_file: Path, out: Path, timeout: float):
        self.job_file, self.out, self.timeout = job_file, out, timeout
        self.todo = backends()
        self.why: list[str] = [] if self.todo else [f"MUJOCO_GL={os.environ.get('MUJOCO_GL')} turns OpenGL off"]
        self.t0 = time.perf_counter()
        self.proc = self._spawn() if self.todo else None

    def _spawn(self):
        env = {**os.environ, "MUJOCO_GL": self.todo[0]}
        # PyOpenGL reads its platform at import too; mujoco.egl / osmesa set it when it is unset
        env.pop("PYOPENGL_PLATFORM", None)
        return subprocess.Popen([sys.executable, "-m", "psimap.sim.render", str(self.job_file), str(self.out)],
                                env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def cancel(self) -> None:
        """Stop the child (the export failed meanwhile); nothing when it is done."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate()

    def result(self) -> tuple[dict | None, str]:
        """(arrays, the backend that drew them) or (None, why there are none: one line)."""
        while self.proc is not None:
            backend = self.todo.pop(0)
            try:
                _, err = self.proc.communicate(timeout=max(1.0, self.timeout - (time.perf_counter() - self.t0)))
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.communicate()
                self.why.append(f"{backend}: no picture within {self.timeout:.0f} s")
                break
            if self.proc.returncode == 0:
                with np.load(self.out) as z:
                    return {k: z[k] for k in z.files}, backend
            lines = [ln.strip() for ln in err.strip().splitlines() if ln.strip()]
            self.why.append(f"{backend}: {lines[-1] if lines else f'exit {self.proc.returncode}'}")
            self.proc = self._spawn() if self.todo else None
        return None, "no offscreen OpenGL for MuJoCo (" + "; ".join(self.why) + ")"


def start_render(xml: str | Path, job: dict, out: str | Path, *, timeout: float = 120.0) -> PendingRender:
    """Start drawing `job` (module docstring) of the MJCF at `xml` in a child process; the arrays go
    to `out` (.npz) and the job next to it as JSON."""
    out = Path(out)
    job_file = out.with_suffix(".json")
    job_file.write_text(json.dumps({**job, "xml": str(xml)}))
    return PendingRender(job_file, out, timeout)


# ---- the child -------------------------------------------------------------------------------

def _geom_boxes(model, data, geoms: list[int]) -> np.ndarray:
    """World axis-aligned box [2, 3] around `geoms` (their local boxes, turned)."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
    for g in geoms:
        c, h = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
        corners = (c + signs * h) @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g]
        lo, hi = np.minimum(lo, corners.min(0)), np.maximum(hi, corners.max(0))
    return np.stack([lo, hi])


def _framing(model, box: np.ndarray, aspect: float, azimuth: float, elevation: float):
    """A free camera looking at the box's centre from (azimuth, elevation), as near as it can be
    with all eight corners of the box inside the view (and a 5 % margin)."""
    import mujoco

    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = box.mean(0)
    cam.azimuth, cam.elevation = azimuth, elevation
    a, e = np.radians(azimuth), np.radians(elevation)
    forward = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    signs = np.array(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")).reshape(3, -1).T
    corners = np.where(signs, box[1], box[0]) - box.mean(0)
    tan_v = np.tan(np.radians(model.vis.global_.fovy) / 2) / 1.05
    tan_h = tan_v * aspect
    # a corner at depth z (along the view) beyond the centre fits when |x| <= (distance + z) tan
    need = np.maximum(np.abs(corners @ right) / tan_h, np.abs(corners @ up) / tan_v) - corners @ forward
    cam.distance = max(float(need.max()), 0.05)
    # a near plane in proportion to the distance keeps the depth buffer's precision on the objects
    model.vis.map.znear = 0.02 * cam.distance / max(model.stat.extent, 1e-9)
    return cam


def _set_poses(model, data, poses: dict | None) -> None:
    import mujoco

    mujoco.mj_resetData(model, data)
    for name, pose in (poses or {}).items():
        b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        j = model.body_jntadr[b] if b >= 0 else -1
        if j >= 0 and model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            adr = model.jnt_qposadr[j]
            data.qpos[adr:adr + 7] = pose
    mujoco.mj_forward(model, data)


def draw(job: dict) -> dict[str, np.ndarray]:
    """The child's work (module docstring); needs a MuJoCo with an offscreen backend."""
    import mujoco

    model = mujoco.MjModel.from_xml_path(job["xml"])
    data = mujoco.MjData(model)
    names = [n for n in job["tint"] if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) >= 0]
    body_ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in names]
    visual = {b: [g for g in range(model.ngeom) if model.geom_bodyid[g] == b and model.geom_group[g] == 2]
              for b in body_ids}
    for n, dz in job.get("sink", {}).items():
        g = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, n)
        if g >= 0 and model.geom_bodyid[g] == 0:
            model.geom_pos[g, 2] -= dz
    matid0, rgba0 = model.geom_matid.copy(), model.geom_rgba.copy()
    index = np.full(model.ngeom + 1, -1, np.int16)       # geom id (+1, so -1 = nothing) -> body index
    for i, b in enumerate(body_ids):
        index[np.array(visual[b], int) + 1] = i

    # light that never adds up past white: a clipped face loses its tint's hue (the writers' headlight
    # plus a sun take a lit top face to 1.7x its colour)
    model.vis.headlight.ambient[:], model.vis.headlight.diffuse[:] = 0.45, 0.35
    model.vis.headlight.specular[:] = 0.0
    model.light_diffuse[:], model.light_specular[:], model.light_ambient[:] = 0.2, 0.0, 0.0
    # a 1024-texel shadow map instead of 4096: 40 % of the software renderer's time on the demo
    # room, and shadows a few pixels softer at 800 x 600
    model.vis.quality.shadowsize = 1024
    w, h, s = int(job["width"]), int(job["height"]), int(job.get("thumb_px", 0))
    model.vis.global_.offwidth, model.vis.global_.offheight = max(w, s), max(h, s)
    opt = mujoco.MjvOption()             # groups 0-2 shown: floor, visuals; 3 (colliders) hidden
    out: dict[str, np.ndarray] = {"bodies": np.array(names, dtype=str)}
    az, el = float(job.get("azimuth", 135.0)), float(job.get("elevation", -35.0))

    def shot(renderer, cam, labels: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        renderer.update_scene(data, camera=cam, scene_option=opt)
        rgb = renderer.render().copy()
        if not labels:
            return rgb, None
        renderer.enable_segmentation_rendering()
        seg = renderer.render()
        renderer.disable_segmentation_rendering()
        geom = np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)
        return rgb, index[geom + 1]

    views = job["views"]
    _set_poses(model, data, views[0]["poses"] if views else None)
    tinted = [g for b in body_ids for g in visual[b]]
    everything = _geom_boxes(model, data, tinted) if tinted else \
        np.stack([model.stat.center - model.stat.extent / 2, model.stat.center + model.stat.extent / 2])
    cam = _framing(model, everything, w / h, az, el)
    with mujoco.Renderer(model, h, w) as r:
        for b, name in zip(body_ids, names):
            for g in visual[b]:
                model.geom_matid[g] = -1
                model.geom_rgba[g] = [*job["tint"][name], 1.0]
        for v in views:
            _set_poses(model, data, v["poses"])
            out[v["name"]], who = shot(r, cam, bool(job.get("labels")))
            if who is not None:
                out[v["name"] + "_body"] = who
    if s:
        model.geom_matid[:], model.geom_rgba[:] = matid0, rgba0
        _set_poses(model, data, views[0]["poses"] if views else None)
        with mujoco.Renderer(model, s, s) as r:
            for i, b in enumerate(body_ids):
                if not visual[b]:
                    continue
                model.geom_group[:] = 5          # this body's visual geoms alone (5: a group never shown)
                model.geom_group[visual[b]] = 2
                rgb, who = shot(r, _framing(model, _geom_boxes(model, data, visual[b]), 1.0, az, el + 5.0))
                out[f"thumb_{i}"], out[f"thumb_{i}_mask"] = rgb, who == i
    return out


def _main(argv: list[str]) -> int:
    job_file, out = Path(argv[0]), Path(argv[1])
    job = json.loads(job_file.read_text())
    try:
        import mujoco

        mujoco.GLContext(1, 1).free()    # no OpenGL here: say so on NO_GL_EXIT, the parent tries the next
    except Exception as e:
        print(f"{type(e).__name__}: {' '.join(str(e).split())}", file=sys.stderr)
        return NO_GL_EXIT
    arrays = draw(job)
    tmp = out.with_name(out.stem + ".part.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, out)
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
