"""psimap.geometry: the SOGMM geometric prior (paper §3.2) and the 4D point clouds it is fitted to.

`fit_sogmm(points) -> SOGMM`, `sample_surfels(sogmm, n)`, `SOGMMIndex`, `point_to_plane`,
`normal_alignment`, `geo_loss` (psimap.geometry.sogmm); `frames_to_points`, `backproject_frame`,
`lidar_points`, `voxel_downsample` (psimap.geometry.points); `estimate_depth_noise`, `noise_at`
(psimap.geometry.depth_noise: sensor noise sigma(z) from the depth images). Attributes are imported on first use so
`import psimap.geometry` stays cheap.
"""
from __future__ import annotations

_SOGMM = ("SOGMM", "fit_sogmm", "sample_surfels", "SOGMMIndex", "point_to_plane", "normal_alignment",
          "geo_loss")
_POINTS = ("frames_to_points", "backproject_frame", "lidar_points", "voxel_downsample", "drop_nonfinite", "rgb_to_grey")

_NOISE = ("estimate_depth_noise", "noise_at")

__all__ = list(_SOGMM + _POINTS + _NOISE)


def __getattr__(name):
    if name in _SOGMM:
        from psimap.geometry import sogmm

        return getattr(sogmm, name)
    if name in _POINTS:
        from psimap.geometry import points

        return getattr(points, name)
    if name in _NOISE:
        from psimap.geometry import depth_noise

        return getattr(depth_noise, name)
    raise AttributeError(f"module 'psimap.geometry' has no attribute {name!r}")
