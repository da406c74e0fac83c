"""`psimap demo`: the whole pipeline on an embedded synthetic scene, stage by stage.

The demo is a list of stages run in order; each takes the shared `DemoState` and returns one line
saying what it wrote. Later stages (train -> export -> simulation check) are appended to `STAGES`
as they land, each reading what the earlier ones left in the state.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from psimap import PsimapError


@dataclass
class DemoState:
    """What the stages share: the options, the output folder and each stage's results by name."""

    opts: object
    out: Path
    results: dict = field(default_factory=dict)

    @property
    def data_dir(self) -> Path:
        return self.out / "scene"


def stage_generate(state: DemoState) -> str:
    """A synthetic scene with exact ground truth, in the scene format, under OUT/scene."""
    from psimap.data.synthetic import describe, generate

    o = state.opts
    summary = generate(state.data_dir, seed=o.seed, frames=o.frames, width=o.width, height=o.height)
    state.results["generate"] = summary
    return describe(summary)


STAGES: list[tuple[str, Callable[[DemoState], str]]] = [
    ("generate", stage_generate),
]


def run(opts) -> int:
    """Run every stage of the demo into `opts.out`; print what each wrote and its time."""
    if not opts.out:
        raise PsimapError("an output folder is required (--out DIR)")
    out = Path(opts.out)
    if out.exists() and not out.is_dir():
        raise PsimapError(f"--out {out} exists and is not a folder")
    state = DemoState(opts, out)
    t_all = time.perf_counter()
    for i, (name, stage) in enumerate(STAGES, 1):
        print(f"[{i}/{len(STAGES)}] {name} ...", flush=True)
        t0 = time.perf_counter()
        line = stage(state)
        print(f"[{i}/{len(STAGES)}] {name}: {time.perf_counter() - t0:.1f} s\n  {line}", flush=True)
    print(f"psimap demo: done in {time.perf_counter() - t_all:.1f} s; outputs under {out.resolve()}")
    return 0
