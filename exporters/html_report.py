"""`report.html` of an export: what report.json says, as a page a person reads in a browser.

The previews (preview.png, next to it in the export folder), the outcome and check lines, then one
row per object: its thumbnail (inline PNG), class, role, mass and its model, collider kind and
error, faces, completion and static reason. Every figure is read from report.json's data (the dict
as written, exporters.report.object_entry): nothing is recomputed here. Self-contained: no script,
no network, no stylesheet but its own; deterministic like report.json.
"""
from __future__ import annotations

import base64
from html import escape

from psimap.exporters.preview import TINTS

CSS = """
body { font-family: sans-serif; margin: 16px; color: #111; }
h1 { font-size: 20px; margin: 0 0 8px 0; }
p { margin: 4px 0; }
img.preview { max-width: 100%; border: 1px solid #ccc; margin: 8px 0; }
table { border-collapse: collapse; font-size: 13px; }
th, td { border-bottom: 1px solid #ddd; padding: 3px 8px; text-align: left; vertical-align: middle; }
th { background: #f2f2f2; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
img.thumb { width: 96px; height: 96px; background: #eee; display: block; }
span.swatch { display: inline-block; width: 12px; height: 12px; border: 1px solid #000;
              margin-right: 4px; vertical-align: middle; }
.failed { color: #b00; font-weight: bold; }
.small { color: #555; font-size: 12px; }
"""


def role(entry: dict, check: dict | None) -> str:
    """dynamic / static / pinned of a report.json object entry (pinned: named in check.pinned)."""
    if not entry.get("static"):
        return "dynamic"
    return "pinned" if entry["name"] in ((check or {}).get("pinned") or {}) else "static"


def _swatch(name: str) -> str:
    rgb = TINTS[name][0]
    return '<span class="swatch" style="background:#%02x%02x%02x"></span>' % tuple(round(255 * c) for c in rgb)


def _g(x: float) -> str:
    return f"{x:.3g}"


def _length(m: float | None) -> str:
    if m is None:
        return "-"
    return f"{m * 1000:.1f} mm" if abs(m) < 0.1 else f"{m * 100:.1f} cm"


def object_row(e: dict, check: dict | None, thumb: bytes | None) -> str:
    """One <tr> of the objects table for report.json entry `e`."""
    r = role(e, check)
    img = (f'<img class="thumb" alt="{escape(e["name"])}" src="data:image/png;base64,'
           f'{base64.b64encode(thumb).decode()}">' if thumb else '<span class="small">no picture</span>')
    ph = e.get("physics") or {}
    if ph:
        lo, hi = ph.get("mass_range_kg") or (None, None)
        mass = (f'<span class="mass-kg">{_g(ph["mass_kg"])}</span> kg<br><span class="small">'
                f'{escape(str(ph.get("mass_model")))}'
                + (f", plausible {_g(lo)}–{_g(hi)} kg" if lo is not None else "") + "</span>")
    else:
        mass = "-"
    c = e.get("collision") or {}
    if c:
        hulls = f", {c['hull_count']} hulls" if c.get("kind") == "decomposition" else ""
        collider = (f'{escape(c["kind"])}{hulls}<br><span class="small">error {_length(c.get("error_m"))} '
                    f'(tolerance {_length(c.get("tolerance_m"))})</span>')
    else:
        collider = "-"
    faces = f'{e["faces_after"]}<br><span class="small">from {e["faces_before"]}</span>'
    completion = (f'{escape(str(e.get("completion_method")))}<br><span class="small">'
                  f'{"completed" if e.get("completed") else "as observed"}</span>')
    reason = escape(e.get("static_reason") or "")
    return (f'<tr class="object" data-name="{escape(e["name"])}" data-role="{r}">'
            f"<td>{img}</td><td>{escape(e['name'])}</td><td class=\"class\">{escape(e['class'])}</td>"
            f"<td>{_swatch(r)}{r}</td><td class=\"num mass\">{mass}</td><td>{collider}</td>"
            f'<td class="num">{faces}</td><td>{completion}</td><td>{reason}</td></tr>')


def check_line(check: dict | None) -> str:
    if check is None:
        return "MuJoCo settle check: not run (--no-check)"
    words = "passed" if check.get("passed") else '<span class="failed">FAILED</span>: ' + escape(
        "; ".join(check.get("failures") or []))
    pinned = check.get("pinned") or {}
    return (f"MuJoCo settle check ({check.get('duration_s', 0):g} s): {words}; "
            f"min contact distance {check.get('min_contact_dist', 0) * 1000:.2f} mm, "
            f"max drift {check.get('max_drift', 0) * 100:.2f} cm, {len(check.get('nudges') or {})} nudged, "
            f"{len(pinned)} pinned")


def render_html(report: dict, thumbs: dict[str, bytes]) -> str:
    """The page for `report` (report.json's data, as written) and {object name: thumbnail PNG}."""
    out = report.get("outcome") or {}
    check = report.get("check")
    prev = report.get("preview") or {}
    parts = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
             "<title>psimap export report</title>", f"<style>{CSS}</style></head><body>",
             "<h1>psimap export</h1>",
             f'<p class="outcome">{"" if out.get("passed", True) else "<span class=failed>FAILED</span>: "}'
             f'{escape(out.get("summary", ""))}</p>',
             f'<p class="check">{check_line(check)}</p>',
             f'<p class="small">formats: {escape(", ".join(report.get("format") or []))}; '
             f'floor at {report.get("floor_z", 0):.3f} m</p>']
    env = report.get("environment")
    if env:
        cols = ", ".join(f"{n} {escape(k)}" for k, n in sorted((env.get("colliders") or {}).items()))
        unseen = env.get("unseen_supports") or []
        parts.append(f'<p class="small">static world: floor {"seen" if env.get("floor_observed") else "not seen"}'
                     f"; colliders {cols}"
                     + (f"; slabs inferred under {escape(', '.join(u['thing'] for u in unseen))} (standing on a "
                        "support no camera saw)" if unseen else "") + "</p>")
    if prev.get("image"):
        parts.append(f'<img class="preview" src="{escape(prev["image"])}" alt="the scene before and after '
                     f'the settle check, objects tinted by role">')
    else:
        parts.append(f'<p class="small">no preview: {escape(str(prev.get("reason", "not drawn")))}</p>')
    parts.append('<table id="objects"><thead><tr><th></th><th>object</th><th>class</th><th>role</th><th>mass</th>'
                 "<th>collider</th><th>faces</th><th>completion</th><th>static because</th></tr></thead><tbody>")
    parts += [object_row(e, check, thumbs.get(e["name"])) for e in report.get("objects") or []]
    parts.append("</tbody></table>")
    skipped = report.get("skipped") or []
    if skipped:
        parts.append("<p>skipped: " + "; ".join(f"{escape(s['name'])} ({escape(s['reason'])})" for s in skipped)
                     + "</p>")
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"


def write_html(path, report: dict, thumbs: dict[str, bytes]) -> None:
    from pathlib import Path

    Path(path).write_text(render_html(report, thumbs), encoding="utf-8")
