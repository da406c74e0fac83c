"""Object-level metrics (docs/metrics.md, "Objects"): each ground-truth thing matched to at most one
predicted object, and how well that object's mesh reproduces the complete GT object.

Predictions are `PredictedObject`s: a name, a class, a mesh in the capture's frame, and what the
export decided about the object (role, mass). They come from an export folder (`read_export`) or,
through the entry points, from a checkpoint's extraction (psimap.api.predicted_objects): this
module never imports the export stage. The ground truth (`read_gt_things`) is DATA's gt/:
gt/objects/<id>.ply (complete meshes), gt/instances.json (class, optional mass_kg) and gt/mesh.ply's
per-face `instance` (the part of each object DATA's cameras saw).

Matching: score(pred, gt) = F-score at MATCH_THRESHOLD between the two (precision against the
complete GT mesh, recall against its observed part); one-to-one by Hungarian assignment on the
score; a GT thing is found when its match scores >= FOUND_SCORE. Only pairs whose boxes come within
MATCH_THRESHOLD of each other are scored: any other pair has precision 0, so it scores 0 anyway.

Sampling: points are area-uniform on each surface, from a seeded stream per surface (the result is
deterministic). How many: the first draw puts one point per SAMPLE_SPACING^2 of surface (bounded
by MIN_SAMPLES and `max_samples`), then the count doubles until the standard error of every
reported fraction is within FRACTION_SE. Distances are exact point-to-triangle distances
(psimap.metrics.geometry.raycasting_scene).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psimap import PsimapError
from psimap.metrics.geometry import face_areas, load_mesh, raycasting_scene, sample_surface

THRESHOLDS = (0.01, 0.025)      # metres: the F-scores and completeness reported per object
MATCH_THRESHOLD = 0.025         # metres: the F-score that decides the matching
FOUND_SCORE = 0.5               # a GT thing is found when its match scores at least this
FRACTION_SE = 0.005             # standard error budget of every reported fraction
SAMPLE_SPACING = 0.02           # metres: the first draw's density (an apple gets MIN_SAMPLES, a table ~10^4)
MIN_SAMPLES = 500
MAX_SAMPLES = 40_000
ROLES = ("dynamic", "static", "skipped", "n/a")


def key(threshold: float) -> str:
    """The suffix of a threshold's keys: 0.01 -> "10mm"."""
    return f"{round(threshold * 1000):d}mm"


@dataclass
class PredictedObject:
    """One predicted object. mesh: trimesh.Trimesh in metres, the capture's frame (DATA's world);
    None for an object that was skipped (it has no mesh)."""

    name: str
    label: str                          # class name
    mesh: object | None
    role: str = "n/a"                   # one of ROLES; "n/a": not decided (a checkpoint's extraction)
    reason: str | None = None           # why static or skipped, in words
    static_class: bool = False          # static furniture on purpose: not asked to move
    mass_kg: float | None = None
    observed_coverage: float | None = None   # the export's share of its surface the views saw


class SurfaceSamples:
    """Area-uniform points on a mesh's faces (vertices [V,3], faces [F,3]; only those where face_mask
    [F] is True; only points point_filter(points [N,3], faces [N]) -> [N] bool keeps), drawn from
    their own seeded stream and kept: first(n) is a prefix of first(m) for n <= m, so an error budget
    can ask for more points without changing those it has."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, seed, face_mask: np.ndarray | None = None,
                 point_filter=None):
        self.vertices, self.faces = vertices, faces
        self.face_mask, self.point_filter = face_mask, point_filter
        areas = face_areas(vertices, faces)
        self.area = float(areas.sum() if face_mask is None else areas[face_mask].sum())
        self.rng = np.random.default_rng(np.random.SeedSequence(seed))
        self.points = np.empty((0, 3))
        self.drawn = 0

    @property
    def accepted_share(self) -> float:
        """Share of the drawn points the filter kept (1 without a filter)."""
        return len(self.points) / self.drawn if self.drawn else 1.0

    def first(self, n: int) -> np.ndarray:
        """The first n points [n, 3] (fewer when the filter keeps almost nothing of the surface)."""
        while len(self.points) < n and self.area > 0:
            need = n - len(self.points)
            # rejection keeps the points area-uniform over the kept surface: draw enough extra
            k = int(math.ceil(need / max(self.accepted_share, 0.02)))
            pts, fid = sample_surface(self.vertices, self.faces, k, self.rng, self.face_mask, return_faces=True)
            self.drawn += k
            if self.point_filter is not None:
                pts = pts[self.point_filter(pts, fid)]
            # all kept points stay (beyond n too): their share of the drawn ones is the seen share
            self.points = np.concatenate([self.points, pts])
            if self.drawn >= 50 * max(n, MIN_SAMPLES) and len(self.points) < n:
                break       # a sliver of surface: what was kept is all there is
        return self.points[:n]


def start_count(area: float, max_samples: int) -> int:
    """The first draw on a surface of `area` m^2: one point per SAMPLE_SPACING^2."""
    return int(min(max_samples, max(MIN_SAMPLES, math.ceil(area / SAMPLE_SPACING**2))))


def distances_within_budget(samples: SurfaceSamples, other, *, max_samples: int = MAX_SAMPLES) -> np.ndarray:
    """Distances [n] of samples' first n points to the mesh behind `other` (raycasting_scene), n
    doubling from start_count until the standard error of the share within every threshold of
    THRESHOLDS is at most FRACTION_SE (or max_samples)."""
    import open3d as o3d

    n = start_count(samples.area, max_samples)
    d = np.empty(0)
    while True:
        pts = samples.first(n)
        if len(pts) > len(d):
            new = other.compute_distance(o3d.core.Tensor(pts[len(d):].astype(np.float32)))
            d = np.concatenate([d, new.numpy().astype(np.float64)])
        k = len(d)
        if k == 0 or len(pts) < n or n >= max_samples:
            return d
        # binomial standard error, never below the resolution 1/k of k samples
        if all(math.sqrt(max(p * (1 - p), 1.0 / k) / k) <= FRACTION_SE for p in (np.mean(d < t) for t in THRESHOLDS)):
            return d
        n = min(2 * n, max_samples)


def fscore(precision: float, recall: float) -> float:
    return 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0


@dataclass
class GTThing:
    """One ground-truth thing: its complete mesh and the part of it DATA's cameras saw (`observed`:
    samples on gt/mesh.ply's faces of the instance, kept where a camera sees them; None when no
    camera saw any of it)."""

    id: int
    label: str                          # class name
    name: str
    mesh: object                        # trimesh.Trimesh, complete
    observed: SurfaceSamples | None
    mass_kg: float | None = None
    scene_area: float = 0.0             # its area in gt/mesh.ply (the observed share's denominator)

    @property
    def size(self) -> float:
        """Bounding-box diagonal (m)."""
        return float(np.linalg.norm(np.ptp(np.asarray(self.mesh.vertices), axis=0)))

    @property
    def seen_fraction(self) -> float:
        """Share of its surface in gt/mesh.ply that some camera sees (seen faces, times the share of
        points on them a camera sees)."""
        if self.observed is None or self.scene_area <= 0:
            return 0.0
        self.observed.first(MIN_SAMPLES)       # no matching candidate may have drawn any yet
        return float(self.observed.area * self.observed.accepted_share / self.scene_area)


# --------------------------------------------------------------------------------------------------
# reading


def read_export(folder) -> list[PredictedObject]:
    """The objects of an export folder (docs/report.md): report.json's objects with their visual
    meshes (meshes/<name>.obj) turned back into the capture's frame (report gravity.rotation takes
    the capture to the exported frame), and its skipped objects (no mesh)."""
    folder = Path(folder)
    rpath = folder / "report.json"
    if not rpath.is_file():
        raise PsimapError(f"{folder}: no report.json (an export folder is what `psimap export` writes: "
                          f"report.json + meshes/)")
    try:
        report = json.loads(rpath.read_text())
        entries, skipped = report["objects"], report.get("skipped", [])
        gravity = report.get("gravity") or {}
        R = np.asarray(gravity.get("rotation", np.eye(3)), np.float64).reshape(3, 3)
        if not (np.isfinite(R).all() and np.allclose(R @ R.T, np.eye(3), atol=1e-6)):
            raise PsimapError(f"{rpath}: gravity.rotation is not a rotation")
        not_dynamic = set((report.get("outcome") or {}).get("not_dynamic", {}))
        out = []
        for e in entries:
            mesh_file = (e.get("files") or {}).get("mesh", f"meshes/{e['name']}.obj")
            mesh = load_mesh(folder / mesh_file, f"object {e['name']} of {rpath}")
            # exported = R @ capture, so capture = R^T @ exported (row vectors: v @ R)
            mesh.vertices = np.asarray(mesh.vertices, np.float64) @ R
            static = bool(e.get("static"))
            mass = (e.get("physics") or {}).get("mass_kg")
            cov = e.get("observed_coverage")
            out.append(PredictedObject(
                name=str(e["name"]), label=str(e.get("class", "")), mesh=mesh,
                role="static" if static else "dynamic", reason=e.get("static_reason") if static else None,
                # report.json's outcome: static objects it does not list as not dynamic are static furniture
                static_class=static and e["name"] not in not_dynamic,
                mass_kg=None if mass is None else float(mass),
                observed_coverage=None if cov is None or cov < 0 else float(cov)))
        out += [PredictedObject(name=str(s["name"]), label=str(s.get("class", "")), mesh=None, role="skipped",
                                reason=str(s.get("reason", ""))) for s in skipped]
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as e:
        raise PsimapError(f"{rpath}: not a psimap export report ({type(e).__name__}: {e})") from None
    return out


def read_gt_things(root, cameras, classes, *, seed: int = 0, progress: bool = False) -> list[GTThing]:
    """Every thing of DATA's ground truth (root: the scene folder; cameras: DATA's (K [3,3], c2w
    [4,4] OpenCV, width, height); classes: DATA's ClassInfo list, [] = every instance is a thing).
    Needs gt/objects/<id>.ply for each; gt/mesh.ply's per-face `instance` (optional) gives the
    observed parts."""
    from psimap.data.scene_format import read_gt
    from psimap.metrics.geometry import CameraVisibility

    gt_dir = Path(root) / "gt"
    if not (gt_dir / "objects").is_dir():
        raise PsimapError(f"{gt_dir / 'objects'} not found: object metrics need the complete GT object meshes")
    gt = read_gt(root)
    is_thing = {c.id: c.isthing for c in classes}
    class_name = {c.id: c.name for c in classes}
    rows = gt.instances or [{"id": i, "semantic": 0, "name": ""} for i in sorted(gt.objects)]
    rows = [r for r in rows if is_thing.get(r["semantic"], not classes)]
    if not rows:
        raise PsimapError(f"{gt_dir}: no thing instance to evaluate (gt/instances.json lists none of a thing class)")
    vis = None
    if gt.mesh is not None and gt.face_instance is not None and cameras:
        vis = CameraVisibility(gt.mesh, cameras, progress=progress)
        seen = vis.faces_seen()
        scene_v = np.asarray(gt.mesh.vertices, np.float64)
        scene_f = np.asarray(gt.mesh.faces, np.int64)
        scene_areas = face_areas(scene_v, scene_f)
    things = []
    for k, r in enumerate(sorted(rows, key=lambda r: r["id"])):
        iid = int(r["id"])
        if iid not in gt.objects:
            raise PsimapError(f"{gt_dir / 'objects' / f'{iid}.ply'} not found: thing {iid} "
                              f"({r.get('name') or class_name.get(r['semantic'], '')}) has no complete GT mesh")
        mesh = load_mesh(gt.objects[iid], f"GT object {iid}")
        observed, scene_area = None, 0.0
        if vis is not None:
            mine = gt.face_instance == iid
            scene_area = float(scene_areas[mine].sum())
            if scene_areas[mine & seen].sum() > 0:
                observed = SurfaceSamples(scene_v, scene_f, (seed, 2, k), face_mask=mine & seen,
                                          point_filter=vis.points_seen)
        mass = r.get("mass_kg")
        if mass is not None and not (isinstance(mass, (int, float)) and mass > 0):
            raise PsimapError(f"{gt_dir / 'instances.json'}: mass_kg of instance {iid} must be a positive number, "
                              f"got {mass!r}")
        things.append(GTThing(id=iid, label=class_name.get(r["semantic"], r.get("name", "")), name=r.get("name", ""),
                              mesh=mesh, observed=observed, scene_area=scene_area,
                              mass_kg=None if mass is None else float(mass)))
    return things


# --------------------------------------------------------------------------------------------------
# matching and metrics


def _boxes_near(a, b, margin: float) -> bool:
    """Whether the bounding boxes of meshes a and b come within `margin` of each other."""
    (alo, ahi), (blo, bhi) = np.asarray(a.bounds), np.asarray(b.bounds)
    return bool(np.all(alo <= bhi + margin) and np.all(blo <= ahi + margin))


class _Pairs:
    """Distances between the surfaces of predictions and GT things, measured once, on demand."""

    def __init__(self, preds: list[PredictedObject], things: list[GTThing], seed: int, max_samples: int):
        v = lambda m: np.asarray(m.vertices, np.float64)        # noqa: E731
        f = lambda m: np.asarray(m.faces, np.int64)             # noqa: E731
        self.max_samples = max_samples
        self.pred_samples = [SurfaceSamples(v(p.mesh), f(p.mesh), (seed, 0, i)) for i, p in enumerate(preds)]
        self.gt_samples = [SurfaceSamples(v(g.mesh), f(g.mesh), (seed, 1, j)) for j, g in enumerate(things)]
        self.pred_field = [raycasting_scene(v(p.mesh), f(p.mesh)) for p in preds]
        self.gt_field = [raycasting_scene(v(g.mesh), f(g.mesh)) for g in things]
        self.things = things
        self.cache: dict = {}

    def _get(self, what: str, i: int, j: int) -> np.ndarray:
        if (what, i, j) not in self.cache:
            if what == "precision":         # prediction i's points -> complete GT j
                samples, other = self.pred_samples[i], self.gt_field[j]
            elif what == "recall":          # complete GT j's points -> prediction i
                samples, other = self.gt_samples[j], self.pred_field[i]
            else:                           # observed part of GT j -> prediction i
                samples, other = self.things[j].observed, self.pred_field[i]
            self.cache[what, i, j] = distances_within_budget(samples, other, max_samples=self.max_samples)
        return self.cache[what, i, j]

    def share(self, what: str, i: int, j: int, t: float) -> float:
        d = self._get(what, i, j)
        return float(np.mean(d < t)) if len(d) else 0.0

    def score(self, i: int, j: int) -> float:
        """The matching score: F-score at MATCH_THRESHOLD, recall over the observed part."""
        recall = "observed" if self.things[j].observed is not None else "recall"
        return fscore(self.share("precision", i, j, MATCH_THRESHOLD), self.share(recall, i, j, MATCH_THRESHOLD))


def match_objects(preds: list[PredictedObject], things: list[GTThing], *, seed: int = 0,
                  max_samples: int = MAX_SAMPLES):
    """(score [P, G], {gt index: pred index} of the found things, _Pairs) for predictions with a mesh."""
    from scipy.optimize import linear_sum_assignment

    pairs = _Pairs(preds, things, seed, max_samples)
    score = np.zeros((len(preds), len(things)))
    for i, p in enumerate(preds):
        for j, g in enumerate(things):
            if _boxes_near(p.mesh, g.mesh, MATCH_THRESHOLD):
                score[i, j] = pairs.score(i, j)
    rows, cols = linear_sum_assignment(score, maximize=True)
    found = {int(j): int(i) for i, j in zip(rows, cols) if score[i, j] >= FOUND_SCORE}
    return score, found, pairs


def evaluate_objects(predicted: list[PredictedObject], things: list[GTThing], *, seed: int = 0,
                     max_samples: int = MAX_SAMPLES) -> dict:
    """{"per_object": one row per GT thing, "summary": {...}, "false_objects": [...]} (docs/metrics.md)."""
    preds = [p for p in predicted if p.mesh is not None]
    skipped = [p for p in predicted if p.mesh is None]
    score, found, pairs = match_objects(preds, things, seed=seed, max_samples=max_samples)
    rows = []
    for j, g in enumerate(things):
        i = found.get(j)
        best = int(score[:, j].argmax()) if len(preds) and score[:, j].max() > 0 else None
        row = {"id": g.id, "class": g.label, "name": g.name, "size_m": g.size, "seen_fraction": g.seen_fraction,
               "found": i is not None,
               # found: the score of its pair; missed: the best any prediction reaches (maybe paired elsewhere)
               "match_score": float(score[i, j] if i is not None else score[:, j].max(initial=0.0)),
               "best_candidate": preds[best].name if i is None and best is not None else None}
        for t in THRESHOLDS:
            p = pairs.share("precision", i, j, t) if i is not None else 0.0
            r = pairs.share("recall", i, j, t) if i is not None else 0.0
            c = pairs.share("observed", i, j, t) if i is not None and g.observed is not None else 0.0
            row.update({f"fscore_{key(t)}": fscore(p, r), f"precision_{key(t)}": p, f"recall_{key(t)}": r,
                        f"observed_completeness_{key(t)}": c if g.observed is not None else None})
        pred = preds[i] if i is not None else None
        row.update({"prediction": pred.name if pred else None, "role": pred.role if pred else "n/a",
                    "reason": pred.reason if pred else None, "static_class": bool(pred and pred.static_class),
                    "observed_coverage": pred.observed_coverage if pred else None,
                    "mass_kg": pred.mass_kg if pred else None, "gt_mass_kg": g.mass_kg,
                    "mass_error": None, "skipped_prediction": None})
        if row["mass_kg"] is not None and g.mass_kg:
            row["mass_error"] = (row["mass_kg"] - g.mass_kg) / g.mass_kg
        rows.append(row)
    _attribute_skipped(rows, skipped)
    false_objects = [p.name for i, p in enumerate(preds) if i not in set(found.values())]
    return {"per_object": rows, "summary": summarize_objects(rows, false_objects, len(predicted)),
            "false_objects": false_objects}


def _attribute_skipped(rows: list[dict], skipped: list[PredictedObject]) -> None:
    """A skipped prediction has no mesh: it is attributed by class to a missed GT thing (the largest
    one of its class not yet attributed), whose role becomes "skipped" with the reason and whose
    `skipped_prediction` names it."""
    for s in skipped:
        cands = [r for r in rows if not r["found"] and r["role"] == "n/a"
                 and r["class"].casefold() == s.label.casefold()]
        if cands:
            r = max(cands, key=lambda r: r["size_m"])
            r.update(role="skipped", reason=s.reason, skipped_prediction=s.name)


def summarize_objects(rows: list[dict], false_objects: list[str], n_predicted: int) -> dict:
    """The summary of the per-object rows (docs/metrics.md)."""
    found = [r for r in rows if r["found"]]
    movable = [r for r in found if r["role"] in ("dynamic", "static") and not r["static_class"]]
    mass_err = [abs(r["mass_error"]) for r in found if r["mass_error"] is not None]
    mean = lambda rs, k: float(np.mean([r[k] for r in rs])) if rs else None      # noqa: E731
    out = {"n_gt_things": len(rows), "n_found": len(found), "found_share": len(found) / len(rows) if rows else None,
           "n_movable_found": len(movable), "n_dynamic": sum(r["role"] == "dynamic" for r in movable),
           "dynamic_share": (sum(r["role"] == "dynamic" for r in movable) / len(movable)) if movable else None,
           "median_abs_mass_error": float(np.median(mass_err)) if mass_err else None, "n_mass_known": len(mass_err),
           "n_predicted": n_predicted, "n_false_objects": len(false_objects),
           "n_skipped": sum(r["role"] == "skipped" for r in rows)}
    for t in THRESHOLDS:
        out[f"mean_fscore_{key(t)}"] = mean(rows, f"fscore_{key(t)}")
        out[f"mean_fscore_{key(t)}_found"] = mean(found, f"fscore_{key(t)}")
    return out


# --------------------------------------------------------------------------------------------------
# reporting


def format_objects(result: dict) -> list[str]:
    """Lines of the objects section of `psimap eval`'s table."""
    def pct(v):
        return "n/a" if v is None else f"{100 * v:.0f}%"

    def num(v):
        return "n/a" if v is None else f"{v:.3f}"

    s = result["summary"]
    t1, t2 = (key(t) for t in THRESHOLDS)
    lines = [f"objects ({s['n_gt_things']} GT things, {s['n_predicted']} predicted; found = matched with "
             f"F@{MATCH_THRESHOLD * 100:g}cm >= {FOUND_SCORE})",
             f"  found {s['n_found']}/{s['n_gt_things']} ({pct(s['found_share'])})   dynamic "
             f"{s['n_dynamic']}/{s['n_movable_found']} of found movable ({pct(s['dynamic_share'])})",
             f"  mean F@{THRESHOLDS[0] * 100:g}cm {num(s[f'mean_fscore_{t1}'])} (found {num(s[f'mean_fscore_{t1}_found'])})"
             f"   mean F@{THRESHOLDS[1] * 100:g}cm {num(s[f'mean_fscore_{t2}'])} (found {num(s[f'mean_fscore_{t2}_found'])})",
             f"  median |mass error| {pct(s['median_abs_mass_error'])} ({s['n_mass_known']} known)   "
             f"false objects {s['n_false_objects']}" + (f": {', '.join(result['false_objects'])}"
                                                         if result["false_objects"] else ""),
             f"  {'id':>4} {'class':<14} {'size':>6}  {'found':<5} {'prediction':<18} {'F@1':>5} {'F@2.5':>5} "
             f"{'obs@1':>5} {'obs@2.5':>7}  {'role':<8} {'mass':>7} {'GT':>7}  reason"]
    for r in result["per_object"]:
        def m(v):
            return "" if v is None else f"{v:.3f}"
        obs = [r[f"observed_completeness_{k}"] for k in (t1, t2)]
        lines.append(f"  {r['id']:>4} {r['class'][:14]:<14} {r['size_m']:>5.2f}m  {'yes' if r['found'] else 'no':<5} "
                     f"{(r['prediction'] or r['skipped_prediction'] or '-')[:18]:<18} {r[f'fscore_{t1}']:>5.3f} {r[f'fscore_{t2}']:>5.3f} "
                     f"{m(obs[0]):>5} {m(obs[1]):>7}  {r['role']:<8} {m(r['mass_kg']):>7} {m(r['gt_mass_kg']):>7}  "
                     f"{r['reason'] or ''}")
    return lines


def plot_objects(result: dict, path) -> None:
    """PNG: each GT thing's F-score at both thresholds against its size; missed things marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

    from psimap.io_utils import save_figure

    rows = result["per_object"]
    size = np.array([r["size_m"] for r in rows])
    found = np.array([r["found"] for r in rows], dtype=bool)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for t, color in zip(THRESHOLDS, ("tab:blue", "tab:orange")):
        f = np.array([r[f"fscore_{key(t)}"] for r in rows])
        ax.scatter(size[found], f[found], color=color, label=f"F-score @ {t * 100:g} cm")
    if (~found).any():
        ax.scatter(size[~found], np.zeros((~found).sum()), marker="x", color="red", label="missed (counts 0)")
    for r in rows:
        ax.annotate(r["class"], (r["size_m"], r[f"fscore_{key(THRESHOLDS[-1])}"]), fontsize=7,
                    xytext=(3, 3), textcoords="offset points")
    s = result["summary"]
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))     # 0.1 0.2 0.5 1 2 m
    ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_ylim(-0.03, 1.05)
    ax.set_xlabel("GT object size (bounding-box diagonal, m)")
    ax.set_ylabel("F-score against the complete GT object")
    ax.set_title(f"found {s['n_found']}/{s['n_gt_things']}, mean F@1cm {s[f'mean_fscore_{key(THRESHOLDS[0])}']:.3f}, "
                 f"F@2.5cm {s[f'mean_fscore_{key(THRESHOLDS[1])}']:.3f}")
    ax.legend(loc="lower right")
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)
