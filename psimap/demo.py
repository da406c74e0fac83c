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


def stage_preview(state: DemoState) -> str:
    """A picture of the generated data: colour, depth, pseudo-labels and ground truth of a few frames."""
    path = state.out / "scene_preview.png"
    write_preview(state.data_dir, path)
    return f"wrote {path}"


def write_preview(scene_dir: Path, png: Path, n_frames: int = 4) -> None:
    """PNG grid, one row per frame (spread over the sequence): RGB | depth | per-frame instance
    pseudo-labels | consistent GT instances."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from psimap.data import load
    from psimap.io_utils import atomic_path

    seq = load(scene_dir)
    picks = sorted({int(i) for i in np.linspace(0, len(seq) - 1, min(n_frames, len(seq)))})
    cols = ["colour", "depth (m)", "pseudo-label instances", "ground-truth instances"]
    fig, axes = plt.subplots(len(picks), 4, figsize=(11, 2.1 * len(picks)), squeeze=False)
    rng = np.random.default_rng(0)
    palette = rng.uniform(0.15, 1.0, size=(65536, 3))
    palette[0] = 0.0
    for row, i in zip(axes, picks):
        f = seq[i]
        row[0].imshow(f.rgb)
        im = row[1].imshow(np.where(f.depth > 0, f.depth, np.nan), cmap="viridis")
        fig.colorbar(im, ax=row[1], fraction=0.046)
        for ax, lab in ((row[2], f.instance), (row[3], f.gt_instance)):
            ax.imshow(palette[lab] if lab is not None else np.zeros_like(f.rgb))
        row[0].set_ylabel(f.name, fontsize=8)
    for ax, c in zip(axes[0], cols):
        ax.set_title(c, fontsize=9)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    with atomic_path(png) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)


STAGES: list[tuple[str, Callable[[DemoState], str]]] = [
    ("generate", stage_generate),
    ("preview", stage_preview),
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
