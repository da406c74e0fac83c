"""psimap.panoptic: the panoptic field (paper §4), 3D-consistent label rendering, and the naive baseline.

Names are imported on first use so `import psimap.panoptic` (and the CLI's lookup of `cli_labels`)
stays cheap; torch loads only when a function runs.
"""
from __future__ import annotations

_EXPORTS = {
    "PanopticConfig": "psimap.panoptic.config",
    "PanopticField": "psimap.panoptic.field",
    "fit_panoptic": "psimap.panoptic.fit",
    "render_labels": "psimap.panoptic.labels",
    "write_labels": "psimap.panoptic.labels",
    "instance_classes": "psimap.panoptic.labels",
    "baseline_panoptic": "psimap.panoptic.baseline",
    "write_coco_panoptic": "psimap.panoptic.coco",
}

__all__ = [*_EXPORTS, "cli_labels"]


def cli_labels(opts) -> int:
    """`psimap labels scene.ckpt DATA --out DIR` (see psimap.panoptic.labels.cli_labels)."""
    from psimap.panoptic.labels import cli_labels as run

    return run(opts)


def __getattr__(name):
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'psimap.panoptic' has no attribute {name!r}")
