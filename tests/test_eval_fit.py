"""`psimap eval scene.ckpt DATA` on a capture without ground truth: the map's fit to its own frames
(psimap/metrics/fit.py): depth error against the sensor, coverage, what the map adds, PSNR."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from psimap.camera import look_at
from psimap.data.frames import ClassInfo, Frame

W, H, F = 48, 36, 40.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])


@pytest.fixture(scope="module")
def scene():
    from psimap.scene import scene_from_meshes

    floor = trimesh.creation.box([2.0, 2.0, 0.02], trimesh.transformations.translation_matrix([0, 0, -0.01]))
    box = trimesh.creation.box([0.4, 0.4, 0.4], trimesh.transformations.translation_matrix([0, 0, 0.2]))
    cams = [look_at(np.array([1.4 * np.cos(a), 1.4 * np.sin(a), 1.0]), [0, 0, 0.2])
            for a in np.linspace(0, 2 * np.pi, 4, endpoint=False)]
    return scene_from_meshes([floor, box], [0, 1], [1, 2],
                             [ClassInfo(1, "floor", False), ClassInfo(2, "box", True)],
                             colors=[(0.3, 0.6, 0.3), (0.8, 0.2, 0.2)], cameras={"K": np.stack([K] * len(cams)), "c2w": np.stack(cams), "width": W,
                                      "height": H, "names": [f"f{i}" for i in range(len(cams))]},
                             spacing=0.02, seed=0)


def _frames(scene, depth_of=lambda i, d: d, rgb_noise=0.0):
    """The scene's cameras as frames, their depth and colour its own render (edited by depth_of)."""
    rng = np.random.default_rng(0)
    frames = []
    for i in range(len(scene.cameras["names"])):
        Kc, c2w, w, h = scene.camera(i)
        out = scene.render(i)
        depth = np.where(out.alpha.numpy() >= 0.5, out.median_depth.numpy(), 0).astype(np.float32)
        rgb = np.clip(out.rgb.numpy() + rgb_noise * rng.standard_normal((h, w, 3)), 0, 1).astype(np.float32)
        frames.append(Frame(rgb=rgb, depth=depth_of(i, depth).astype(np.float32), K=Kc, c2w=c2w, name=f"f{i}"))
    return frames


def test_fit_measures_depth_error_coverage_and_colour(scene):
    from psimap.metrics.fit import evaluate_fit

    own = evaluate_fit(scene, _frames(scene))
    assert own["frames"] == 4 and own["depth_mae_cm"] < 0.01 and own["depth_within_1cm"] > 0.999
    assert own["coverage"] > 0.999 and own["added"] < 0.001 and own["psnr_db"] > 60
    # the sensor 3 cm further in every other frame: half the compared pixels 3 cm off
    far = evaluate_fit(scene, _frames(scene, lambda i, d: np.where(d > 0, d + 0.03 * (i % 2), 0)))
    assert far["depth_mae_cm"] == pytest.approx(1.5, abs=0.1)
    assert far["depth_within_1cm"] == pytest.approx(0.5, abs=0.05) and far["depth_within_5cm"] > 0.999
    assert [round(r["depth_mae_cm"]) for r in far["per_frame"]] == [0, 3, 0, 3]
    # the sensor returned nothing on the left half of the images (a black surface): the map adds it
    half = evaluate_fit(scene, _frames(scene, lambda i, d: np.where(np.arange(W)[None] < W // 2, 0, d)))
    assert half["added"] == pytest.approx(0.5, abs=0.1) and half["coverage"] > 0.999
    # noisy colour: PSNR of sigma 0.05 is about 26 dB
    noisy = evaluate_fit(scene, _frames(scene, rgb_noise=0.05))
    assert 24.0 < noisy["psnr_db"] < 28.0


def test_fit_of_an_empty_map_and_of_frames_without_depth(scene):
    from psimap.metrics.fit import evaluate_fit

    blank = evaluate_fit(scene, _frames(scene, lambda i, d: np.zeros_like(d)))
    assert blank["coverage"] != blank["coverage"] and blank["depth_mae_cm"] != blank["depth_mae_cm"]   # NaN
    assert blank["added"] == pytest.approx(1.0)
    gone = scene.__class__({k: v[:0] for k, v in scene.surfels.items()}, classes=scene.classes,
                           cameras=scene.cameras, queries=scene.queries, config=scene.config)
    none = evaluate_fit(gone, _frames(scene))
    assert none["coverage"] == 0.0 and none["depth_mae_cm"] != none["depth_mae_cm"]


def test_eval_cli_reports_the_fit_without_ground_truth(scene, tmp_path, capsys):
    from psimap.cli import main
    from psimap.data.scene_format import write_scene

    data = write_scene(tmp_path / "data", _frames(scene, lambda i, d: np.where(d > 0, d + 0.02, 0)),
                       [ClassInfo(1, "floor", False), ClassInfo(2, "box", True)])
    scene.save(tmp_path / "scene.ckpt")
    assert main(["eval", str(tmp_path / "scene.ckpt"), str(data), "--json", "--plot", str(tmp_path / "fit.png")]) == 0
    fit = json.loads(capsys.readouterr().out)["fit"]
    assert fit["depth_mae_cm"] == pytest.approx(2.0, abs=0.1) and fit["depth_within_1cm"] < 0.01
    assert (tmp_path / "fit.png").stat().st_size > 1000
    assert main(["eval", str(tmp_path / "scene.ckpt"), str(data)]) == 0
    text = capsys.readouterr().out
    assert "fit to the capture" in text and "2.0" in text
