"""psimap.data: posed RGB-D frames from the psimap scene folder and from real-data layouts.

`load(path)` auto-detects the layout (scene format / nerfstudio, 7-Scenes, ScanNet, Replica, TUM RGB-D,
BOP) and returns a lazily loaded `FrameSequence` of `Frame`s (`.describe()`: what was read and
assumed). Attributes are imported on first use so `import psimap.data` stays cheap.
"""
from __future__ import annotations

__all__ = ["load", "Frame", "FrameSequence", "ClassInfo", "LoadReport"]


def __getattr__(name):
    if name == "load":
        from psimap.data.loaders import load

        return load
    if name in ("Frame", "FrameSequence", "ClassInfo", "LoadReport"):
        from psimap.data import frames

        return getattr(frames, name)
    raise AttributeError(f"module 'psimap.data' has no attribute {name!r}")
