"""psimap.exporters: from a trained checkpoint to per-object, simulation-ready assets.

One module per step (DESIGN.md data flow): instance meshes (TSDF) -> repair -> completion ->
decimation -> UV + texture -> collision geometry + mass -> MJCF / USD / GLB writers.
Installed as `psimap.exporters` (never as a top-level `exporters`).
"""
