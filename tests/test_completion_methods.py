"""The completion method table (psimap.completion.methods): forcing one method by name (Python and
`psimap export --completion NAME`), the typed context, and a third-party method registered through
the `psimap.completion` entry-point group."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from psimap import PsimapError
from psimap.completion import CompletionContext, complete
from psimap.completion.meshops import sample_surface
from psimap.completion.methods import BUILTIN, Choices, Method, method_names, methods

VOXEL = 0.005
BOX = trimesh.creation.box([0.1, 0.06, 0.12]).apply_translation([0, 0, 0.06])


def _front_of(mesh, view=(-0.5, -1.0, 0.6)):
    """[P, 3] surface points of `mesh` facing a viewer looking along -view (front, left, top)."""
    pts = sample_surface(mesh, 0.003, seed=0)
    _, _, fid = trimesh.proximity.closest_point(mesh, pts)
    return pts[mesh.face_normals[fid] @ np.asarray(view) > 0.05]


def test_builtin_table_runs_in_tier_order():
    table = methods()
    assert [m.name for m in table] == ["plugin", "sphere", "cylinder", "box", "revolution", "closing", "mirror",
                                       "support"]
    assert [m.name for m in table if m.parametric] == ["sphere", "cylinder", "box", "revolution"]
    assert [m.name for m in table if m.adds_outliers] == ["plugin", "sphere", "cylinder", "box", "revolution"]
    assert [m.name for m in table if m.fallback] == ["support"]
    assert list(Choices()) == ["auto", "none", "sphere", "cylinder", "box", "revolution", "closing", "mirror",
                               "support"]            # the plugin hook needs a Python callable


def test_forced_method_is_used_even_when_it_fails_the_fit_test():
    pts = _front_of(BOX)
    auto = complete(None, CompletionContext(points=pts, voxel_size=VOXEL))
    assert auto.method == "box" and "rejected sphere" in auto.reason
    res = complete(None, CompletionContext(points=pts, voxel_size=VOXEL, method="sphere"))
    assert res.completed and res.method == "sphere"
    assert res.reason.startswith("sphere asked for") and "forced: only" in res.reason
    assert res.candidates["sphere"]["accepted"] and res.candidates["sphere"]["inliers"] < 0.9
    assert list(res.candidates) == ["sphere"]                         # no other method ran
    # a fully observed object is left alone in auto, completed when a method is asked for
    full = sample_surface(BOX, 0.003)
    assert complete(BOX, CompletionContext(points=full, voxel_size=VOXEL)).method == "none"
    forced = complete(BOX, CompletionContext(points=full, voxel_size=VOXEL, method="box"))
    assert forced.completed and forced.method == "box" and forced.fit_residual < 1e-3


def test_forced_method_that_cannot_run_leaves_the_object_as_observed():
    pts = _front_of(BOX)
    res = complete(None, CompletionContext(points=pts, voxel_size=VOXEL, method="plugin"))
    assert not res.completed and res.method == "none" and res.mesh is None
    assert res.reason == ("plugin (asked for) gave no closed shape that meets the constraints: "
                          "no plugin callable in the completion context")
    with pytest.raises(PsimapError, match="unknown method 'blob'"):
        complete(None, CompletionContext(points=pts, method="blob"))


def test_context_mapping_is_checked_against_the_fields():
    pts = _front_of(BOX)
    assert complete(None, {"points": pts, "voxel_size": VOXEL}).method == "box"
    # an exporter key that leaked into the completion context is an error, not silently ignored
    with pytest.raises(PsimapError, match="unknown key 'support_z'"):
        complete(None, {"points": pts, "support_z": 0.0})


# ---------------------------------------------------------------- a third-party method

PLUGIN = '''
import trimesh
from psimap.completion.methods import Method

def fit_bounds(obs):
    """The axis-aligned box around the observed points."""
    lo, hi = obs.points.min(0), obs.points.max(0)
    return trimesh.creation.box(bounds=[lo, hi])

METHOD = Method("bounds", tier=5, fit=fit_bounds, parametric=True)
NOT_A_METHOD = object()
'''


def _install(root, entry: str = "bounds = psimap_bounds:METHOD"):
    """A distribution on sys.path that registers `entry` under psimap.completion, as pip would."""
    (root / "psimap_bounds.py").write_text(PLUGIN)
    info = root / "psimap_bounds-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: psimap-bounds\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[psimap.completion]\n{entry}\n")


@pytest.fixture
def installed(tmp_path, monkeypatch):
    _install(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def test_registered_method_is_listed_and_joins_auto_in_its_tier(installed):
    assert "bounds" in method_names() and "bounds" in Choices()
    table = methods()
    assert [m.name for m in table][:2] == ["plugin", "bounds"]        # tier 5: before the primitives
    assert "bounds" not in [m.name for m in BUILTIN]
    res = complete(None, CompletionContext(points=_front_of(BOX), voxel_size=VOXEL))
    assert res.method == "bounds" and res.completed, res.reason        # its tier wins, the box's never runs
    assert list(res.candidates) == ["bounds"]
    np.testing.assert_allclose(res.mesh.bounds, BOX.bounds, atol=2e-3)


def test_bad_registrations_are_one_clear_error(tmp_path, monkeypatch):
    _install(tmp_path, "bounds = psimap_bounds:NOT_A_METHOD")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(PsimapError, match="'bounds' .* is not a psimap.completion.methods.Method"):
        methods()
    (tmp_path / "psimap_bounds-0.1.dist-info" / "entry_points.txt").write_text(
        "[psimap.completion]\nbox = psimap_bounds:METHOD\n")
    with pytest.raises(PsimapError, match="not a psimap.completion.methods.Method named 'box'"):
        methods()
    assert isinstance(BUILTIN[0], Method)


# ---------------------------------------------------------------- through `psimap export`

@pytest.fixture(scope="module")
def ball_box_ckpt(ring_checkpoint):
    """A checkpoint of a ball and a box on a floor, seen from a ring of cameras."""
    from psimap.data.frames import ClassInfo

    floor = trimesh.creation.box(extents=[1.4, 1.4, 0.02]).apply_translation([0, 0, -0.01])
    ball = trimesh.creation.icosphere(3, radius=0.07).apply_translation([-0.15, 0, 0.07])
    box = trimesh.creation.box(extents=[0.16, 0.12, 0.1]).apply_translation([0.18, 0.05, 0.05])
    classes = [ClassInfo(1, "floor", False), ClassInfo(2, "ball", True), ClassInfo(3, "box", True)]
    return ring_checkpoint([floor, ball, box], [0, 4, 5], [1, 2, 3], classes,
                           colors=[(0.5, 0.5, 0.5), (0.1, 0.8, 0.1), (0.9, 0.1, 0.1)], target=[0, 0, 0.05],
                           radius=0.8, height=0.6, views=10)


def _export(ckpt, out, *args):
    from psimap.cli import main

    rc = main(["export", str(ckpt), "--format", "mjcf", "--no-check", "--out", str(out), *args])
    report = json.loads((out / "report.json").read_text()) if rc == 0 else None
    return rc, {o["name"]: o for o in report["objects"]} if report else None


def test_cli_runs_the_method_it_is_given(ball_box_ckpt, tmp_path, installed, capsys):
    rc, forced = _export(ball_box_ckpt, tmp_path / "cyl", "--completion", "cylinder")
    assert rc == 0 and set(forced) == {"ball_4", "box_5"}
    assert [o["completion_method"] for o in forced.values()] == ["cylinder", "cylinder"]
    assert all(o["completed"] for o in forced.values())
    # the installed method, by name through the CLI
    rc, third = _export(ball_box_ckpt, tmp_path / "bounds", "--completion", "bounds")
    assert rc == 0 and {o["completion_method"] for o in third.values()} == {"bounds"}
    # the ball closed as the box around what was seen of it, carved by the free space the views saw:
    # 1.22 x the ball's volume (the box alone 1.9 x; the forced cylinder's 1.06 x; 1.50 and 1.30 x
    # while the depth tests read the pixel half a pixel off, which carved less)
    ball = 4 / 3 * np.pi * 0.07 ** 3
    assert 1.1 * forced["ball_4"]["physics"]["volume_m3"] < third["ball_4"]["physics"]["volume_m3"] < 1.6 * ball
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:        # argparse: not a registered method
        _export(ball_box_ckpt, tmp_path / "x", "--completion", "blob")
    assert e.value.code == 2 and "invalid choice: 'blob'" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_export_scene_rejects_an_unknown_completion(tmp_path):
    from psimap.exporters.pipeline import export_scene

    with pytest.raises(PsimapError, match="unknown completion 'plugin' .*auto, none, sphere"):
        export_scene([], tmp_path / "o", completion="plugin")
