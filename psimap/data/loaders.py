"""Frame loaders for real-data layouts and `load(path)` auto-detection (work in progress)."""
from __future__ import annotations

import os
from pathlib import Path

from psimap import PsimapError


def load(path: str | os.PathLike):
    """Open a scene folder; returns a lazily loaded FrameSequence."""
    from psimap.data.scene_format import TRANSFORMS, read_scene

    p = Path(path)
    if not p.exists():
        raise PsimapError(f"no such file or folder: {p}")
    if p.is_file() and p.name.endswith(".json") or (p / TRANSFORMS).is_file():
        return read_scene(p)
    raise PsimapError(f"{p}: not a recognised scene layout")
