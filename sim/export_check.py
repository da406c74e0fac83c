"""`psimap check OUT`: settle an export folder again, in MuJoCo (scene.xml) and / or Newton
(scene.usda), reading it only.

The export already ran the MuJoCo check with its nudges and pins; here nothing is nudged
(check_mjcf with resolve=False: a penetration is a failure, not a fix) and no file in the folder is
written, so a folder checked twice, or checked after a user edited it, reads the same.
"""
from __future__ import annotations

import json
from pathlib import Path

from psimap import PsimapError

ENGINES = ("mujoco", "newton")
SCENE_FILE = {"mujoco": "scene.xml", "newton": "scene.usda"}


def engines_of(engine: str) -> list[str]:
    """"mujoco" | "newton" | "all" -> the engines it names."""
    if engine == "all":
        return list(ENGINES)
    if engine not in ENGINES:
        raise PsimapError(f"unknown engine {engine!r} (choose from {', '.join(ENGINES)}, all)")
    return [engine]


def check_export(folder: str | Path, engine: str = "mujoco", *, duration: float = 2.0,
                 max_drift: float = 0.01, progress: bool = False) -> dict:
    """{engine: report} of the settle check of `folder`'s scene.xml (MuJoCo) and / or scene.usda
    (Newton); the reports have check_mjcf's shape. Reads the folder only."""
    from psimap.sim.check import check_mjcf

    folder = Path(folder)
    engines = engines_of(engine)
    if not folder.is_dir():
        raise PsimapError(f"export folder not found: {folder}")
    missing = [SCENE_FILE[e] for e in engines if not (folder / SCENE_FILE[e]).is_file()]
    if missing:
        raise PsimapError(f"{folder} holds no {' and no '.join(missing)} (psimap export --format "
                          f"{'all' if len(missing) > 1 else {'scene.xml': 'mjcf', 'scene.usda': 'usd'}[missing[0]]})")
    reports = {}
    for e in engines:
        if e == "mujoco":
            reports[e] = {"engine": "mujoco", **check_mjcf(folder / SCENE_FILE[e], duration=duration,
                                                           max_drift=max_drift, resolve=False)}
        else:
            from psimap.sim.newton_check import check_usd_newton

            reports[e] = check_usd_newton(folder / SCENE_FILE[e], duration=duration, max_drift=max_drift,
                                          progress=progress)
    return reports


def summary_line(engine: str, r: dict) -> str:
    """One line per engine: verdict, deepest contact, worst drift, speed."""
    status = "passed" if r["passed"] else "FAILED: " + "; ".join(r["failures"])
    return (f"{engine}: {status} ({r['bodies']} bodies, min contact dist {r['min_contact_dist'] * 1000:.2f} mm, "
            f"max drift {r['max_drift'] * 100:.2f} cm, {r['sim_seconds_per_wall_second']:.1f} sim s / wall s)")


def cli_check(opts) -> int:
    """`psimap check OUT [--engine mujoco|newton|all] [--json]`: exit 0 passed, 2 failed, 1 error."""
    import sys

    reports = check_export(opts.out, opts.engine, duration=opts.duration, max_drift=opts.max_drift,
                           progress=sys.stderr.isatty() and not opts.json)
    if opts.json:
        print(json.dumps(reports, indent=2, sort_keys=True))
    else:
        for e, r in reports.items():
            print(summary_line(e, r))
        if len(reports) > 1:
            a, b = reports["mujoco"]["drift"], reports["newton"]["drift"]
            common = sorted(set(a) & set(b))
            if common:
                worst = max(common, key=lambda n: abs(a[n] - b[n]))
                print(f"engines: {len(common)} resting bodies in both; the largest difference in drift is "
                      f"{worst} ({a[worst] * 100:.2f} cm in MuJoCo, {b[worst] * 100:.2f} cm in Newton)")
    return 0 if all(r["passed"] for r in reports.values()) else 2
