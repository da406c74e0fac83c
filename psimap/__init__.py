"""psimap: panoptic 2D-Gaussian-surfel maps (the Psi-Map method) turned into simulation-ready scenes.

Heavy modules (torch, open3d, trimesh, ...) are imported lazily so that `import psimap` and
`psimap --help` stay instant.
"""
from __future__ import annotations

import os

__version__ = "0.1.0"

# OpenMP threads (the native renderer's; torch shares the same libgomp) sleep at once when idle
# instead of spinning: on a 2-core machine with two busy processes a training frame took 122 ms
# spinning vs 101 ms passive (idle machine: 54 vs 50 ms). libgomp reads this when it loads, so
# it takes effect when psimap is imported before torch (the CLI, and `import psimap` first); a
# value the user set is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


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
