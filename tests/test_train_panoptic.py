"""`psimap train` trains the panoptic field jointly after the geometry schedule (by default)."""

import pytest
import torch


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    from psimap.data.synthetic import generate

    root = tmp_path_factory.mktemp("syn") / "scene"
    generate(root, seed=1, frames=10, width=64, height=48, n_objects=5)
    return root


def test_joint_panoptic_phase_writes_labels_and_prunes_queries(tiny_scene, tmp_path):
    import psimap
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import train

    scene = train(tiny_scene, TrainConfig(iters=30, panoptic_iters=70), progress=False, log=lambda m: None)
    s = scene.surfels
    n = s["means"].shape[0]
    assert s["semantic"].shape == (n, len(scene.classes))
    assert s["instance"].shape == (n, 16)
    assert torch.isfinite(s["semantic"]).all() and torch.isfinite(s["instance"]).all()
    m = scene.metrics
    assert 1 <= m["queries_final"] <= m["queries_initial"]
    assert m["queries_final"] < m["queries_initial"]          # dynamic adjustment dropped some
    ids = s["instance_id"]
    assert int(ids.max()) == m["instances"] >= 1
    # stuff surfels (floor / walls) never carry an instance id
    thing = {c["id"] for c in scene.classes if c["isthing"]}
    stuff_mask = ~torch.isin(s["semantic_id"], torch.tensor(sorted(thing)))
    assert int((ids[stuff_mask] > 0).sum()) == 0
    path = tmp_path / "scene.ckpt"
    scene.save(path)
    back = psimap.load(path)
    assert torch.equal(back.instance_ids(), ids)
    assert back.queries["feature"].shape[0] == m["queries_final"]


def test_panoptic_can_be_switched_off(tiny_scene):
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import train

    scene = train(tiny_scene, TrainConfig(iters=10, panoptic=False), progress=False, log=lambda m: None)
    assert scene.surfels["semantic"].shape[1] == 0 and "instance_id" not in scene.surfels
    assert "queries_final" not in scene.metrics
