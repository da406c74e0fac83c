"""`psimap eval PRED DATA`: geometry and/or panoptic metrics of a prediction against DATA's ground truth.

PRED is
- a mesh file (.ply .obj .glb .gltf .off .stl): geometry against DATA/gt/mesh.ply, GT culled to the
  surface DATA's cameras see;
- a trained checkpoint (.ckpt): its whole-scene mesh (`Scene.mesh()`), evaluated as above when
  DATA has gt/mesh.ply, and, when DATA has GT label maps and the checkpoint carries panoptic labels,
  the labels rendered from the scene for every frame of DATA (`psimap.panoptic.labels.render_labels`)
  scored as below;
  With predicted objects (`objects`: the CLI's --objects, which the entry points extract from the
  checkpoint), also the object metrics below;
- an export folder (report.json + meshes/, what `psimap export` writes): object metrics only
  (psimap.metrics.objects): every GT thing of DATA/gt/objects matched to an exported object;
- a folder of predicted labels: panoptic against DATA/gt/{semantic,instance}/<stem>.png, either
  COCO panoptic (`panoptic.json` + PNGs whose pixel id = R + 256 G + 256^2 B) or
  `semantic/<stem>.png` + `instance/<stem>.png` (uint16). Frames are matched by stem; a frame with
  no prediction counts as all void (and is reported).
"""
from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path

import numpy as np

from psimap import PsimapError
from psimap.metrics.geometry import load_mesh

MESH_SUFFIXES = (".ply", ".obj", ".glb", ".gltf", ".off", ".stl")
GEOMETRY_KEYS = ("accuracy", "completeness", "chamfer_l1", "precision", "recall", "f1", "threshold",
                 "n_pred_points", "n_gt_points", "gt_seen_fraction")
PANOPTIC_KEYS = ("pq", "sq", "rq", "miou", "macc", "mcov", "mwcov", "pq_frame", "pq_thing", "pq_stuff",
                 "n_frames", "n_gt_instances", "missing_frames", "unmatched_predictions")


# --------------------------------------------------------------------------------------------------
# reading predictions


def _read_panoptic_png(path: Path) -> np.ndarray:
    """COCO panoptic PNG -> [H, W] segment ids (R + 256 G + 256^2 B)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as img:
            rgb = np.asarray(img.convert("RGB")).astype(np.int64)
    except (UnidentifiedImageError, OSError) as e:
        raise PsimapError(f"cannot read panoptic PNG {path}: {e}") from None
    return rgb[..., 0] + 256 * rgb[..., 1] + 65536 * rgb[..., 2]


class _CocoPanoptic:
    """Predicted frames of a COCO panoptic folder: stem -> (semantic, instance) on demand."""

    def __init__(self, root: Path):
        jpath = root / "panoptic.json"
        try:
            meta = json.loads(jpath.read_text())
            anns = meta["annotations"]
            things = {int(c["id"]) for c in meta.get("categories", []) if c.get("isthing", True)}
            self.files: dict[str, tuple[Path, dict[int, int]]] = {}
            for a in anns:
                name = a["file_name"]
                cats = {int(s["id"]): int(s["category_id"]) for s in a["segments_info"]}
                self.files[Path(name).stem] = (self._find(root, name), cats)
        except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as e:
            raise PsimapError(f"{jpath}: not a COCO panoptic file ({type(e).__name__}: {e})") from None
        self.things = things

    @staticmethod
    def _find(root: Path, name: str) -> Path:
        for cand in (root / name, root / "panoptic" / name):
            if cand.is_file():
                return cand
        raise PsimapError(f"missing file: {root / name} (listed in {root / 'panoptic.json'})")

    def stems(self) -> set[str]:
        return set(self.files)

    def read(self, stem: str) -> tuple[np.ndarray, np.ndarray]:
        path, cats = self.files[stem]
        ids = _read_panoptic_png(path)
        seg_ids, inv = np.unique(ids, return_inverse=True)
        unknown = [int(s) for s in seg_ids if s != 0 and s not in cats]
        if unknown:
            raise PsimapError(f"{path}: segment id {unknown[0]} is not listed in panoptic.json")
        sem_of = np.array([cats.get(int(s), 0) for s in seg_ids], dtype=np.int64)
        # Stuff segments carry no instance id (one segment per class); thing segments keep theirs.
        inst_of = np.array([int(s) if cats.get(int(s), 0) in self.things else 0 for s in seg_ids],
                           dtype=np.int64)
        inv = inv.reshape(ids.shape)
        return sem_of[inv], inst_of[inv]


class _SemanticInstance:
    """Predicted frames as `semantic/<stem>.png` + `instance/<stem>.png`."""

    def __init__(self, root: Path):
        self.root = root
        self._stems = {p.stem for p in (root / "semantic").glob("*.png")}

    def stems(self) -> set[str]:
        return self._stems

    def read(self, stem: str) -> tuple[np.ndarray, np.ndarray]:
        from psimap.data.scene_format import read_label_png

        sem = read_label_png(self.root / "semantic" / f"{stem}.png")
        ipath = self.root / "instance" / f"{stem}.png"
        inst = read_label_png(ipath) if ipath.is_file() else np.zeros_like(sem)
        if inst.shape != sem.shape:
            raise PsimapError(f"{ipath} is {inst.shape[::-1]} pixels but its semantic map is {sem.shape[::-1]}")
        return sem, inst


def open_labels(root: str | os.PathLike):
    """A folder of predicted labels (COCO panoptic or semantic/ + instance/)."""
    root = Path(root)
    if (root / "panoptic.json").is_file():
        return _CocoPanoptic(root)
    if (root / "semantic").is_dir():
        return _SemanticInstance(root)
    raise PsimapError(f"{root}: a label folder needs panoptic.json (COCO panoptic) or semantic/ + instance/; "
                      f"an export folder needs report.json")


def is_export_folder(path: Path) -> bool:
    """Whether folder `path` is (or is meant as) an export folder rather than a label folder."""
    return (path / "report.json").is_file() or ((path / "meshes").is_dir() and not (path / "semantic").is_dir()
                                                and not (path / "panoptic.json").is_file())


# --------------------------------------------------------------------------------------------------
# evaluation


def _load_data(data):
    from psimap.data import load

    data = Path(data)
    if not data.exists():
        raise PsimapError(f"no such data folder: {data}")
    return load(data)


def cameras_of(seq) -> list:
    """DATA's cameras: (K [3,3], c2w [4,4] OpenCV, width, height) of every frame."""
    cameras = []
    for i in range(len(seq)):
        f = seq[i]
        cameras.append((f.K, f.c2w, f.width, f.height))
    return cameras


def evaluate_geometry(pred_mesh, data, *, threshold=0.05, samples=200_000, seed=0, plot=None,
                      progress=False) -> dict:
    """Geometry metrics of `pred_mesh` (trimesh) against DATA/gt/mesh.ply, GT culled by DATA's cameras."""
    from psimap.data.scene_format import read_gt
    from psimap.metrics.geometry import geometry_metrics, plot_geometry

    seq = _load_data(data)
    gt = read_gt(seq.root or data)
    if gt.mesh is None:
        raise PsimapError(f"{Path(seq.root or data) / 'gt' / 'mesh.ply'} not found: geometry needs the "
                          f"ground-truth mesh")
    cameras = cameras_of(seq)
    out, dist = geometry_metrics(pred_mesh, gt.mesh, threshold=threshold, cameras=cameras,
                                 max_samples=samples, seed=seed, progress=progress,
                                 return_distances=True)
    if plot:
        plot_geometry(dist, plot, threshold)
    return out


def gt_things(data, *, seed=0, progress=False) -> list:
    """DATA's ground-truth things for the object metrics (psimap.metrics.objects.read_gt_things);
    checked before any prediction is extracted."""
    from psimap.metrics.objects import read_gt_things

    seq = _load_data(data)
    return read_gt_things(seq.root or data, cameras_of(seq), seq.classes or [], seed=seed, progress=progress)


def evaluate_objects(predicted, things, *, seed=0, samples=200_000, plot=None) -> dict:
    """Object metrics of predicted objects (a list of psimap.metrics.objects.PredictedObject, or a
    callable returning one) against the GT things of `gt_things`; at most `samples` points per
    surface (psimap.metrics.objects.MAX_SAMPLES at most)."""
    from psimap.metrics.objects import MAX_SAMPLES, plot_objects
    from psimap.metrics.objects import evaluate_objects as object_metrics

    out = object_metrics(predicted() if callable(predicted) else predicted, things, seed=seed,
                         max_samples=min(int(samples), MAX_SAMPLES))
    if plot:
        plot_objects(out, plot)
    return out


def evaluate_panoptic(labels, data, *, progress=False, plot=None) -> dict:
    """Panoptic metrics of a predicted label folder (see `open_labels`) against DATA's GT label maps."""
    from tqdm import tqdm

    from psimap.metrics.panoptic import PanopticAccumulator

    seq = _load_data(data)
    labels = open_labels(labels) if isinstance(labels, (str, os.PathLike)) else labels
    things = [c.id for c in seq.classes if c.isthing] if seq.classes else None
    acc = PanopticAccumulator(things)
    stems = seq.names or [seq[i].name for i in range(len(seq))]
    have = labels.stems()
    missing = []
    for i in tqdm(range(len(seq)), desc="panoptic", unit="frame", disable=None if progress else True):
        f = seq[i]
        if f.gt_semantic is None:
            raise PsimapError(f"{Path(seq.root) / 'gt' / 'semantic' / (f.name + '.png')} not found: "
                              f"panoptic metrics need the ground-truth label maps")
        gt_inst = f.gt_instance if f.gt_instance is not None else np.zeros_like(f.gt_semantic)
        if f.name in have:
            sem, inst = labels.read(f.name)
            if sem.shape != f.gt_semantic.shape:
                raise PsimapError(f"predicted labels of frame {f.name} are {sem.shape[1]}x{sem.shape[0]} "
                                  f"pixels, ground truth is {f.width}x{f.height}")
        else:
            missing.append(f.name)
            sem = inst = np.zeros_like(f.gt_semantic)
        acc.add(sem, inst, f.gt_semantic, gt_inst, name=f.name)
    if len(missing) == len(seq):
        raise PsimapError(f"no predicted frame matches a frame of {data} (frames are matched by file stem)")
    out = acc.result()
    out["missing_frames"] = missing
    out["unmatched_predictions"] = sorted(have - set(stems))
    names = {c.id: c.name for c in seq.classes}
    for c, v in out["per_class"].items():
        v["name"] = names.get(c, "")
    if plot:
        plot_panoptic(out, plot, {c.id: c.name for c in seq.classes})
    return out


class _RenderedLabels:
    """Predicted frames rendered from a scene's hard labels, for the frames of DATA (matched by stem)."""

    def __init__(self, scene, seq):
        self.scene = scene
        self.views = {}
        for i in range(len(seq)):
            self.views[seq.names[i] if seq.names else seq[i].name] = i
        self.seq = seq

    def stems(self) -> set[str]:
        return set(self.views)

    def read(self, stem: str) -> tuple[np.ndarray, np.ndarray]:
        from psimap.panoptic.labels import render_labels

        f = self.seq[self.views[stem]]
        inst, sem = render_labels(self.scene, f.K, f.c2w, f.width, f.height)
        # Things take their instance's class by vote, as `psimap labels` writes them.
        for iid, cid in self.votes.items():
            sem[inst == iid] = cid
        return sem, inst

    @property
    def votes(self) -> dict[int, int]:
        if not hasattr(self, "_votes"):
            from psimap.panoptic.labels import instance_classes

            self._votes = instance_classes(self.scene)
        return self._votes


def _has_gt_labels(seq) -> bool:
    return len(seq) > 0 and seq[0].gt_semantic is not None


def evaluate_checkpoint(pred, data, *, threshold=0.05, samples=200_000, seed=0, plot=None,
                        progress=False, objects=None) -> dict:
    """Metrics of a scene.ckpt: geometry of its mesh (if DATA has gt/mesh.ply) and panoptic metrics of
    its rendered labels (if DATA has GT label maps and the checkpoint carries labels); with `objects`
    (its predicted objects, or a callable giving them: see evaluate_objects) the object metrics too."""
    from psimap.data.scene_format import read_gt
    from psimap.panoptic.labels import has_labels

    try:
        from psimap.scene import load_scene
    except ImportError:
        raise PsimapError("evaluating a checkpoint needs the training stage (psimap.scene)") from None
    things = gt_things(data, seed=seed, progress=progress) if objects is not None else None
    scene = load_scene(pred)
    seq = _load_data(data)
    root = Path(seq.root or data)
    do_geometry = read_gt(root).mesh is not None
    do_panoptic = _has_gt_labels(seq) and has_labels(scene) and bool(scene.classes)
    if len(seq) == 0:
        raise PsimapError(f"{root}: no frames to evaluate {pred} on")
    out = {}
    parts = [p for p, do in (("geometry", do_geometry), ("panoptic", do_panoptic), ("objects", things)) if do]

    def plot_of(part):         # one plot keeps the name asked for, several are told apart
        if part == "fit":       # the fit is beside any of them; alone, it is the plot asked for
            return plot_path(plot, part) if plot and parts else plot
        return plot_path(plot, part) if plot and len(parts) > 1 else plot

    if things is not None:
        out["objects"] = evaluate_objects(objects, things, seed=seed, samples=samples, plot=plot_of("objects"))
    if do_geometry:
        out["geometry"] = evaluate_geometry(scene.mesh(), data, threshold=threshold, samples=samples,
                                            seed=seed, plot=plot_of("geometry"), progress=progress)
    if do_panoptic:
        plot_pan = plot_of("panoptic")
        from psimap.threads import single_threaded

        with single_threaded():     # one label render per frame: spinning pools cost more than they give
            out["panoptic"] = evaluate_panoptic(_RenderedLabels(scene, seq), data, progress=progress,
                                                plot=plot_pan)
    from psimap.metrics.fit import evaluate_fit

    # no ground truth needed: how well the map fits the frames it came from (a real capture's only
    # quality figure before export)
    out["fit"] = evaluate_fit(scene, seq, progress=progress, plot=plot_of("fit"))
    return out


def plot_path(plot: str, part: str) -> str:
    """Where the `part` ("geometry" / "panoptic" / "objects" / "fit") plot goes when a checkpoint gets
    more than one plot."""
    return str(Path(plot).with_name(Path(plot).stem + "_" + part + Path(plot).suffix))


def evaluate(pred, data, *, threshold: float = 0.05, samples: int = 200_000, seed: int = 0,
             plot: str | None = None, progress: bool = False, objects=None) -> dict:
    """Metrics of `pred` against the ground truth of scene folder `data`.

    pred: a mesh file path, a trimesh.Trimesh, a `.ckpt` path, an export folder or a folder of
    predicted labels. Returns {"geometry": {...}} for meshes, {"panoptic": {...}} for label folders,
    {"objects": {...}} for export folders, and for checkpoints whichever DATA's ground truth and the
    checkpoint allow (both when possible) (keys: GEOMETRY_KEYS / PANOPTIC_KEYS, plus "per_class" for
    panoptic; psimap.metrics.objects.evaluate_objects for objects). `samples` caps the points sampled
    on each mesh (fewer are used once the error budget is met). objects: a checkpoint's predicted
    objects (list of psimap.metrics.objects.PredictedObject in DATA's frame, or a callable returning
    it, called once DATA's object ground truth is read): adds {"objects": ...}.
    """
    if not (threshold > 0 and math.isfinite(threshold)):
        raise PsimapError(f"threshold must be a positive number of metres, got {threshold}")
    if samples < 1:
        raise PsimapError(f"samples must be positive, got {samples}")
    kw = dict(progress=progress, plot=plot)
    if objects is not None and (hasattr(pred, "faces") or Path(pred).suffix.lower() != ".ckpt"):
        raise PsimapError("predicted objects go with a checkpoint (.ckpt); an export folder brings its own")
    if hasattr(pred, "faces"):
        return {"geometry": evaluate_geometry(pred, data, threshold=threshold, samples=samples, seed=seed, **kw)}
    pred = Path(pred)
    if not pred.exists():
        raise PsimapError(f"no such file or folder: {pred}")
    if pred.is_dir() and is_export_folder(pred):
        from psimap.metrics.objects import read_export

        things = gt_things(data, seed=seed, progress=progress)
        return {"objects": evaluate_objects(read_export(pred), things, seed=seed, samples=samples, plot=plot)}
    if pred.is_dir():
        return {"panoptic": evaluate_panoptic(pred, data, **kw)}
    suffix = pred.suffix.lower()
    if suffix == ".ckpt":
        return evaluate_checkpoint(pred, data, threshold=threshold, samples=samples, seed=seed, objects=objects, **kw)
    if suffix in MESH_SUFFIXES:
        mesh = load_mesh(pred)
    else:
        raise PsimapError(f"{pred}: PRED must be a mesh ({', '.join(MESH_SUFFIXES)}), a .ckpt or a label folder")
    return {"geometry": evaluate_geometry(mesh, data, threshold=threshold, samples=samples, seed=seed, **kw)}


# --------------------------------------------------------------------------------------------------
# reporting


def plot_panoptic(result: dict, path, class_names: dict[int, str] | None = None) -> None:
    """PNG: per-class PQ / SQ / RQ and semantic IoU."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from psimap.io_utils import save_figure

    per = result["per_class"]
    cls = sorted(per)
    names = [(class_names or {}).get(c, str(c)) for c in cls]
    x = np.arange(len(cls))
    fig, ax = plt.subplots(figsize=(max(6, 0.6 * len(cls) + 2), 4))
    for k, (key, label) in enumerate((("pq", "PQ"), ("sq", "SQ"), ("rq", "RQ"), ("iou", "IoU"))):
        ax.bar(x + (k - 1.5) * 0.2, [per[c][key] for c in cls], 0.2, label=label)
    ax.set_xticks(x, names, rotation=45, ha="right")
    ax.set_ylim(0, 1.02)
    ax.legend()
    ax.set_title(f"scene PQ {result['pq']:.3f} (per-frame {result['pq_frame']:.3f}), mIoU {result['miou']:.3f}")
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)


def _jsonable(v):
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return None if not math.isfinite(v) else float(v)
    return v


def to_json(result: dict) -> str:
    """The metrics as JSON (undefined values -> null)."""
    out = {}
    if "geometry" in result:
        out["geometry"] = {k: result["geometry"][k] for k in GEOMETRY_KEYS if k in result["geometry"]}
    if "panoptic" in result:
        p = result["panoptic"]
        out["panoptic"] = {k: p[k] for k in PANOPTIC_KEYS if k in p}
        out["panoptic"]["per_class"] = p.get("per_class", {})
    if "objects" in result:
        out["objects"] = result["objects"]
    if "fit" in result:
        from psimap.metrics.fit import FIT_KEYS

        out["fit"] = {k: result["fit"][k] for k in (*FIT_KEYS, "per_frame")}
    return json.dumps(_jsonable(out), indent=1)


def format_table(result: dict) -> str:
    """A readable table of the metrics."""
    def f(v, unit=""):
        if v is None or (isinstance(v, float) and not math.isfinite(v)):
            return "n/a"
        return f"{v * 100:.2f} cm" if unit == "m" else f"{v:.4f}"

    lines = []
    if "geometry" in result:
        g = result["geometry"]
        lines += ["geometry", f"  accuracy      {f(g['accuracy'], 'm')}   (pred -> GT, mean)",
                  f"  completeness  {f(g['completeness'], 'm')}   (seen GT -> pred, mean)",
                  f"  chamfer-L1    {f(g['chamfer_l1'], 'm')}",
                  f"  precision     {f(g['precision'])}   @ {g['threshold'] * 100:g} cm",
                  f"  recall        {f(g['recall'])}",
                  f"  F1            {f(g['f1'])}",
                  f"  points        {g['n_pred_points']} pred, {g['n_gt_points']} GT "
                  f"({g.get('gt_seen_fraction', 1.0) * 100:.1f}% of GT area seen)"]
    if "panoptic" in result:
        p = result["panoptic"]
        lines += ["panoptic (scene level: ids must agree across frames)",
                  f"  PQ {f(p['pq'])}   SQ {f(p['sq'])}   RQ {f(p['rq'])}   "
                  f"(things {f(p['pq_thing'])}, stuff {f(p['pq_stuff'])})",
                  f"  per-frame PQ  {f(p['pq_frame'])}",
                  f"  mIoU {f(p['miou'])}   mAcc {f(p['macc'])}",
                  f"  mCov {f(p['mcov'])}   mW-Cov {f(p['mwcov'])}   ({p['n_gt_instances']} GT instances)",
                  f"  frames {p['n_frames']}"]
        if p.get("missing_frames"):
            lines.append(f"  {len(p['missing_frames'])} frames had no prediction (counted as void): "
                         + ", ".join(p["missing_frames"][:5]) + (" ..." if len(p["missing_frames"]) > 5 else ""))
        if p.get("unmatched_predictions"):
            lines.append(f"  {len(p['unmatched_predictions'])} predicted frames match no DATA frame (ignored)")
        if p.get("per_class"):
            lines.append("  class              PQ      SQ      RQ      IoU     TP  FP  FN")
            for c, v in sorted(p["per_class"].items()):
                label = f"{c} {v.get('name', '')}"[:16]
                lines.append(f"  {label:<16}{'*' if v['isthing'] else ' '} {v['pq']:.4f}  {v['sq']:.4f}  "
                             f"{v['rq']:.4f}  {f(v['iou'])}  {v['tp']:<3} {v['fp']:<3} {v['fn']:<3}")
            lines.append("  (* = thing class)")
    if "objects" in result:
        from psimap.metrics.objects import format_objects

        lines += format_objects(result["objects"])
    if "fit" in result:
        from psimap.metrics.fit import format_fit

        lines += format_fit(result["fit"])
    return "\n".join(lines)


def cli_eval(opts, objects=None) -> int:
    """`psimap eval PRED DATA [--json] [--objects]`. objects: the checkpoint's predicted objects, or a
    callable giving them (the entry point extracts them: psimap.cli.run_eval)."""
    if getattr(opts, "plot", ""):
        from psimap.io_utils import check_output_file

        for p in (opts.plot, *(plot_path(opts.plot, part) for part in ("geometry", "panoptic", "objects", "fit"))):
            check_output_file(p, overwrite=opts.overwrite, what="--plot")     # before the work
    if getattr(opts, "objects", False):
        pred = Path(opts.pred)
        if pred.suffix.lower() != ".ckpt" and not (pred.is_dir() and is_export_folder(pred)):
            raise PsimapError(f"{pred}: --objects needs a checkpoint (.ckpt) or an export folder")
        if pred.suffix.lower() == ".ckpt" and objects is None:
            raise PsimapError("--objects on a checkpoint needs the entry point that extracts its objects "
                              "(psimap.cli.run_eval)")
    result = evaluate(opts.pred, opts.data, threshold=opts.threshold, samples=opts.samples,
                      seed=opts.seed, plot=getattr(opts, "plot", "") or None, progress=True, objects=objects)
    print(to_json(result) if opts.json else format_table(result))
    if result.get("panoptic", {}).get("missing_frames") and opts.json:
        print(f"warning: {len(result['panoptic']['missing_frames'])} frames had no prediction "
              f"(counted as all void)", file=sys.stderr)
    return 0
