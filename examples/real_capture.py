"""A real RGB-D capture to a simulation scene: 7-Scenes frames -> segment -> train -> eval -> export -> summary.

The capture has colour, depth and poses but no masks, so `psimap segment` makes per-frame pseudo-labels
first (planes by orientation and height, then 3D clusters); the panoptic field makes them consistent
in 3D while training. The export is a MuJoCo scene (plus USD and GLB with --format all), read back in
MuJoCo for the summary and a preview image.

    python examples/real_capture.py                                   # ../shared/data/7scenes-chess
    python examples/real_capture.py --data MY_CAPTURE --out OUT --frames 60
    python examples/real_capture.py --quick                           # a few frames, few steps: minutes

Any layout `psimap train` reads works as --data (scene format, 7-Scenes, ScanNet, Replica, TUM, BOP,
nerfstudio). The capture is copied into OUT first: labels are written next to the frames, and the
example never writes into the folder you give it.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

# The preview renders offscreen: MuJoCo picks its OpenGL backend once, at the first import (the
# export's settle check imports it too), so choose EGL before anything imports mujoco.
os.environ.setdefault("MUJOCO_GL", "egl")

ROOT = Path(__file__).resolve().parents[1]
CHESS = ROOT.parent / "shared" / "data" / "7scenes-chess"


def copy_capture(src: Path, dst: Path, frames: int) -> int:
    """Copy every file of `src` into `dst`, keeping `frames` frames evenly spaced when the capture is a
    7-Scenes folder (frame-NNNNNN.*); other layouts are copied whole. Returns the frames kept."""
    from psimap.data import load

    seq = load(src)
    dst.mkdir(parents=True, exist_ok=True)
    if seq.layout != "7scenes":
        shutil.copytree(src, dst, dirs_exist_ok=True)
        return len(seq)
    step = max(1, len(seq) // max(frames, 1))
    keep = set(seq.names[::step][:frames])
    for p in src.iterdir():
        stem = p.name.split(".")[0]
        if p.is_file() and (not stem.startswith("frame-") or stem in keep):
            shutil.copy2(p, dst / p.name)
    return len(keep)


def psimap_cli(*args: str, ok=(0,)) -> int:
    """Run one psimap command in this process; exit unless its status is in `ok`."""
    from psimap.cli import main

    print("$ psimap " + " ".join(args), flush=True)
    t = time.perf_counter()
    rc = main(list(args))
    if rc not in ok:
        sys.exit(f"psimap {args[0]} failed (exit {rc})")
    print(f"  ({time.perf_counter() - t:.0f} s)", flush=True)
    return rc


def summary(export: Path) -> str:
    """One line per exported object and the static world, from report.json."""
    rep = json.loads((export / "report.json").read_text())
    lines = [f"{'object':<22}{'class':<12}{'role':<9}{'mass kg':>8}  {'collider':<14}{'faces':>6}"]
    for o in rep["objects"]:
        if o.get("skipped"):
            continue
        role = "static" if o.get("static") else "dynamic"
        mass = (o.get("physics") or {}).get("mass_kg")
        col = (o.get("collision") or {}).get("kind", "-")
        lines.append(f"{o['name']:<22}{o['class']:<12}{role:<9}{'-' if mass is None else f'{mass:.3f}':>8}  "
                     f"{col:<14}{o.get('faces_after', 0):>6}")
    skipped = rep.get("skipped") or []
    env = rep.get("environment") or {}
    check = rep.get("check") or {}
    lines.append(f"static world: {sum((env.get('colliders') or {}).values())} colliders "
                 f"{env.get('colliders')}, floor {'seen' if env.get('floor_observed') else 'NOT seen (safety plane)'}")
    lines.append(f"MuJoCo check: {'passed' if check.get('passed') else 'FAILED ' + str(check.get('failures'))}, "
                 f"max drift {100 * (check.get('max_drift') or 0):.2f} cm over {check.get('duration_s')} s; "
                 f"{len(skipped)} instance(s) skipped")
    return "\n".join(lines)


def render_preview(export: Path, png: Path, width: int = 640, height: int = 480) -> bool:
    """The exported scene.xml as MuJoCo renders it (offscreen, EGL), from above the objects; False
    when no offscreen OpenGL is available here."""
    try:
        import mujoco
        import numpy as np
        from PIL import Image

        model = mujoco.MjModel.from_xml_path(str(export / "scene.xml"))
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        bodies = [i for i in range(1, model.nbody) if model.body_jntnum[i] > 0] or list(range(1, model.nbody))
        centre = data.xpos[bodies].mean(0) if bodies else np.zeros(3)
        spread = float(np.ptp(data.xpos[bodies], axis=0).max()) if len(bodies) > 1 else 1.0
        cam = mujoco.MjvCamera()
        cam.lookat[:] = centre
        cam.distance, cam.elevation, cam.azimuth = max(1.5 * spread, 1.0), -40.0, 135.0
        with mujoco.Renderer(model, height, width) as r:
            r.update_scene(data, camera=cam)
            Image.fromarray(r.render()).save(png)
        return True
    except Exception as e:          # no EGL / OSMesa on this machine: the summary still stands
        print(f"(no preview: {type(e).__name__}: {e})")
        return False


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(CHESS), help="the capture (any layout psimap reads)")
    ap.add_argument("--out", default="real_capture_out", help="working folder (capture copy, checkpoint, export)")
    ap.add_argument("--frames", type=int, default=50, help="frames kept from a 7-Scenes capture")
    ap.add_argument("--iters", type=int, default=0, help="training steps (0 = psimap's default)")
    ap.add_argument("--format", default="mjcf", help="export format: mjcf, usd, glb or all")
    ap.add_argument("--quick", action="store_true", help="8 frames, 150 steps: checks the pipeline, not quality")
    args = ap.parse_args(argv)
    if args.quick:
        args.frames, args.iters = 8, 150
    data, out = Path(args.data), Path(args.out)
    if not data.exists():
        sys.exit(f"no capture at {data} (pass --data)")
    capture, ckpt, export = out / "capture", out / "scene.ckpt", out / "export"
    t0 = time.perf_counter()
    n = copy_capture(data, capture, args.frames)
    print(f"copied {n} frames of {data} to {capture}")
    psimap_cli("segment", str(capture), "--force")
    train = ["train", str(capture), "--out", str(ckpt)]
    if args.iters:
        train += ["--iters", str(args.iters)]
    psimap_cli(*train)
    # no ground truth on a real capture: eval gives the map's fit to its own frames (depth error
    # against the sensor, coverage, PSNR), the one quality figure before the export
    psimap_cli("eval", str(ckpt), str(capture))
    # exit 2: written, but the settle check failed or too few things came out dynamic; the summary
    # says which (a real capture's large furniture chunks are often pinned static)
    rc = psimap_cli("export", str(ckpt), "--format", args.format, "--out", str(export), ok=(0, 2))
    print("\n" + summary(export))
    if rc == 2:
        print("note: the export's outcome check did not pass (see the first line psimap export printed)")
    png = out / "preview.png"
    if render_preview(export, png):
        print(f"preview: {png}")
    print(f"done in {time.perf_counter() - t0:.0f} s; open {export / 'scene.xml'} with `python -m mujoco.viewer`")
    return 0


if __name__ == "__main__":
    sys.exit(main())
