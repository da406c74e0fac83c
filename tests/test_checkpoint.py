"""Checkpoint schema: round trip, atomic write, refusal to save NaN, clear errors for bad files."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import psimap
from psimap import PsimapError
from psimap.checkpoint import FORMAT, VERSION, build_state, load_checkpoint, save_checkpoint


def _surfels(n=50, seed=0, S=3, F=4):
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g)
    return {"means": torch.randn(n, 3, generator=g), "quats": q / q.norm(dim=1, keepdim=True),
            "scales": torch.rand(n, 2, generator=g) * 0.05 + 0.01,
            "opacities": torch.rand(n, generator=g) * 0.9 + 0.05, "colors": torch.rand(n, 3, generator=g),
            "semantic": torch.randn(n, S, generator=g), "instance": torch.randn(n, F, generator=g)}


def _cams(m=2):
    K = torch.tensor([[100.0, 0, 40], [0, 100, 30], [0, 0, 1]], dtype=torch.float64).expand(m, 3, 3)
    return {"K": K.clone(), "c2w": torch.eye(4, dtype=torch.float64).expand(m, 4, 4).clone(),
            "width": 80, "height": 60, "names": [f"f{i}" for i in range(m)]}


CLASSES = [{"id": 1, "name": "floor", "isthing": False}, {"id": 5, "name": "chair", "isthing": True},
           {"id": 7, "name": "table", "isthing": True}]


def test_round_trip_and_load(tmp_path):
    s = _surfels()
    state = build_state(s, classes=CLASSES, cameras=_cams(), config={"iters": 3, "lr": np.float32(0.5)},
                        metrics={"loss": torch.tensor(0.25)})
    p = save_checkpoint(tmp_path / "scene.ckpt", state)
    assert not list(tmp_path.glob(".*tmp*"))          # no temporary left behind
    back = load_checkpoint(p)
    assert back["format"] == FORMAT and back["version"] == VERSION
    for k in s:
        assert torch.equal(back["surfels"][k], s[k].float())
    assert back["config"] == {"iters": 3, "lr": 0.5} and back["metrics"] == {"loss": 0.25}
    scene = psimap.load(p)
    assert len(scene) == 50 and scene.cameras["names"] == ["f0", "f1"]
    # semantic ids: argmax column j -> j-th class id of the table
    expect = torch.tensor([1, 5, 7])[s["semantic"].argmax(1)]
    assert torch.equal(scene.semantic_ids(), expect)
    assert torch.equal(scene.instance_ids(), torch.zeros(50, dtype=torch.int64))  # no queries


def test_instance_ids_from_queries():
    s = _surfels(n=4, F=2)
    s["means"] = torch.tensor([[0.0, 0, 0], [0.05, 0, 0], [5, 0, 0], [100, 0, 0]])
    s["instance"] = torch.tensor([[5.0, 0], [5, 0], [0, 5], [5, 0]])
    q = {"feature": torch.tensor([[5.0, 0], [0, 5]]), "mean": torch.tensor([[0.0, 0, 0], [5, 0, 0]]),
         "cov": torch.eye(3).expand(2, 3, 3) * 0.25}
    scene = psimap.scene.Scene(s, queries=q)
    # far surfel (100 m) has a tiny geometric affinity -> 0
    assert scene.instance_ids().tolist() == [1, 1, 2, 0]


def test_hard_labels_win():
    s = _surfels(n=5)
    s["instance_id"] = torch.arange(5)
    s["semantic_id"] = torch.full((5,), 7)
    scene = psimap.scene.Scene(s, classes=CLASSES)
    assert scene.instance_ids().tolist() == [0, 1, 2, 3, 4]
    assert scene.semantic_ids().tolist() == [7] * 5


def test_refuses_to_save_nan(tmp_path):
    s = _surfels()
    s["means"][3, 1] = float("nan")
    with pytest.raises(PsimapError, match="means.*NaN"):
        psimap.checkpoint.save_scene_checkpoint(tmp_path / "x.ckpt", s)
    assert not (tmp_path / "x.ckpt").exists()
    state = build_state(_surfels())
    state["surfels"]["colors"][0, 0] = float("inf")
    with pytest.raises(PsimapError, match="refusing to save"):
        save_checkpoint(tmp_path / "y.ckpt", state)
    assert list(tmp_path.iterdir()) == []


def test_bad_shapes_rejected():
    s = _surfels()
    s["scales"] = s["scales"][:, :1]
    with pytest.raises(PsimapError, match="scales"):
        build_state(s)
    s = _surfels()
    s["scales"][0, 0] = -1.0
    with pytest.raises(PsimapError, match="> 0"):
        build_state(s)


def test_truncated_file(tmp_path):
    p = save_checkpoint(tmp_path / "a.ckpt", build_state(_surfels(2000)))
    data = p.read_bytes()
    for cut in (len(data) // 2, len(data) - 30, 10):
        bad = tmp_path / f"cut{cut}.ckpt"
        bad.write_bytes(data[:cut])
        with pytest.raises(PsimapError, match=r"truncated or corrupt|not a psimap"):
            load_checkpoint(bad)
    (tmp_path / "empty.ckpt").write_bytes(b"")
    with pytest.raises(PsimapError, match="empty"):
        psimap.load(tmp_path / "empty.ckpt")


def test_foreign_files(tmp_path):
    (tmp_path / "text.ckpt").write_text("hello, I am not a checkpoint\n")
    with pytest.raises(PsimapError, match="not a psimap"):
        load_checkpoint(tmp_path / "text.ckpt")
    torch.save({"state_dict": {"w": torch.zeros(3)}}, tmp_path / "model.pt")
    with pytest.raises(PsimapError, match="not a psimap scene checkpoint"):
        load_checkpoint(tmp_path / "model.pt")

    class Evil:  # pickled code must never be executed
        def __reduce__(self):
            return (print, ("pwned",))
    torch.save({"format": FORMAT, "x": Evil()}, tmp_path / "evil.ckpt")
    with pytest.raises(PsimapError, match="unsafe or foreign"):
        load_checkpoint(tmp_path / "evil.ckpt")
    with pytest.raises(PsimapError, match="no such"):
        load_checkpoint(tmp_path / "missing.ckpt")


def test_newer_version_and_nan_on_disk(tmp_path):
    state = build_state(_surfels())
    state["version"] = VERSION + 1
    torch.save(state, tmp_path / "new.ckpt")
    with pytest.raises(PsimapError, match="newer"):
        load_checkpoint(tmp_path / "new.ckpt")
    state = build_state(_surfels())
    state["surfels"]["opacities"][0] = float("nan")
    torch.save(state, tmp_path / "nan.ckpt")
    with pytest.raises(PsimapError, match="opacities.*NaN"):
        load_checkpoint(tmp_path / "nan.ckpt")


def test_scene_from_meshes_labels_and_density():
    import trimesh

    box = trimesh.creation.box((0.4, 0.4, 0.4))
    box.apply_translation((0, 0, 0.2))
    floor = trimesh.creation.box((2.0, 2.0, 0.02))
    floor.apply_translation((0, 0, -0.01))
    scene = psimap.scene.scene_from_meshes([floor, box], [0, 3], [1, 5], CLASSES, spacing=0.02,
                                           colors=[(0.2, 0.2, 0.2), None])
    iid, sid = scene.instance_ids(), scene.semantic_ids()
    n_box = int((iid == 3).sum())
    # roughly one surfel per spacing^2 of area (even sampling keeps within a factor of ~2)
    assert 0.4 * box.area / 0.02**2 < n_box < 1.2 * box.area / 0.02**2
    assert torch.equal(sid[iid == 3], torch.full((n_box,), 5))
    assert bool((sid[iid == 0] == 1).all())
    means = scene.surfels["means"].double().numpy()
    # every box surfel lies on the box surface and its normal (quat z-axis) matches the face normal
    _, dist, tri = trimesh.proximity.closest_point(box, means[iid.numpy() == 3])
    assert dist.max() < 1e-6
    from scipy.spatial.transform import Rotation
    q = scene.surfels["quats"].double().numpy()[iid.numpy() == 3]
    normals = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()[:, :, 2]
    assert np.abs((normals * box.face_normals[tri]).sum(1)).min() > 0.999
    assert torch.allclose(scene.surfels["colors"][iid == 0], torch.tensor([0.2, 0.2, 0.2]).expand(
        int((iid == 0).sum()), 3))


def test_scene_from_meshes_spacing_from_cameras():
    import trimesh

    sphere = trimesh.creation.icosphere(3, 0.5)
    cams = _cams(1)
    cams["c2w"][0, 2, 3] = -2.0      # camera 2 m away on -z, looking +z
    scene = psimap.scene.scene_from_meshes([sphere], [1], [5], CLASSES, cams)
    # 2 pixels at the median nearest distance (1.5..2.5 m) with f = 100 px
    assert 0.025 < scene.config["spacing"] < 0.05
