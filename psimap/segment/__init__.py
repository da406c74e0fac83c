"""Model-free panoptic pseudo-labels for a capture without masks (`psimap segment DATA`).

frame: one frame's planes (stuff) and clusters (objects); capture: the capture-wide pass (up, floor,
depth noise), the loop over frames, the labels overlay and the contact sheet.
"""
from __future__ import annotations


def cli_segment(opts) -> int:
    from psimap.segment.capture import cli_segment as run

    return run(opts)
