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


def test_train_config_takes_the_panoptic_defaults_from_panoptic_config():
    from psimap.panoptic.config import PanopticConfig
    from psimap.train.config import PANOPTIC_FIELDS, TrainConfig

    assert TrainConfig().panoptic_config() == PanopticConfig()
    for train_name, field_name in PANOPTIC_FIELDS.items():
        assert getattr(TrainConfig(), train_name) == getattr(PanopticConfig(), field_name)
    c = TrainConfig(panoptic_topk=3, panoptic_feat_dim=5, lambda_ins=0.5, lambda_sem=2.0).panoptic_config()
    assert (c.topk, c.feat_dim, c.w_ins, c.w_sem) == (3, 5, 0.5, 2.0)
    assert c.pixels_per_step == PanopticConfig().pixels_per_step      # the rest stays the default


def test_panoptic_geometry_moves_surfels_in_the_panoptic_steps_only(tiny_scene):
    """panoptic_geometry=True hands the geometry to the panoptic loop (JointGeometry): the same
    geometry schedule, then surfels that keep moving under both losses; off, they stay put."""
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import train

    runs = {}
    for joint in (False, True):
        runs[joint] = train(tiny_scene, TrainConfig(iters=20, panoptic_iters=12, panoptic_geometry=joint),
                            progress=False, log=lambda m: None)
    off, on = runs[False], runs[True]
    assert off.metrics["loss_end"] == on.metrics["loss_end"]          # geometry schedule unchanged
    assert off.surfels["means"].shape == on.surfels["means"].shape
    moved = (off.surfels["means"] - on.surfels["means"]).norm(dim=1)
    assert float(moved.max()) > 1e-4 and bool(torch.isfinite(on.surfels["means"]).all())
    assert on.metrics["panoptic_skipped_steps"] == 0
