"""psimap: panoptic 2D-Gaussian-surfel maps (the Psi-Map method) turned into simulation-ready scenes.

Heavy modules (torch, open3d, trimesh, ...) are imported lazily so that `import psimap` and
`psimap --help` stay instant.
"""
from __future__ import annotations

__version__ = "0.1.0"


class PsimapError(Exception):
    """An error caused by the user's input (bad file, wrong format, ...).

    The CLI prints it as one line and exits non-zero; no traceback unless --debug.
    """


def load(path):
    """Load a trained scene checkpoint (`scene.ckpt`) as a :class:`psimap.api.Scene` (a
    :class:`psimap.scene.Scene` with `objects()`).

    Never unpickles code: checkpoints are read with ``torch.load(weights_only=True)``.
    """
    from psimap.api import Scene

    return Scene.load(path)


__all__ = ["PsimapError", "load", "__version__"]
