"""Options of every `psimap` command: one dataclass per command, defaults and help text in one place.

This module must stay light (stdlib only): `psimap --help` builds its parser from it.
Positional arguments are fields with ``metadata={"positional": True}``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

# stdlib-only registries: the names of the writers and of the completion methods (a writer or a
# method's code is imported only when it runs)
from psimap.completion.methods import Choices, method_names
from psimap.exporters.formats import FORMATS


def opt(default, help: str, **extra):
    """A dataclass field carrying its CLI help text."""
    return field(default=default, metadata={"help": help, **extra})


def overwrite_opt(what: str):
    """--overwrite of a command whose output is a folder, a file or a plot (psimap.io_utils rules)."""
    text = {"folder": "write into --out even when it holds files psimap did not write (files of the same name "
                      "are replaced; nothing else is deleted)",
            "file": "replace --out even when it is a file psimap did not write",
            "plot": "replace --plot even when it is a file psimap did not write"}[what]
    return opt(False, text)


def pos(help: str, **extra):
    """A required positional CLI argument."""
    return field(default=None, metadata={"help": help, "positional": True, **extra})


@dataclass
class GenerateOptions:
    out: str = pos("output folder for the synthetic scene (docs/scene-format.md)")
    seed: int = opt(0, "random seed: the same seed gives the same scene")
    frames: int = opt(60, "number of camera frames")
    width: int = opt(160, "image width in pixels")
    height: int = opt(120, "image height in pixels")
    layout: str = opt("room", "room: furniture and small objects in a room; tabletop: things on a table in a "
                              "room, filmed by a hand-held orbit around the table", choices=["room", "tabletop"])
    objects: int = opt(0, "number of objects (0 = random: 5..15 in a room, 4..8 on the table besides the table)")
    noise: float = opt(0.15, "pseudo-label noise rate (merges, splits, misses, flips), 0..1")
    lidar: bool = opt(False, "also write a LiDAR sweep with intensity")
    pose_noise: float = opt(0.0, "std of pose noise (metres / radians) applied to the written poses")
    overwrite: bool = overwrite_opt("folder")


@dataclass
class EvalOptions:
    pred: str = pos("scene.ckpt, a mesh file (.ply/.obj/.glb), an export folder (report.json + meshes/: "
                    "object metrics) or a folder of predicted label PNGs")
    data: str = pos("the capture: ground truth under gt/ gives geometry / panoptic / object metrics; a "
                    "checkpoint is also measured against the capture's own frames (depth error, coverage, "
                    "PSNR), which needs no ground truth")
    json: bool = opt(False, "print the metrics as JSON")
    threshold: float = opt(0.05, "distance threshold for the geometry's precision / recall / F1, metres "
                                 "(objects: always 1 and 2.5 cm)")
    samples: int = opt(200_000, "at most this many points sampled on each mesh (fewer once the "
                                "metrics' standard error is within budget)")
    seed: int = opt(0, "seed for the surface sampling")
    objects: bool = opt(False, "with a checkpoint: also object metrics (its objects extracted as `psimap export` "
                               "does, matched to DATA's gt/objects: found, F-score at 1 and 2.5 cm, "
                               "docs/metrics.md); an export folder gets them anyway")
    plot: str = opt("", "also write a PNG: P/R/F1 vs threshold (mesh), per-class PQ/IoU (labels) or F-score "
                        "vs object size (objects); a checkpoint's plots get _geometry / _panoptic / _objects "
                        "added to the name when it has more than one")
    overwrite: bool = overwrite_opt("plot")


@dataclass
class DemoOptions:
    out: str = opt("psimap_demo", "output folder")
    seed: int = opt(0, "random seed")
    frames: int = opt(60, "frames of the generated synthetic scene")
    width: int = opt(160, "image width of the generated scene")
    height: int = opt(120, "image height of the generated scene")
    iters: int = opt(0, "geometry training steps (0 = the training default)")
    panoptic_iters: int = opt(-1, "joint panoptic steps (-1 = the training default)")
    overwrite: bool = overwrite_opt("folder")


@dataclass
class TrainOptions:
    data: str = pos("capture folder: scene format or nerfstudio transforms.json, ScanNet, Replica, 7-Scenes, "
                          "TUM RGB-D or BOP layout (docs/scene-format.md)")
    out: str = opt("scene.ckpt", "checkpoint to write")
    iters: int = opt(0, "training iterations (0 = the config default)")
    seed: int = opt(0, "random seed")
    resume: str = opt("", "checkpoint to resume from (its surfels; --iters more steps)")
    no_prior: bool = opt(False, "train without the SOGMM prior (plain 2DGS losses; a baseline)")
    fast: bool = opt(False, "no effect (kept for older scripts): training always uses every core and "
                            "stays bit-reproducible")
    no_lidar: bool = opt(False, "ignore the LiDAR sweeps the frames carry (default: they join the prior "
                                "and a range term)")
    overwrite: bool = overwrite_opt("file")


@dataclass
class MeshOptions:
    ckpt: str = pos("trained scene checkpoint")
    out: str = opt("mesh.ply", "mesh file to write")
    voxel: float = opt(0.0, "TSDF voxel size in metres (0 = from the scene's pixel footprint)")
    overwrite: bool = overwrite_opt("file")


@dataclass
class ExportOptions:
    ckpt: str = pos("trained scene checkpoint")
    format: str = opt("mjcf", "output format (all = every one)", choices=[*FORMATS, "all"])
    out: str = opt("export", "output folder")
    completion: str = opt("auto", "object completion: auto (the methods tier by tier, the first that fits), "
                                  "none, or one method for every object (kept when it gives a closed shape, "
                                  "else the object is closed as observed): "
                                  f"{', '.join(method_names(selectable=True, installed=False))} or one an "
                                  "installed package adds (entry-point group psimap.completion)",
                          choices=Choices(), metavar="METHOD")
    no_check: bool = opt(False, "skip the MuJoCo simulation check")
    no_preview: bool = opt(False, "write no preview.png / report.html (MuJoCo's offscreen pictures of the scene "
                                  "before and after the settle; a second or two on a room)")
    densities: str = opt("", "JSON file {class name: kg/m^3} overriding the default density table")
    static_classes: str = opt("", "comma-separated classes exported static (no freejoint / rigid body); "
                                  "default: heavy furniture (table, cabinet, shelf, ...); 'none' = all dynamic")
    dynamic_all: bool = opt(False, "export every object as a dynamic rigid body (no static furniture, "
                                    "barely seen objects too)")
    no_pin_unstable: bool = opt(False, "keep objects that do not rest stably in the settle check dynamic "
                                       "(the check then fails) instead of exporting them static")
    min_dynamic: float = opt(0.5, "fail (exit 2) when fewer than this share of the things found, those not "
                                  "static by class, come out dynamic (pinned, skipped or too little "
                                  "evidence); 0 = never")
    up: str = opt("auto", "which way is up in the capture: auto (estimated from its supports, walls and "
                          "cameras), or +z, -z, +y, -y, +x, -x, or a vector 'x,y,z'; the scene is exported "
                          "Z-up and the rotation recorded in report.json")
    overwrite: bool = overwrite_opt("folder")
    check_engine: str = opt("mujoco", "engines that settle the exported scene: mujoco (scene.xml; this check "
                                      "also nudges and pins objects), newton (also scene.usda in Newton on the "
                                      "CPU: pip install 'psimap[newton]'; report.json check_newton), all",
                            choices=["mujoco", "newton", "all"])


@dataclass
class LabelsOptions:
    ckpt: str = pos("trained scene checkpoint")
    data: str = pos("scene folder whose cameras to render")
    out: str = opt("labels", "output folder (COCO panoptic)")
    topk: int = opt(0, "blend only the K largest weights per pixel (faster, see benchmarks/panoptic.py's "
                       "Top-K curve); 0 = all")
    overwrite: bool = overwrite_opt("folder")


@dataclass
class SegmentOptions:
    data: str = pos("capture folder without labels (any layout psimap reads)")
    up: str = opt("auto", "which way is up in the capture: auto (estimated from its surfaces and cameras), "
                          "or +z, -z, +y, -y, +x, -x, or a vector 'x,y,z'")
    every: int = opt(0, "label every N-th frame (1 = all; the others stay unlabelled); 0 = the frames "
                        "psimap train reads: all of a capture up to 300 frames, else 300 evenly spaced")
    force: bool = opt(False, "replace the capture's existing labels")
    preview: str = opt("", "contact sheet PNG of a few frames and their labels (default: DATA/segment_preview.png)")
    no_preview: bool = opt(False, "write no contact sheet")
    noise_k: float = opt(3.0, "plane and depth-edge thresholds, in depth-noise std at the pixel's range")
    min_wall_area: float = opt(0.8, "m^2 of one connected vertical plane piece for it to be a wall")
    min_support_area: float = opt(0.15, "m^2 of one connected up-facing plane piece above the floor for it "
                                        "to be a support (table or counter top)")
    colour_edge: float = opt(0.0, "also split clusters at RGB steps larger than this (0..1.7; 0 = off)")
    min_pixels: int = opt(0, "smallest object cluster in pixels (0 = image pixels / 4000, at least 6)")


@dataclass
class ImportMasksOptions:
    data: str = pos("capture folder (any layout psimap reads) to add per-frame labels to (labels.json)")
    masks: str = opt("", "the segmenter's output: a COCO panoptic or instances JSON (or the folder holding it), "
                         "a SAM amg.py output folder, or SAM JSON lists (docs/scene-format.md)", required=True)
    format: str = opt("auto", "mask format (auto: from what --masks holds)",
                      choices=["auto", "coco-panoptic", "coco-instances", "sam"])
    classes: str = opt("", "class mapping JSON: {\"classes\": {source name or id: class name | "
                           "{\"name\", \"isthing\"} | null}, \"unmapped\": rule}")
    unmapped: str = opt("", "rule for categories the mapping does not name: keep (their own name), object "
                            "(things -> object, stuff -> void), void, error (default: the mapping file's, "
                            "else keep)", choices=["", "keep", "object", "void", "error"])
    images: str = opt("", "COCO JSON whose images[] and categories a COCO results list (no images of its "
                          "own) refers to")
    min_area: float = opt(0.0005, "drop masks (and what is left visible of them) under this many pixels; "
                                  "below 1: a share of the image")
    min_score: float = opt(0.5, "drop masks whose score (detection score, or SAM predicted_iou x "
                                "stability_score) is below this; masks without a score count as 1")
    resize: bool = opt(False, "resize masks of another size than the frame to it (nearest neighbour; same "
                              "aspect ratio), e.g. masks of ScanNet's colour images")
    force: bool = opt(False, "replace labels the capture already has (labels.json, semantic/, instance/)")


@dataclass
class BatchOptions:
    manifest: str = pos("TOML or JSON file listing the captures (folders or globs) and their options "
                        "(docs/batch.md)")
    out: str = opt("", "output folder: one folder per capture (checkpoint, export, log) and summary.json",
                   required=True)
    scheduler: str = opt("", "address of a running Dask scheduler (e.g. tcp://host:8786; DIR and the "
                             "captures must be on a filesystem its workers share); default: a local cluster")
    workers: int = opt(0, "local cluster: worker processes (0 = cores / --threads-per-worker)")
    threads_per_worker: int = opt(1, "threads each worker has and each task uses (torch, the native "
                                     "kernels, BLAS); a worker runs one task at a time")


@dataclass
class CheckOptions:
    out: str = pos("export folder (psimap export --out) holding scene.xml and / or scene.usda; never modified")
    engine: str = opt("mujoco", "mujoco settles scene.xml, newton scene.usda (pip install 'psimap[newton]'), "
                                "all both", choices=["mujoco", "newton", "all"])
    json: bool = opt(False, "print the reports as JSON")
    duration: float = opt(2.0, "simulated seconds of the settle")
    max_drift: float = opt(0.01, "metres a resting object may move in the settle")
