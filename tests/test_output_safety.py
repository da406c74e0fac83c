"""No command deletes or replaces what psimap did not write (issue #14 §1).

Every writing command is run against the places a user's files live: a folder with their notes, a file
where a folder should go, the home directory, the working directory and its ancestors, a symlink to a
user folder. The refusal is one line, exit 1, before any work, and every user file is still there byte
for byte; a previous psimap output of the same kind is replaced; `--overwrite` adds files and deletes
none of the user's.
"""
from __future__ import annotations

import json
import os

import numpy as np
import pytest
import trimesh

from psimap import PsimapError
from psimap.cli import main
from psimap.io_utils import (MARKER, atomic_dir, check_output_dir, check_output_file, export_mesh_file,
                             written_by_psimap)


def _user_folder(root):
    """A folder holding a user's work: a file and a sub-folder with a file."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "notes.txt").write_text("my notes")
    (root / "thesis").mkdir()
    (root / "thesis" / "chapter1.tex").write_text("\\chapter{One}")
    return {"notes.txt": "my notes", "thesis/chapter1.tex": "\\chapter{One}"}


def _intact(root, files):
    return all((root / k).is_file() and (root / k).read_text() == v for k, v in files.items())


def _no_temp_left(parent):
    return not [p.name for p in parent.iterdir() if p.name.startswith(".") and (p.name.endswith(".tmp")
                                                                            or p.name.endswith(".old"))]


def _one_line_error(capsys, *needles):
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "internal error" not in err and "Traceback" not in err, err
    for n in needles:
        assert n in err, err
    return err


@pytest.fixture(scope="module")
def box_objects():
    from psimap.exporters.objects import build_object

    box = trimesh.creation.box(extents=[0.2, 0.1, 0.08]).apply_translation([0, 0, 0.04])
    return [build_object(box, "box", 1, completion="none")]


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    from psimap.camera import camera_rig, look_at
    from psimap.data.frames import ClassInfo
    from psimap.scene import scene_from_meshes

    floor = trimesh.creation.box(extents=[1.0, 1.0, 0.02]).apply_translation([0, 0, -0.01])
    box = trimesh.creation.box(extents=[0.2, 0.14, 0.12]).apply_translation([0.1, 0.05, 0.06])
    w, h, n = 48, 36, 4
    c2ws = [look_at(np.array([0.7 * np.cos(a), 0.7 * np.sin(a), 0.55]), [0.1, 0.05, 0.04])
            for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]
    cams = camera_rig(c2ws, w, h, 40.0)
    scene = scene_from_meshes([floor, box], [0, 7], [1, 2], [ClassInfo(1, "floor", False),
                                                            ClassInfo(2, "box", True)], cams)
    path = tmp_path_factory.mktemp("ckpt") / "scene.ckpt"
    scene.save(path)
    return path


# ---- the folder rules --------------------------------------------------------------------------
def test_export_refuses_a_user_folder_and_keeps_every_file(ckpt, tmp_path, capsys):
    out = tmp_path / "work"
    files = _user_folder(out)
    rc = main(["export", str(ckpt), "--format", "mjcf", "--no-check", "--out", str(out)])
    assert rc == 1
    _one_line_error(capsys, "did not write", "--overwrite", "notes.txt")
    assert _intact(out, files) and sorted(p.name for p in out.iterdir()) == ["notes.txt", "thesis"]
    assert _no_temp_left(tmp_path)


def test_export_refuses_a_file_where_the_folder_goes(ckpt, tmp_path, capsys):
    f = tmp_path / "thesis.pdf"
    f.write_bytes(b"%PDF-1.4 mine")
    for extra in ([], ["--overwrite"]):             # --overwrite never turns a file into a folder
        assert main(["export", str(ckpt), "--no-check", "--out", str(f), *extra]) == 1
        _one_line_error(capsys, "is a file")
        assert f.read_bytes() == b"%PDF-1.4 mine"


@pytest.mark.parametrize("where", ["cwd", "dot", "dotdot", "ancestor", "home", "root"])
def test_forbidden_folders_are_refused_even_with_overwrite(ckpt, tmp_path, monkeypatch, capsys, where):
    home = tmp_path / "home" / "user"
    work = home / "work" / "project"
    files = _user_folder(home)
    work.mkdir(parents=True)
    (work / "data.txt").write_text("data")
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(work)
    out = {"cwd": str(work), "dot": ".", "dotdot": "..", "ancestor": str(tmp_path / "home"),
           "home": "~", "root": "/"}[where]
    rc = main(["export", str(ckpt), "--no-check", "--out", out, "--overwrite"])
    assert rc == 1
    _one_line_error(capsys, "refusing to write an output folder there")
    assert _intact(home, files) and (work / "data.txt").read_text() == "data"
    assert sorted(p.name for p in home.iterdir()) == ["notes.txt", "thesis", "work"]


def test_symlink_to_a_user_folder_is_refused(ckpt, tmp_path, capsys):
    real = tmp_path / "real"
    files = _user_folder(real)
    link = tmp_path / "link"
    link.symlink_to(real, target_is_directory=True)
    assert main(["export", str(ckpt), "--no-check", "--out", str(link)]) == 1
    _one_line_error(capsys, "did not write")
    assert link.is_symlink() and _intact(real, files)


def test_previous_export_is_replaced_and_user_files_inside_it_stop_the_replace(box_objects, tmp_path):
    from psimap.exporters.pipeline import export_scene

    out = tmp_path / "exp"
    export_scene(box_objects, out, "mjcf", check=False)
    meta = json.loads((out / MARKER).read_text())
    assert meta["kind"] == "export" and "scene.xml" in meta["files"] and "report.json" in meta["files"]
    stale = out / "meshes" / "box_1.obj"
    assert stale.is_file()
    # a second export replaces the first whole: a file only the first wrote is gone
    export_scene(box_objects, out, "glb", check=False)
    assert (out / "scene.glb").is_file() and not (out / "scene.xml").exists()
    assert json.loads((out / MARKER).read_text())["files"] == sorted(
        str(p.relative_to(out)) for p in out.rglob("*") if p.is_file() and p.name != MARKER)
    # the user keeps notes inside the export folder: a re-export must not delete them
    (out / "meshes" / "my_notes.txt").write_text("keep")
    with pytest.raises(PsimapError, match="did not write.*my_notes.txt"):
        export_scene(box_objects, out, "mjcf", check=False)
    assert (out / "meshes" / "my_notes.txt").read_text() == "keep" and (out / "scene.glb").is_file()
    # --overwrite: the new export is added, the notes stay, the old export's own files go
    export_scene(box_objects, out, "mjcf", check=False, overwrite=True)
    assert (out / "meshes" / "my_notes.txt").read_text() == "keep"
    assert (out / "scene.xml").is_file() and not (out / "scene.glb").exists()
    assert _no_temp_left(tmp_path)


def test_overwrite_into_a_user_folder_adds_and_deletes_nothing(box_objects, tmp_path):
    from psimap.exporters.pipeline import export_scene

    out = tmp_path / "work"
    files = _user_folder(out)
    (out / "report.json").write_text("the user's own report")
    export_scene(box_objects, out, "mjcf", check=False, overwrite=True)
    assert _intact(out, files)
    assert json.loads((out / "report.json").read_text())["objects"][0]["name"] == "box_1"   # same name: replaced
    assert (out / "scene.xml").is_file() and json.loads((out / MARKER).read_text())["kind"] == "export"
    # twice: still nothing of the user's deleted
    export_scene(box_objects, out, "mjcf", check=False, overwrite=True)
    assert _intact(out, files)


def test_failed_export_leaves_the_previous_one_untouched(box_objects, tmp_path, monkeypatch):
    from psimap.exporters import pipeline

    out = tmp_path / "exp"
    pipeline.export_scene(box_objects, out, "mjcf", check=False)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}

    def boom(*a, **k):
        raise RuntimeError("writer crashed")

    monkeypatch.setattr("psimap.exporters.glb.write_glb", boom)
    with pytest.raises(RuntimeError):
        pipeline.export_scene(box_objects, out, "glb", check=False)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert _no_temp_left(tmp_path)


def test_a_folder_of_another_kind_is_not_replaced(box_objects, tmp_path):
    from psimap.exporters.pipeline import export_scene

    out = tmp_path / "exp"
    export_scene(box_objects, out, "mjcf", check=False)
    with pytest.raises(PsimapError, match="holds a psimap export output, not a labels output"):
        check_output_dir(out, "labels")
    assert check_output_dir(out, "labels", overwrite=True)[1] == "merge"
    assert check_output_dir(out, "export")[1] == "replace"
    assert check_output_dir(tmp_path / "new", "export")[1] == "new"
    (tmp_path / "empty").mkdir()
    assert check_output_dir(tmp_path / "empty", "export")[1] == "new"


def test_merge_refuses_a_file_where_it_writes_a_folder(tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / "meshes").write_text("a file named like psimap's folder")
    with pytest.raises(PsimapError, match="meshes is a file"):
        with atomic_dir(out, "export", overwrite=True) as tmp:
            (tmp / "meshes").mkdir()
            (tmp / "meshes" / "a.obj").write_text("v 0 0 0")
    assert (out / "meshes").read_text() == "a file named like psimap's folder" and _no_temp_left(tmp_path)


# ---- every other writing command -------------------------------------------------------------
def test_labels_refuse_a_user_folder_and_replace_their_own(ckpt, tmp_path, capsys):
    data = tmp_path / "data"
    _write_tiny_scene(data)
    out = tmp_path / "labels"
    files = _user_folder(out)
    assert main(["labels", str(ckpt), str(data), "--out", str(out)]) == 1
    _one_line_error(capsys, "did not write")
    assert _intact(out, files)
    out2 = tmp_path / "labels2"
    assert main(["labels", str(ckpt), str(data), "--out", str(out2)]) == 0
    assert json.loads((out2 / MARKER).read_text())["kind"] == "labels"
    assert main(["labels", str(ckpt), str(data), "--out", str(out2)]) == 0      # its own: replaced
    capsys.readouterr()
    assert main(["labels", str(ckpt), str(data), "--out", str(out), "--overwrite"]) == 0
    assert _intact(out, files) and (out / "panoptic.json").is_file()


def _write_tiny_scene(path, **kw):
    from psimap.data.synthetic import generate

    return generate(path, seed=3, frames=2, width=32, height=24, n_objects=2, progress=False, **kw)


def test_generate_refuses_a_user_capture_and_replaces_its_own(tmp_path, capsys):
    capture = tmp_path / "capture"
    files = _user_folder(capture)
    (capture / "transforms.json").write_text('{"frames": []}')       # a user's own capture
    files["transforms.json"] = '{"frames": []}'
    assert main(["generate", str(capture), "--frames", "2", "--width", "32", "--height", "24"]) == 1
    _one_line_error(capsys, "did not write")
    assert _intact(capture, files)
    gen = tmp_path / "gen"
    _write_tiny_scene(gen)
    first = (gen / "transforms.json").read_text()
    _write_tiny_scene(gen)                                           # psimap's own: replaced
    assert (gen / "transforms.json").read_text() == first
    assert json.loads((gen / MARKER).read_text())["kind"] == "scene"
    _write_tiny_scene(capture, overwrite=True)
    assert _intact(capture, {k: v for k, v in files.items() if k != "transforms.json"})
    assert json.loads((capture / "transforms.json").read_text())["frames"]


def test_train_refuses_before_training(tmp_path, capsys, monkeypatch):
    data = tmp_path / "data"
    _write_tiny_scene(data)

    def no_training(*a, **k):
        raise AssertionError("trained before checking --out")

    monkeypatch.setattr("psimap.train.trainer.train", no_training)
    mine = tmp_path / "mine.ckpt"
    mine.write_text("not a checkpoint")
    assert main(["train", str(data), "--out", str(mine)]) == 1
    _one_line_error(capsys, "was not written by psimap")
    assert mine.read_text() == "not a checkpoint"
    folder = tmp_path / "folder"
    files = _user_folder(folder)
    assert main(["train", str(data), "--out", str(folder), "--overwrite"]) == 1
    _one_line_error(capsys, "is a folder")
    assert _intact(folder, files)


def test_checkpoints_replace_only_checkpoints(ckpt, tmp_path):
    import psimap

    scene = psimap.load(ckpt)
    mine = tmp_path / "notes.ckpt"
    mine.write_bytes(b"PK\x03\x04 a zip of mine")
    with pytest.raises(PsimapError, match="was not written by psimap"):
        scene.save(mine)
    assert mine.read_bytes() == b"PK\x03\x04 a zip of mine"
    scene.save(mine, overwrite=True)
    assert written_by_psimap(mine)
    scene.save(mine)                         # now a psimap checkpoint: replaced without asking
    assert len(psimap.load(mine)) == len(scene)


def test_mesh_command_refuses_user_files_and_replaces_its_own(ckpt, tmp_path, capsys):
    mine = tmp_path / "mesh.ply"
    mine.write_text("ply\nmy scan\n")
    assert main(["mesh", str(ckpt), "--out", str(mine)]) == 1
    _one_line_error(capsys, "was not written by psimap")
    assert mine.read_text() == "ply\nmy scan\n"
    out = tmp_path / "ours.ply"
    assert main(["mesh", str(ckpt), "--out", str(out)]) == 0
    assert written_by_psimap(out) and main(["mesh", str(ckpt), "--out", str(out)]) == 0
    assert len(trimesh.load(out).faces) > 100


@pytest.mark.parametrize("ext", ["ply", "obj", "off", "stl", "glb"])
def test_signed_mesh_files_read_back(tmp_path, ext):
    box = trimesh.creation.box(extents=[1, 2, 3])
    p = tmp_path / f"m.{ext}"
    export_mesh_file(box, p)
    assert written_by_psimap(p)
    back = trimesh.load(p, force="mesh")
    np.testing.assert_allclose(back.extents, [1, 2, 3], atol=1e-6)
    assert back.is_watertight or ext == "stl"
    plain = tmp_path / f"plain.{ext}"
    box.export(plain)                      # the same format, not written through psimap
    assert not written_by_psimap(plain)


def test_eval_plot_refuses_a_user_png(tmp_path, capsys):
    from PIL import Image

    data = tmp_path / "data"
    _write_tiny_scene(data)
    png = tmp_path / "figure.png"
    Image.new("RGB", (4, 4), (255, 0, 0)).save(png)
    before = png.read_bytes()
    assert main(["eval", str(data / "gt" / "mesh.ply"), str(data), "--plot", str(png)]) == 1
    _one_line_error(capsys, "--plot", "was not written by psimap")
    assert png.read_bytes() == before
    ours = tmp_path / "ours.png"
    assert main(["eval", str(data / "gt" / "mesh.ply"), str(data), "--plot", str(ours), "--samples", "2000"]) == 0
    assert written_by_psimap(ours)
    assert main(["eval", str(data / "gt" / "mesh.ply"), str(data), "--plot", str(ours), "--samples", "2000"]) == 0


def test_demo_refuses_a_user_folder_and_checks_before_any_stage(tmp_path, capsys, monkeypatch):
    from psimap import demo

    ran = []
    monkeypatch.setattr(demo, "STAGES", [("generate", lambda s: ran.append(1) or "")])
    out = tmp_path / "work"
    files = _user_folder(out)
    assert main(["demo", "--out", str(out)]) == 1
    _one_line_error(capsys, "did not write")
    assert _intact(out, files) and not ran
    # an earlier demo folder is fine; a user's file where the demo writes eval.json is not
    d = tmp_path / "demo"
    assert main(["demo", "--out", str(d)]) == 0 and ran == [1]
    assert json.loads((d / MARKER).read_text())["kind"] == "demo"
    (d / "eval.json").write_text("mine")
    assert main(["demo", "--out", str(d)]) == 1
    _one_line_error(capsys, "eval.json exists and was not written by psimap")
    assert (d / "eval.json").read_text() == "mine"
    (d / "notes.txt").write_text("mine too")
    assert main(["demo", "--out", str(d), "--overwrite"]) == 0
    assert (d / "notes.txt").read_text() == "mine too"


def test_check_output_file_rules(tmp_path):
    assert check_output_file(tmp_path / "new.ckpt") == (tmp_path / "new.ckpt").resolve()
    (tmp_path / "d").mkdir()
    with pytest.raises(PsimapError, match="is a folder"):
        check_output_file(tmp_path / "d", overwrite=True)
    f = tmp_path / "x.png"
    f.write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    assert not written_by_psimap(f)
    with pytest.raises(PsimapError):
        check_output_file(f)
    assert check_output_file(f, overwrite=True)
    os.chmod(f, 0)                           # unreadable: not ours (root may still read it)
    check_output_file(f, overwrite=True)
