"""Core data types shared by every loader: a posed RGB-D frame and a lazily loaded sequence of them.

Conventions (docs/conventions.md): world frame Z-up, metres; cameras OpenCV (x right, y down, z forward);
`c2w` is camera-to-world. Loaders convert to this at load time.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

# Frames `psimap train` uses at most (TrainConfig.max_frames), and the ones `psimap segment` labels
# by default: a 30 fps phone capture has thousands, and more views of the same room only repeat it.
TRAIN_FRAMES = 300


def evenly_spaced(count: int, most: int) -> list[int]:
    """Indices of at most `most` of `count` frames, evenly spaced from the first to the last: the
    frames training reads (psimap.train.trainer) and the ones `psimap segment` labels for it."""
    if count <= 0 or most <= 0:
        return []
    return np.unique(np.linspace(0, count - 1, min(count, most)).round().astype(int)).tolist()


class DepthSized:
    """`height` / `width` of a frame from its depth map [H, W] (numpy array or tensor)."""

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])


@dataclass
class Frame(DepthSized):
    """One posed RGB-D frame.

    rgb: [H, W, 3] float32 in [0, 1]; depth: [H, W] float32 metres, 0 = invalid;
    K: [3, 3] float64 intrinsics; c2w: [4, 4] float64 camera-to-world (OpenCV).
    semantic / instance: [H, W] integer label maps (per-frame pseudo-labels) or None.
    lidar: [N, 4] float32 (x, y, z world, intensity) or None; lidar_origin: [3] world position of
    the sensor for that sweep, or None (training then takes the camera centre).
    """

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    c2w: np.ndarray
    semantic: np.ndarray | None = None
    instance: np.ndarray | None = None
    lidar: np.ndarray | None = None
    name: str = ""                      # image file stem, used to name per-frame outputs
    gt_semantic: np.ndarray | None = None   # cross-view-consistent ground truth, when present
    gt_instance: np.ndarray | None = None
    lidar_origin: np.ndarray | None = None

    @property
    def w2c(self) -> np.ndarray:
        return np.linalg.inv(self.c2w)


@dataclass
class ClassInfo:
    id: int
    name: str
    isthing: bool


@dataclass
class LoadReport:
    """What a loader read and what it assumed, so a user sees how their files were understood
    (`FrameSequence.describe()`). Each field is one short sentence; `skipped` and `assumed` one
    entry per reason ("3 frames: pose non-finite (tracking lost)")."""

    resolution: tuple[int, int] = (0, 0)      # (W, H) of the frames as loaded
    depth: str = ""                           # how stored depth values become metres
    poses: str = ""                           # where poses come from, their convention
    intrinsics: str = ""                      # where K comes from
    labels: str = ""                          # where semantic / instance maps come from
    skipped: list[str] = field(default_factory=list)
    assumed: list[str] = field(default_factory=list)


@dataclass
class FrameSequence(Sequence):
    """A lazily loaded sequence of frames: `len(seq)`, `seq[i]` -> Frame (read from disk on access).

    `loader(i)` reads frame i. `classes` is the class table (COCO panoptic style, may be empty).
    `root` is the folder it came from; `layout` names the detected layout; `report` says what the
    loader read and assumed (`describe()`).
    """

    loader: Callable[[int], Frame]
    count: int
    classes: list[ClassInfo] = field(default_factory=list)
    root: str = ""
    layout: str = ""
    names: list[str] = field(default_factory=list)
    report: LoadReport = field(default_factory=LoadReport)

    def describe(self) -> str:
        """A few lines: layout, frame count (and skipped), resolution, depth, poses, intrinsics,
        labels, and every assumption the loader made."""
        r = self.report
        size = f", {r.resolution[0]}x{r.resolution[1]}" if r.resolution[0] else ""
        lines = [f"{self.layout or 'frames'} {self.root}: {self.count} frames{size}"]
        lines += [f"  skipped {s}" for s in r.skipped]
        for key in ("depth", "poses", "intrinsics", "labels"):
            if getattr(r, key):
                lines.append(f"  {key}: {getattr(r, key)}")
        lines += [f"  assumed: {a}" for a in r.assumed]
        return "\n".join(lines)

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(self.count))]
        if i < 0:
            i += self.count
        if not 0 <= i < self.count:
            raise IndexError(f"frame index {i} out of range (0..{self.count - 1})")
        return self.loader(i)

    def class_by_id(self) -> dict[int, ClassInfo]:
        return {c.id: c for c in self.classes}
