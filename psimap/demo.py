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
from psimap.io_utils import (OVERWRITE_HINT, check_file_in_marked_dir, check_output_dir, mark_output_dir,
                             read_marker, resolve_output_dir)


@dataclass
class DemoState:
    """What the stages share: the options, the output folder and each stage's results by name."""

    opts: object
    out: Path
    results: dict = field(default_factory=dict)
    failed: str = ""        # set by a stage whose check failed: the demo exits non-zero at the end

    @property
    def data_dir(self) -> Path:
        return self.out / SCENE


# what the demo writes into its folder (the folder is filled in place and never replaced as a whole)
SCENE, PREVIEW, CKPT, EVAL, EXPORT = "scene", "scene_preview.png", "scene.ckpt", "eval.json", "export"


def check_demo_dir(out: Path, *, overwrite: bool = False) -> None:
    """PsimapError (one line) unless the demo may write into `out`: absent, empty, or an earlier demo
    folder (psimap's marker), or --overwrite; and each of its outputs may replace what is there
    (psimap.io_utils rules). Checked before the first stage, so a refusal costs nothing."""
    p = resolve_output_dir(out, what="--out")
    if p.is_dir() and any(p.iterdir()) and not overwrite:
        meta = read_marker(p)
        if meta is None or meta["kind"] != "demo":
            what = "a folder psimap did not write" if meta is None else f"a psimap {meta['kind']} output"
            raise PsimapError(f"--out {out} is {what}; {OVERWRITE_HINT} (nothing of yours is deleted)")
    check_output_dir(p / SCENE, "scene", overwrite=overwrite, what="--out")
    check_output_dir(p / EXPORT, "export", overwrite=overwrite, what="--out")
    for rel in (PREVIEW, CKPT, EVAL):
        check_file_in_marked_dir(p, rel, overwrite=overwrite, what="--out")


def stage_generate(state: DemoState) -> str:
    """A synthetic scene with exact ground truth, in the scene format, under OUT/scene."""
    from psimap.data.synthetic import describe, generate

    o = state.opts
    summary = generate(state.data_dir, seed=o.seed, frames=o.frames, width=o.width, height=o.height,
                       overwrite=o.overwrite)
    state.results["generate"] = summary
    return describe(summary)


def stage_preview(state: DemoState) -> str:
    """A picture of the generated data: colour, depth, pseudo-labels and ground truth of a few frames."""
    path = state.out / PREVIEW
    write_preview(state.data_dir, path)
    mark_output_dir(state.out, "demo", [PREVIEW])
    return f"wrote {path}"


def write_preview(scene_dir: Path, png: Path, n_frames: int = 4) -> None:
    """PNG grid, one row per frame (spread over the sequence): RGB | depth | per-frame instance
    pseudo-labels | consistent GT instances."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from psimap.data import load
    from psimap.io_utils import save_figure

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
    save_figure(fig, png, dpi=90)
    plt.close(fig)


def stage_train(state: DemoState) -> str:
    """Train the surfel map (SOGMM prior, geometry, then the joint panoptic phase) -> OUT/scene.ckpt."""
    import sys

    from psimap.checkpoint import save_checkpoint
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import train

    o = state.opts
    cfg = TrainConfig(seed=o.seed)
    if getattr(o, "iters", 0):
        cfg.iters = o.iters
    if getattr(o, "panoptic_iters", -1) >= 0:
        cfg.panoptic_iters = o.panoptic_iters
    scene = train(state.data_dir, cfg, progress=sys.stderr.isatty())
    path = state.out / CKPT
    save_checkpoint(path, scene.state(), overwrite=o.overwrite)
    mark_output_dir(state.out, "demo", [CKPT])
    state.results["train"] = scene.metrics
    m = scene.metrics
    return (f"wrote {path}: {len(scene)} surfels, {m.get('queries_final', 0)} queries -> "
            f"{m.get('instances', 0)} instances, depth L1 {m['depth_l1_end'] * 100:.2f} cm")


def stage_eval(state: DemoState) -> str:
    """Geometry and panoptic metrics of the checkpoint against the generator's ground truth."""
    import json

    from psimap.metrics.evaluate import evaluate, to_json

    from psimap.io_utils import write_text_atomic

    res = evaluate(state.out / CKPT, state.data_dir)
    write_text_atomic(state.out / EVAL, to_json(res))
    mark_output_dir(state.out, "demo", [EVAL])
    state.results["eval"] = json.loads(to_json(res))
    g, p = res.get("geometry", {}), res.get("panoptic", {})
    parts = []
    if g:
        parts.append(f"F1@{g['threshold'] * 100:.0f}cm {g['f1']:.3f}, Chamfer-L1 {g['chamfer_l1'] * 100:.2f} cm")
    if p:
        parts.append(f"PQ {p['pq']:.3f} (things {p['pq_thing']:.3f}, stuff {p['pq_stuff']:.3f}), "
                     f"mIoU {p['miou']:.3f}")
    return "; ".join(parts) + f" -> {state.out / 'eval.json'}"


def stage_export(state: DemoState) -> str:
    """Per-object assets in every format + the MuJoCo simulation check -> OUT/export/."""
    from psimap.exporters.pipeline import export_scene
    from psimap.scene import load_scene

    scene = load_scene(state.out / CKPT)
    report = export_scene(scene, state.out / EXPORT, format="all", check=True, overwrite=state.opts.overwrite)
    state.results["export"] = report
    check = report.get("check", {})
    objs = report.get("objects", [])
    outcome = report["outcome"]
    if check.get("passed"):
        verdict = "passed"
    else:
        verdict = "FAILED: " + ("; ".join(check.get("failures", [])) or "see report.json")
        state.failed = "simulation check failed"
    if not outcome["passed"]:
        state.failed = state.failed or f"too few things dynamic ({outcome['summary']})"
    return (f"{outcome['summary']}\n  "
            f"{len(objs)} objects -> {state.out / 'export'} (scene.xml, scene.usda, scene.glb, report.json); "
            f"simulation check {verdict} (min contact dist {check.get('min_contact_dist', 0.0) * 1000:.2f} mm, "
            f"max drift {check.get('max_drift', 0.0) * 100:.2f} cm, {len(check.get('nudges', {}))} nudged"
            + (f", pinned static as unstable: {', '.join(check['pinned'])}" if check.get("pinned") else "") + ")")


STAGES: list[tuple[str, Callable[[DemoState], str]]] = [
    ("generate", stage_generate),
    ("preview", stage_preview),
    ("train", stage_train),
    ("eval", stage_eval),
    ("export", stage_export),
]


def run(opts) -> int:
    """Run every stage of the demo into `opts.out`; print what each wrote and its time."""
    if not opts.out:
        raise PsimapError("an output folder is required (--out DIR)")
    out = Path(opts.out)
    check_demo_dir(out, overwrite=opts.overwrite)
    mark_output_dir(out, "demo")
    state = DemoState(opts, out)
    t_all = time.perf_counter()
    for i, (name, stage) in enumerate(STAGES, 1):
        print(f"[{i}/{len(STAGES)}] {name} ...", flush=True)
        t0 = time.perf_counter()
        line = stage(state)
        print(f"[{i}/{len(STAGES)}] {name}: {time.perf_counter() - t0:.1f} s\n  {line}", flush=True)
    if state.failed:
        # every stage still ran and wrote its outputs (the report says why); the exit code tells
        # scripts the scene is not simulation-ready
        print(f"psimap demo: {state.failed} (outputs under {out.resolve()}); "
              f"{time.perf_counter() - t_all:.1f} s", flush=True)
        return 2
    print(f"psimap demo: done in {time.perf_counter() - t_all:.1f} s; outputs under {out.resolve()}")
    return 0
