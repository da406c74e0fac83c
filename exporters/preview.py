"""`preview.png` of an export: the scene in MuJoCo before and after the settle check's 2 s, objects
tinted by role, plus one small picture of every object alone (report.html's thumbnails).

The pictures are drawn by MuJoCo's offscreen renderer in a child process (psimap.sim.render: EGL,
else OSMesa) from the MJCF the settle check simulated, started as soon as the check is done so that
it draws while the writers write; the "after" poses are the check's own (check_mjcf `settled`),
never a second simulation. With no offscreen OpenGL the export goes on without pictures and says why
(report.json "preview", a PreviewWarning).
"""
from __future__ import annotations

import warnings

import numpy as np

from psimap.exporters.roles import Reason, Role

# Okabe-Ito colours (told apart with any colour vision): role -> (RGB 0..1, legend words)
TINTS = {
    "dynamic": ((0.337, 0.706, 0.914), "dynamic"),
    "static": ((0.800, 0.475, 0.655), "static: furniture or too little evidence"),
    "pinned": ((0.902, 0.624, 0.0), "pinned: made static by the settle check"),
}
VIEW_PX = (800, 600)        # width, height of each of the two scene views
THUMB_PX = 96               # report.html's thumbnails (drawn at twice this size, then shrunk)
# the floor plane under a background whose own floor lies on it is drawn this much lower, so that
# the reconstructed floor wins the depth test and the plane only fills its holes
FLOOR_SINK_M = 0.02


class PreviewWarning(UserWarning):
    """An export wrote no preview (no offscreen OpenGL here); report.json "preview" says why."""


def role(obj) -> str:
    """The preview's role of an exported SceneObject: dynamic, pinned (static after moving in the
    settle check) or static (furniture, too little evidence)."""
    if obj.role is Role.DYNAMIC:
        return "dynamic"
    return "pinned" if obj.reason is Reason.UNSTABLE else "static"


def start_preview(scene, xml, out_npz, settled: dict | None, *, labels: bool = False):
    """Start drawing `scene` (ExportScene, roles final) from the MJCF at `xml` (written for it, the
    settle check's); `settled`: the check's poses after the settle (None: no check, one view);
    labels: also which object each pixel of a view shows (`<view>_body`). Returns a
    psimap.sim.render.PendingRender."""
    from psimap.exporters.mjcf import CAMERA_AZIMUTH, CAMERA_ELEVATION
    from psimap.sim.render import start_render

    views = [{"name": "before", "poses": None}]
    if settled is not None:
        views.append({"name": "after", "poses": settled})
    job = {"tint": {o.name: TINTS[role(o)][0] for o in scene.objects},
           "sink": {"floor": FLOOR_SINK_M} if scene.background is not None else {},
           "views": views, "width": VIEW_PX[0], "height": VIEW_PX[1], "thumb_px": 2 * THUMB_PX,
           # the side scene.xml's own free camera looks from (exporters.mjcf), framed tighter here
           "azimuth": CAMERA_AZIMUTH, "elevation": CAMERA_ELEVATION, "labels": labels}
    return start_render(xml, job, out_npz)


def finish_preview(pending, scene, check: dict | None, out_dir) -> tuple[dict, dict[str, bytes]]:
    """Wait for `pending`, write `out_dir/preview.png`; returns (report.json's "preview" entry,
    {object name: thumbnail PNG bytes}). No OpenGL: no file, the entry says why, a PreviewWarning."""
    from psimap.exporters.objfile import png_bytes

    arrays, how = pending.result()
    if arrays is None:
        warnings.warn(f"no preview.png: {how}", PreviewWarning, stacklevel=2)
        return {"image": None, "reason": how}, {}
    counts = {k: 0 for k in TINTS}
    for o in scene.objects:
        counts[role(o)] += 1
    image = compose(arrays["before"], arrays.get("after"), counts, check)
    save_png(image, out_dir / "preview.png")
    thumbs = {}
    for i, name in enumerate(arrays["bodies"]):
        if f"thumb_{i}" in arrays:      # (none for a body without a visual mesh)
            thumbs[str(name)] = png_bytes(thumbnail(arrays[f"thumb_{i}"], arrays[f"thumb_{i}_mask"]))
    return {"image": "preview.png", "renderer": how, "view_px": list(VIEW_PX), "thumbnail_px": THUMB_PX}, thumbs


def thumbnail(rgb: np.ndarray, mask: np.ndarray, size: int = THUMB_PX):
    """rgb [S, S, 3] uint8 and the object's pixels mask [S, S] -> an RGBA PIL image size x size,
    transparent where the object is not (shrunk with a box filter: the edges stay smooth)."""
    from PIL import Image

    rgba = np.dstack([rgb, np.where(mask, 255, 0).astype(np.uint8)])
    return Image.fromarray(rgba, "RGBA").resize((size, size), Image.Resampling.BOX)


def compose(before: np.ndarray, after: np.ndarray | None, counts: dict[str, int], check: dict | None):
    """before | after side by side [H, W, 3] each, a caption over each, the role legend under them
    (`counts` {role: objects}). Returns a PIL image."""
    from PIL import Image, ImageDraw, ImageFont

    font = ImageFont.load_default(size=16)
    h, w = before.shape[:2]
    gap, top, bottom = 8, 30, 34
    panels = [(before, "before: as exported (t = 0)")]
    if after is not None:
        drift = (check or {}).get("max_drift", 0.0) * 100
        words = "passed" if (check or {}).get("passed") else "FAILED"
        panels.append((after, f"after: {check.get('duration_s', 2.0):g} s in MuJoCo, max drift {drift:.2f} cm "
                              f"(check {words})"))
    else:
        panels[0] = (before, "as exported (no settle check: no 'after')")
    width = len(panels) * w + (len(panels) - 1) * gap
    canvas = Image.new("RGB", (width, top + h + bottom), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for k, (img, caption) in enumerate(panels):
        x = k * (w + gap)
        canvas.paste(Image.fromarray(img), (x, top))
        draw.text((x + 6, 6), caption, fill=(0, 0, 0), font=font)
    x = 6
    for name, (rgb, words) in TINTS.items():
        y = top + h + 8
        draw.rectangle([x, y, x + 18, y + 18], fill=tuple(int(round(255 * c)) for c in rgb), outline=(0, 0, 0))
        label = f"{words} ({counts.get(name, 0)})"
        draw.text((x + 26, y), label, fill=(0, 0, 0), font=font)
        x += 26 + int(draw.textlength(label, font=font)) + 28
    return canvas


def _pnginfo():
    from PIL.PngImagePlugin import PngInfo

    from psimap import __version__

    info = PngInfo()
    info.add_text("Software", f"psimap {__version__}")     # psimap.io_utils.written_by_psimap
    return info


def save_png(image, path) -> None:
    image.save(path, format="PNG", pnginfo=_pnginfo())     # optimize: 4x the time, no smaller

