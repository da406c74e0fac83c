"""psimap.completion: collision-aware completion of partially observed objects.

Installed as `psimap.completion`. Until the completion method lands this is the identity hook the
exporter calls (step 3 of the export pipeline): it returns the input unchanged with completed=False,
so reports say honestly that nothing was completed.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass
class CompletionResult:
    mesh: Any            # trimesh.Trimesh, metres, world frame
    completed: bool      # True only when geometry was actually added
    method: str          # name of the method that ran ("identity" for the hook)
    reason: str          # why it was (not) completed, one line


def complete(partial, context: dict) -> CompletionResult:
    """Complete a partially observed object mesh.

    partial: trimesh.Trimesh (metres, world frame). context: free-form hints (label, scene
    background mesh, other objects, cameras). The hook returns `partial` unchanged.
    """
    return CompletionResult(mesh=partial, completed=False, method="identity",
                            reason="completion not available yet: mesh passed through unchanged")


__all__ = ["CompletionResult", "complete"]
