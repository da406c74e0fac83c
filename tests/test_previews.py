"""preview.png and report.html of an export: MuJoCo's offscreen pictures tinted by role, the "after"
from the settle check's own poses, the backend fallback, no OpenGL at all, and the page as headless
Chromium shows it."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from dataclasses import replace
from html.parser import HTMLParser

import numpy as np
import pytest
import trimesh

CHROMIUM = "/usr/bin/chromium"


def _objects():
    """A box on the floor (dynamic), a cabinet (static furniture), a ball 6 cm above the floor with
    nothing under it (falls in the settle: pinned, or it moves in the "after" view)."""
    from psimap.exporters.objects import build_object

    box = trimesh.creation.box(extents=[0.16, 0.12, 0.1]).apply_translation([0.0, 0.0, 0.05])
    box.visual.vertex_colors = [200, 40, 40, 255]
    cabinet = trimesh.creation.box(extents=[0.3, 0.3, 0.4]).apply_translation([0.45, 0.0, 0.2])
    cabinet.visual.vertex_colors = [90, 160, 60, 255]
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.05).apply_translation([-0.35, 0.1, 0.11])
    ball.visual.vertex_colors = [40, 40, 200, 255]
    return [build_object(m, lab, i + 1, completion="none")
            for i, (m, lab) in enumerate([(box, "box"), (cabinet, "cabinet"), (ball, "ball")])]


@pytest.fixture(scope="module")
def objects():
    """_objects(), built once (export_scene decides roles on copies)."""
    return _objects()


@pytest.fixture(scope="module")
def pinned_export(tmp_path_factory, objects):
    """An export whose ball is pinned by the settle check (report, folder)."""
    from psimap.exporters.pipeline import export_scene

    out = tmp_path_factory.mktemp("prev") / "pinned"
    return export_scene(objects, out, "mjcf"), out


def _halves(png) -> tuple[np.ndarray, np.ndarray]:
    """The before and after panels of preview.png (exporters.preview.compose's layout)."""
    from PIL import Image

    from psimap.exporters.preview import VIEW_PX

    img = np.asarray(Image.open(png).convert("RGB")).astype(float)
    w, h = VIEW_PX
    return img[30:30 + h, :w], img[30:30 + h, w + 8:2 * w + 8]


def _near(img: np.ndarray, rgb, tol: float = 0.03) -> np.ndarray:
    """Pixels whose chromaticity (r, g, b over their sum) is within `tol` of the tint's: a flat tint
    under any light keeps its chromaticity, the grey floor and the background never have it."""
    s = img.sum(-1, keepdims=True)
    chroma = img / np.maximum(s, 1)
    tint = np.asarray(rgb, float) / sum(rgb)
    return (np.abs(chroma - tint).max(-1) < tol) & (s[..., 0] > 60)


def test_export_pictures_are_tinted_by_role(pinned_export):
    from PIL import Image

    from psimap.exporters.preview import TINTS, VIEW_PX

    report, out = pinned_export
    assert report["check"]["pinned"].keys() == {"ball_3"}
    assert report["preview"] == {"image": "preview.png", "renderer": report["preview"]["renderer"],
                                 "view_px": list(VIEW_PX), "thumbnail_px": 96}
    im = Image.open(out / "preview.png")
    assert im.size == (2 * VIEW_PX[0] + 8, VIEW_PX[1] + 64) and im.info["Software"].startswith("psimap")
    before, after = _halves(out / "preview.png")
    # one object per role: each tint covers its object's pixels, in both panels
    for half in (before, after):
        counts = {r: int(_near(half, TINTS[r][0]).sum()) for r in TINTS}
        assert min(counts.values()) > 150, counts
        assert counts["static"] > 4 * counts["dynamic"], counts       # the cabinet is the biggest
    # pinned: the ball no longer moves, so the panels agree where it is
    pin_b, pin_a = _near(before, TINTS["pinned"][0]), _near(after, TINTS["pinned"][0])
    assert (pin_b ^ pin_a).sum() < 0.05 * pin_b.sum()
    assert not (out / ".preview").exists() and not (out / ".check").exists()


def test_the_pixels_of_each_body_carry_its_role_tint(objects, tmp_path):
    """Per body (MuJoCo's segmentation of the same shot): its pixels have its role's chromaticity."""
    from psimap.exporters.formats import ExportScene
    from psimap.exporters.mjcf import write_mjcf
    from psimap.exporters.pipeline import assign_roles
    from psimap.exporters.preview import TINTS, role, start_preview
    from psimap.exporters.roles import Reason

    objs = [replace(o) for o in objects]
    assign_roles(objs)
    objs[2].make_static(Reason.UNSTABLE, "moved")
    scene = ExportScene(tuple(objs), None, 0.0)
    xml = write_mjcf(scene, tmp_path)
    arrays, how = start_preview(scene, xml, tmp_path / "p.npz", None, labels=True).result()
    assert arrays is not None, how
    assert [role(o) for o in objs] == ["dynamic", "static", "pinned"]
    for i, o in enumerate(objs):
        mine = arrays["before_body"] == i
        assert mine.sum() > 100, o.name
        share = _near(arrays["before"][mine].astype(float)[None], TINTS[role(o)][0]).mean()
        assert share > 0.9, (o.name, share)
        # its thumbnail: that object alone, in its own colour (vertex colours), framed (> 20 % of it)
        thumb, mask = arrays[f"thumb_{i}"], arrays[f"thumb_{i}_mask"]
        assert 0.2 < mask.mean() < 0.95, (o.name, mask.mean())
        colour = thumb[mask].astype(float).mean(0)
        assert np.argmax(colour) == np.argmax(np.asarray(o.vertex_rgb).mean(0)), (o.name, colour)


def test_after_panel_shows_the_settle(objects, tmp_path):
    """Not pinned, the ball falls in the check: the after panel has it lower (its pixels moved down
    the picture), the box and the cabinet stay where they were."""
    from psimap.exporters.pipeline import export_scene
    from psimap.exporters.preview import TINTS

    r = export_scene(objects, tmp_path / "e", "usd", pin_unstable=False)
    assert not r["check"]["passed"] and r["check"]["fell"]["ball_3"] > 0.03
    before, after = _halves(tmp_path / "e" / "preview.png")
    ball_b, ball_a = (_near(h, TINTS["dynamic"][0]) for h in (before, after))
    # the box stays; the ball leaves pixels (old) and covers new ones lower in the picture (new)
    old, new = ball_b & ~ball_a, ball_a & ~ball_b
    assert old.sum() > 50 and new.sum() > 50, (old.sum(), new.sum())
    assert np.nonzero(new)[0].mean() - np.nonzero(old)[0].mean() >= 5
    changed = np.abs(before - after).sum(-1) > 30
    assert changed.sum() > 100
    static_b = _near(before, TINTS["static"][0])
    assert (static_b ^ _near(after, TINTS["static"][0])).sum() < 0.02 * static_b.sum()
    # a usd-only export renders from the check's own MJCF, which is not left behind
    assert sorted(p.name for p in (tmp_path / "e").iterdir() if p.suffix in (".xml", ".usda")) == ["scene.usda"]


def test_backend_fallback_and_no_opengl(objects, tmp_path, monkeypatch):
    """MUJOCO_GL naming a backend that cannot start here (glx without a display) falls back to EGL /
    OSMesa; with OpenGL off the export still succeeds: no preview.png, one reason, the page is there."""
    from psimap.exporters.pipeline import export_scene
    from psimap.exporters.preview import PreviewWarning
    from psimap.sim.render import backends

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setenv("MUJOCO_GL", "glx")
    assert backends() == ["glx", "egl", "osmesa"]
    r = export_scene(objects[:1], tmp_path / "a", "mjcf", check=False)
    assert r["preview"]["renderer"] in ("egl", "osmesa")
    assert (tmp_path / "a" / "preview.png").is_file()
    monkeypatch.setenv("MUJOCO_GL", "off")
    with pytest.warns(PreviewWarning, match="MUJOCO_GL=off"):
        r = export_scene(objects[:1], tmp_path / "b", "mjcf")
    assert r["preview"]["image"] is None and "OpenGL" in r["preview"]["reason"]
    assert r["check"]["passed"] and not (tmp_path / "b" / "preview.png").exists()
    assert "no preview: no offscreen OpenGL" in (tmp_path / "b" / "report.html").read_text()
    saved = json.loads((tmp_path / "b" / "report.json").read_text())
    assert saved["preview"] == {"image": None, "reason": r["preview"]["reason"]}


def test_cli_no_preview_and_its_warning_line(tmp_path, monkeypatch, capsys):
    """--no-preview reaches export_scene; a preview that could not be drawn is one stderr line."""
    import psimap.exporters.pipeline as pipeline
    import psimap.scene
    from psimap.cli import main

    seen = {}

    def fake_export(scene, out, fmt, **kw):
        seen.update(kw)
        return {"outcome": {"passed": True, "summary": "1 of 1 thing(s) dynamic"}, "objects": [], "skipped": [],
                "preview": {"image": None, "reason": "no offscreen OpenGL for MuJoCo (egl: X)"}, "timings": {}}

    monkeypatch.setattr(pipeline, "export_scene", fake_export)
    monkeypatch.setattr(psimap.scene, "load_scene", lambda path: None)
    assert main(["export", "x.ckpt", "--out", str(tmp_path / "o"), "--no-preview", "--no-check"]) == 0
    assert seen["preview"] is False
    assert main(["export", "x.ckpt", "--out", str(tmp_path / "o"), "--no-check"]) == 0
    assert seen["preview"] is True
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["warning: no preview.png (no offscreen OpenGL for MuJoCo (egl: X)); report.html has the table"] * 2


class _Rows(HTMLParser):
    """Rows of report.html's objects table as Chromium's DOM has them: {name: {role, class, mass,
    loaded}}, and every <img>'s data-loaded (set by the test's probe script)."""

    def __init__(self):
        super().__init__()
        self.rows, self.imgs, self._row, self._cell = {}, [], None, None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "tr" and "object" in (a.get("class") or ""):
            self._row = self.rows.setdefault(a["data-name"], {"role": a["data-role"]})
        elif tag == "img":
            self.imgs.append(a)
        elif self._row is not None and tag in ("td", "span") and a.get("class") in ("class", "mass-kg"):
            self._cell = a["class"]

    def handle_data(self, data):
        if self._cell:
            self._row[self._cell] = data.strip()
            self._cell = None

    def handle_endtag(self, tag):
        if tag == "tr":
            self._row = None


def _chromium(args: list[str], tmp_path) -> subprocess.CompletedProcess:
    profile = tmp_path / f"profile{len(list(tmp_path.glob('profile*')))}"
    profile.mkdir()
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={profile}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=True)


@pytest.mark.skipif(not os.path.exists(CHROMIUM), reason="chromium is not installed (make install puts it there)")
def test_report_html_in_headless_chromium(pinned_export, tmp_path):
    from PIL import Image

    from psimap.exporters.preview import TINTS

    report, out = pinned_export
    page = out / "report.html"
    html = page.read_text()
    assert "<script" not in html and "http" not in html       # no JS, nothing from the network
    # the test's probe: a copy of the page whose script marks every image that loaded (naturalWidth)
    shutil.copytree(out, out.parent / "probe_dir")
    probe = out.parent / "probe_dir" / "probe.html"
    probe.write_text(html.replace("</body>", "<script>addEventListener('load', () => {for (const i of "
                                   "document.images) i.setAttribute('data-loaded', i.complete ? i.naturalWidth "
                                   "+ 'x' + i.naturalHeight : 'no');});</script></body>"))
    dom = _chromium(["--virtual-time-budget=3000", "--dump-dom", probe.as_uri()], tmp_path).stdout
    rows = _Rows()
    rows.feed(dom)
    entries = {e["name"]: e for e in report["objects"]}
    assert sorted(rows.rows) == sorted(entries)
    for name, e in entries.items():
        got = rows.rows[name]
        assert got["class"] == e["class"]
        assert float(got["mass-kg"]) == pytest.approx(e["physics"]["mass_kg"], rel=5e-3), name
        assert got["role"] == {"box_1": "dynamic", "cabinet_2": "static", "ball_3": "pinned"}[name]
    loaded = {i.get("alt", "").split(",")[0]: i.get("data-loaded") for i in rows.imgs}
    assert len(rows.imgs) == 1 + len(entries)
    w, h = Image.open(out / "preview.png").size
    assert loaded["the scene before and after the settle check"] == f"{w}x{h}"
    assert all(loaded[n] == "96x96" for n in entries), loaded
    # the page as a person sees it: not blank, the preview's tints on screen, each thumbnail drawn
    shot = tmp_path / "shot.png"
    _chromium([f"--screenshot={shot}", "--window-size=1200,1400", "--hide-scrollbars", page.as_uri()], tmp_path)
    img = np.asarray(Image.open(shot).convert("RGB")).astype(float)
    assert img.std() > 20
    for r, (rgb, _) in TINTS.items():
        assert _near(img, rgb).sum() > 30, r
