"""Rigid camera poses for the renderer tests (imported by them; not a test module).

The renderer's analytic tests place surfels in the camera frame (identity viewmat), where a camera
rotation applied the wrong way round cannot show. `to_world` moves such a scene into the world by a
random camera-to-world pose; rendered from `viewmat(c2w)` it must give the same images exactly.
"""
from __future__ import annotations

import numpy as np
import torch


def random_c2w(seed: int, dtype=torch.float64) -> torch.Tensor:
    """A random camera-to-world pose [4, 4]: any rotation, translation within 3 m of the origin."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    c2w = np.eye(4)
    c2w[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    c2w[:3, 3] = rng.uniform(-3.0, 3.0, 3)
    return torch.tensor(c2w, dtype=dtype)


def viewmat(c2w: torch.Tensor) -> torch.Tensor:
    """World-to-camera [4, 4] of a rigid c2w [4, 4] (exact transpose, no general inverse)."""
    R, t = c2w[:3, :3], c2w[:3, 3]
    out = torch.eye(4, dtype=c2w.dtype)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def to_world(c2w: torch.Tensor, means: torch.Tensor, quats: torch.Tensor):
    """Camera-frame surfels (means [N, 3], quats [N, 4] wxyz) -> world-frame (means, quats)."""
    from scipy.spatial.transform import Rotation

    R, t = c2w[:3, :3].double(), c2w[:3, 3].double()
    means_w = means.detach().double() @ R.T + t
    q = quats.detach().double().numpy()
    rot = Rotation.from_quat(np.concatenate([q[:, 1:], q[:, :1]], axis=1)) if len(q) else None
    if rot is None:
        quats_w = torch.zeros(0, 4, dtype=torch.float64)
    else:
        xyzw = (Rotation.from_matrix(R.numpy()) * rot).as_quat()
        quats_w = torch.tensor(np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1))
    return means_w.to(means.dtype), quats_w.to(quats.dtype)
