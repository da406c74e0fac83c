"""Suite-wide settings and shared fixtures."""
import psimap  # noqa: F401  (first: it sets OMP_WAIT_POLICY before torch loads libgomp)

import numpy as np
import pytest
import torch

# The suite's tensors are small: torch's intra-op thread pool only adds spin-waiting on a 2-core
# machine (a 40-step panoptic fit took 3 s on one thread and 66 s on two).
torch.set_num_threads(1)


@pytest.fixture(scope="session")
def ring_checkpoint(tmp_path_factory):
    """make(meshes, instance_ids, semantic_ids, classes, colors, target, radius, height, views) -> the
    path of a scene.ckpt of `meshes` (psimap.scene.scene_from_meshes) seen by `views` 96x72 cameras
    on a ring of `radius` at `height`, looking at `target`: a checkpoint for the export tests."""
    def make(meshes, instance_ids, semantic_ids, classes, colors, target, radius=0.7, height=0.55, views=8):
        from psimap.camera import camera_rig, look_at
        from psimap.scene import scene_from_meshes

        w, h = 96, 72
        c2ws = [look_at(np.array([radius * np.cos(a), radius * np.sin(a), height]), target)
                for a in np.linspace(0, 2 * np.pi, views, endpoint=False)]
        cams = camera_rig(c2ws, w, h, 80.0)
        scene = scene_from_meshes(meshes, instance_ids, semantic_ids, classes, cams, colors=colors)
        path = tmp_path_factory.mktemp("ckpt") / "scene.ckpt"
        scene.save(path)
        return path

    return make


@pytest.fixture
def poison_native_outputs():
    """Every native output buffer starts as NaN (-1 / max for integers), so a value a kernel leaves
    unwritten fails the test (psimap.render.native.POISON_OUTPUTS). Only where the native module is
    built: use with a skip when it is not."""
    import psimap.render.native as native

    native.POISON_OUTPUTS = True
    yield
    native.POISON_OUTPUTS = False
