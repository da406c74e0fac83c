"""examples/ run as a user runs them (a subprocess, its own MuJoCo GL choice)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scripts import load_script

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_real_capture_example_end_to_end(tmp_path):
    """A capture without masks of its own (the generated scene's are overridden) -> segment -> train ->
    export -> summary table and a MuJoCo render; the user's folder is copied, never written."""
    from psimap.data.synthetic import generate

    data = tmp_path / "capture"
    generate(data, seed=1, frames=8, width=64, height=48, progress=False)
    before = sorted(p.relative_to(data) for p in data.rglob("*"))
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, str(ROOT / "examples" / "real_capture.py"), "--data", str(data),
                        "--out", str(out), "--quick"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(p.relative_to(data) for p in data.rglob("*")) == before      # the input is untouched
    labels = json.loads((out / "capture" / "labels.json").read_text())
    assert labels["source"].startswith("psimap segment") and len(labels["frames"]) == 8
    report = json.loads((out / "export" / "report.json").read_text())
    names = [o["name"] for o in report["objects"] if not o.get("skipped")]
    assert names, "no object exported"
    table = r.stdout[r.stdout.index("object  "):]
    assert all(n in table for n in names)                      # one row per exported object
    assert "static world:" in table and "MuJoCo check: passed" in table
    assert "fit to the capture" in r.stdout and "% of the sensor's depth pixels rendered" in r.stdout
    if "no preview" not in r.stdout:                           # offscreen GL (EGL) present
        import numpy as np
        from PIL import Image

        img = np.asarray(Image.open(out / "preview.png").convert("L"))
        assert img.shape == (480, 640) and len(np.unique(img)) > 50                     # not a blank frame


# ---------------------------------------------------------------- examples/policy_env.py

def _example(name: str):
    """An examples/ script imported as a module (examples/ is no package)."""
    return load_script(f"examples/{name}.py", f"example_{name}")


@pytest.fixture(scope="module")
def policy(tmp_path_factory):
    """(the policy_env module, its small table-top export built through psimap's API)."""
    P = _example("policy_env")
    return P, P.tiny_export(tmp_path_factory.mktemp("policy") / "export")


def test_policy_env_resets_onto_the_supports_without_penetration(policy):
    """Random yaw about the vertical through the centre of mass, no contact deeper than the export
    check's 1 mm after mj_forward, the height kept (on its support), and it stays there."""
    P, export = policy
    env = P.PolicyEnv(export)
    home = {n: q.copy() for n, q in env.home_qpos.items()}
    redraws = 0
    for seed in range(8):
        obs, info = env.reset(seed=seed)
        assert info["min_contact_dist"] >= -1e-3, (seed, info["min_contact_dist"])
        assert info["kept_home"] == []
        redraws += info["redraws"]
        for k, n in enumerate(env.objects):
            assert obs["object_pos"][k][2] == pytest.approx(home[n][2], abs=1e-9)          # same height
            assert np.linalg.norm(obs["object_pos"][k][:2] - home[n][:2]) <= np.sqrt(2) * 0.02 + 1e-9
            turn = 2 * np.degrees(np.arccos(min(1.0, abs(float(obs["object_quat"][k] @ home[n][3:])))))
            assert turn > 0.5, (seed, n)                                                   # yaw drawn
    assert redraws > 0          # box and book stand 1 cm apart: some yaws collide and are drawn again
    obs0, _ = env.reset(seed=3)
    for _ in range(50):                                            # 1 s with the gripper still
        obs, reward, terminated, truncated, info = env.step(np.zeros(5))
    assert np.abs(obs["object_pos"] - obs0["object_pos"]).max() < 0.005
    assert not terminated and not truncated and obs["gripper"].shape == (5,)
    assert env.reset(seed=5)[0]["object_quat"].tolist() == env.reset(seed=5)[0]["object_quat"].tolist()


def test_scripted_push_moves_the_target_along_the_push_and_nothing_else(policy):
    P, export = policy
    env = P.PolicyEnv(export, target="box_2")
    _, info = env.reset(seed=0)
    start = info["distance"]
    r = P.scripted_push(env, max_steps=300)
    assert r["steps"] <= 300
    assert r["along"] >= 0.06 and r["sideways"] < 0.02, r             # an 8 cm push
    assert max(r["others"].values()) < 0.01, r["others"]              # the rest stay
    assert env._distance() < start - 0.05                             # the task's reward saw it


def test_grasp_lifts_the_light_box_and_the_heavy_twin_slips(policy):
    """Same shape, same squeeze (2 x 2.5 N, friction 1): the 0.22 kg box rises with the fingers,
    the 0.78 kg book (3.5 times as dense) stays on the table: masses and friction as exported."""
    P, export = policy
    env = P.PolicyEnv(export)
    m = env.model
    assert m.body_subtreemass[env.body["book_3"]] / m.body_subtreemass[env.body["box_2"]] == pytest.approx(3.5, rel=1e-3)
    env.reset(seed=0)
    light = P.scripted_grasp(env, "box_2")
    env.reset(seed=0)
    heavy = P.scripted_grasp(env, "book_3")
    assert light["width"] == pytest.approx(0.07, abs=2e-3)
    assert light["lift"] > 0.06, light
    assert heavy["lift"] < 0.01, heavy


def test_policy_env_script_runs_on_an_export(policy, tmp_path):
    """`python examples/policy_env.py EXPORT_DIR --steps N` as a user runs it (headless)."""
    _, export = policy
    png = tmp_path / "env.png"
    r = subprocess.run([sys.executable, str(ROOT / "examples" / "policy_env.py"), str(export), "--steps", "300",
                        "--seeds", "2", "--object", "can_4", "--grasp", "box_2", "--image", str(png)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "reset seed 1: min contact dist" in r.stdout and "push can_4 8 cm" in r.stdout
    assert "grasp box_2 (0.224 kg" in r.stdout
    if "no image" not in r.stdout:          # offscreen GL (EGL, chosen before mujoco's import) present
        from PIL import Image

        img = np.asarray(Image.open(png).convert("RGB"))
        assert img.shape == (480, 640, 3) and len(np.unique(img.reshape(-1, 3), axis=0)) > 50
    bad = subprocess.run([sys.executable, str(ROOT / "examples" / "policy_env.py"), str(export), "--object", "nope"],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode != 0 and "no dynamic object 'nope'" in bad.stderr


# ---------------------------------------------------------------- examples/objects_api.py

@pytest.fixture(scope="module")
def table_checkpoint(ring_checkpoint):
    """A floor, a static table and a box on it, seen by a ring of cameras (seconds to make)."""
    import trimesh

    from psimap.data.frames import ClassInfo

    floor = trimesh.creation.box(extents=[1.4, 1.4, 0.02]).apply_translation([0, 0, -0.01])
    table = trimesh.creation.box(extents=[0.6, 0.4, 0.3]).apply_translation([-0.1, 0, 0.15])
    box = trimesh.creation.box(extents=[0.16, 0.1, 0.12]).apply_translation([0.35, 0.1, 0.06])
    return ring_checkpoint([floor, table, box], [0, 3, 7], [1, 2, 3],
                           [ClassInfo(1, "floor", False), ClassInfo(2, "table", True), ClassInfo(3, "box", True)],
                           colors=[(0.5, 0.5, 0.5), (0.6, 0.4, 0.2), (0.9, 0.1, 0.1)], target=[0.1, 0.05, 0.1])


@pytest.mark.slow
def test_objects_api_example_prints_every_object_and_saves_one(table_checkpoint, tmp_path):
    import trimesh

    out = tmp_path / "objs"
    r = subprocess.run([sys.executable, str(ROOT / "examples" / "objects_api.py"), str(table_checkpoint),
                        "--out", str(out), "--completion", "none"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = {ln.split()[0]: ln.split() for ln in r.stdout.splitlines()[3:] if ln.strip() and not ln.startswith("saved")}
    assert set(rows) == {"table_3", "box_7"}, r.stdout
    assert rows["table_3"][1:3] == ["table", "static"] and rows["box_7"][1:3] == ["box", "dynamic"]
    mass = float(rows["box_7"][3])
    assert 0.5 * 0.16 * 0.1 * 0.12 * 200 < mass < 1.6 * 0.16 * 0.1 * 0.12 * 200          # volume x box density
    assert "saved box_7" in r.stdout                    # the first dynamic object, by default
    mesh = trimesh.load(out / "box_7.obj", process=False, force="mesh")
    np.testing.assert_allclose(mesh.bounds.mean(0)[:2], [0.35, 0.1], atol=0.02)         # world frame, metres
    collider = trimesh.load(out / "box_7_collider.obj", process=False, force="mesh")
    # the collider encloses the visual mesh it was fitted to, within the error the table prints
    assert collider.is_watertight and 0.8 < collider.volume / mesh.convex_hull.volume < 1.25
    err = float(rows["box_7"][-2]) / 1000
    np.testing.assert_allclose(collider.bounds, mesh.bounds, atol=err + 1e-3)
    phys = json.loads((out / "box_7.json").read_text())
    assert phys["mass_kg"] == pytest.approx(mass, abs=1e-3) and phys["role"] == "dynamic"
    # the folder is psimap's output now: a second run replaces it; a folder of the user's is refused
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    bad = subprocess.run([sys.executable, str(ROOT / "examples" / "objects_api.py"), str(table_checkpoint),
                          "--out", str(tmp_path / "mine"), "--completion", "none", "--save", "table_3"],
                         capture_output=True, text=True, timeout=600)
    assert bad.returncode != 0 and "objects_api:" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    assert sorted(p.name for p in (tmp_path / "mine").iterdir()) == ["notes.txt"]



def test_policy_env_camera_image(policy):
    """The optional camera image in the observation: the export's `overview` camera through
    mujoco.Renderer, in a fresh interpreter (MuJoCo picks its GL backend at its first import: the
    example chooses EGL before it; a test process may have imported mujoco earlier without it)."""
    _, export = policy
    code = (f"import sys; sys.path.insert(0, {str(ROOT / 'examples')!r}); import numpy as np, policy_env as P\n"
            f"env = P.PolicyEnv({str(export)!r}, image=True, width=96, height=72)\n"
            "try:\n    obs, _ = env.reset(seed=0)\nexcept Exception as e:\n    print('no image', e); sys.exit(0)\n"
            "img = obs['image']; obs2 = env.step([1, 0, 0, 0, -1])[0]\n"
            "print(env.camera, img.shape, img.dtype, len(np.unique(img.reshape(-1, 3), axis=0)), obs2['image'].shape)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    if r.stdout.startswith("no image"):
        pytest.skip(f"no offscreen rendering here: {r.stdout.strip()}")
    camera, shape, dtype, colours, shape2 = r.stdout.replace(", ", ",").split()
    assert camera == "overview" and shape == shape2 == "(72,96,3)" and dtype == "uint8"
    assert int(colours) > 50                                              # a scene, not a blank frame
