"""psimap.render: differentiable 2D Gaussian surfel rasterizer (math in SPEC.md).

`rasterize(...)` is the entry point; `project_surfels` is stage 1, shared by every backend.
"""
from __future__ import annotations

from psimap.render.api import rasterize
from psimap.render.output import RenderOutput
from psimap.render.project import Projected, project_surfels

__all__ = ["rasterize", "RenderOutput", "project_surfels", "Projected"]
