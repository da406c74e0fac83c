"""`psimap segment` benchmark: the model-free segmenter's pseudo-labels against ground truth, beside the
generator's own noisy labels, and its time per frame.

Per frame: class-agnostic things PQ (every GT thing instance, furniture included, against the object
clusters; classes ignored, stuff kept apart), floor and wall IoU. With --train: PQ^scene after
`psimap train` on the segmenter's labels vs on the generator's noisy labels (same capture, same
options), class-agnostic too (the segmenter names no classes). With the shared 7-Scenes chess frames
(../shared, skipped when absent): frames/s at 640x480 and what it finds, and a contact sheet.

Run: .venv/bin/python benchmarks/segment.py [--quick] [--train [--train-seeds 0 1 2 3 4]] [--no-write]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import markdown_table, save_plot, write_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CHESS = ROOT.parent / "shared" / "data" / "7scenes-chess"
# class-agnostic ids both sides are mapped to
THING, FLOOR, WALL, CEILING, OTHER = 1, 2, 3, 4, 5
STUFF_OF = {"floor": FLOOR, "wall": WALL, "ceiling": CEILING}
# the generator's furniture classes (psimap.data.synthetic_shapes.FURNITURE)
FURNITURE = ("table", "chair", "shelf", "cabinet")


def agnostic(semantic, instance, classes) -> tuple[np.ndarray, np.ndarray]:
    """(semantic, instance) with every thing class -> THING and floor / wall / ceiling -> their ids;
    other stuff (the segmenter's support) -> OTHER; instance ids kept on things only."""
    lut = np.zeros(int(max([c.id for c in classes] + [int(semantic.max())])) + 1, np.int64)
    for c in classes:
        lut[c.id] = THING if c.isthing else STUFF_OF.get(c.name, OTHER)
    sem = lut[semantic.astype(np.int64)]
    return sem, np.where(sem == THING, instance, 0)


def small_only(gt_sem, gt_inst, gt_classes) -> tuple[np.ndarray, np.ndarray]:
    """GT (agnostic ids) with furniture made void: things PQ over the small things alone (a prediction
    lying mostly on a table is then neither a match nor a false positive)."""
    furniture = [c.id for c in gt_classes if c.name in FURNITURE]
    return np.where(np.isin(gt_sem, furniture), 0, gt_sem), np.where(np.isin(gt_sem, furniture), 0, gt_inst)


def things_pq(pairs) -> dict:
    """Things PQ, and floor / wall IoU, of [(pred sem, pred inst, gt sem, gt inst)] (agnostic ids)."""
    from psimap.metrics.panoptic import panoptic_metrics

    r = panoptic_metrics(pairs, thing_classes=[THING])
    pc = r["per_class"]
    return {"pq": pc.get(THING, {}).get("pq", float("nan")), "floor_iou": pc.get(FLOOR, {}).get("iou", float("nan")),
            "wall_iou": pc.get(WALL, {}).get("iou", float("nan"))}


def per_frame_pq(frames) -> float:
    vals = [things_pq([f])["pq"] for f in frames]
    vals = [v for v in vals if not np.isnan(v)]
    return float(np.mean(vals)) if vals else float("nan")


def rotate_capture(src: Path, dst: Path, R: np.ndarray) -> None:
    """A copy of scene-format capture `src` whose world is turned by R [3, 3] (poses only: the
    per-frame images and labels do not change, the world frame does)."""
    shutil.copytree(src, dst)
    meta = json.loads((dst / "transforms.json").read_text())
    T = np.eye(4)
    T[:3, :3] = R
    for fr in meta["frames"]:
        fr["transform_matrix"] = (T @ np.asarray(fr["transform_matrix"])).tolist()
    (dst / "transforms.json").write_text(json.dumps(meta))


def run_capture(path: Path) -> dict:
    """Segment every frame of the generated capture at `path` in process; score against its GT."""
    from psimap.data import load
    from psimap.data.frames import ClassInfo
    from psimap.segment.capture import survey
    from psimap.segment.frame import CLASS_TABLE, segment_frame

    seq = load(path)
    ours = [ClassInfo(i, n, t) for i, n, t in CLASS_TABLE]
    c0 = time.process_time()
    capture, found = survey(seq, list(range(0, len(seq), max(1, len(seq) // 24))))
    survey_cpu = time.process_time() - c0
    seg, ref, seg_small, ref_small, cpu, objects = [], [], [], [], [], []
    for i in range(len(seq)):
        f = seq[i]
        c0 = time.process_time()
        sem, inst, info = segment_frame(f.depth, f.rgb, f.K, f.c2w, capture, seed=i)
        cpu.append(time.process_time() - c0)
        objects.append(info["objects"])
        gt = agnostic(f.gt_semantic, f.gt_instance, seq.classes)
        gt_small = agnostic(*small_only(f.gt_semantic, f.gt_instance, seq.classes), seq.classes)
        p_seg, p_ref = agnostic(sem, inst, ours), agnostic(f.semantic, f.instance, seq.classes)
        seg.append((*p_seg, *gt))
        ref.append((*p_ref, *gt))
        seg_small.append((*p_seg, *gt_small))
        ref_small.append((*p_ref, *gt_small))
    s, r = things_pq(seg), things_pq(ref)
    return {"frames": len(seq), "size": f"{seq[0].width}x{seq[0].height}", "up": found["up"],
            "pq_frame": per_frame_pq(seg), "ref_pq_frame": per_frame_pq(ref),
            "small_pq_frame": per_frame_pq(seg_small), "ref_small_pq_frame": per_frame_pq(ref_small),
            "floor_iou": s["floor_iou"], "wall_iou": s["wall_iou"],
            "ref_floor_iou": r["floor_iou"], "ref_wall_iou": r["wall_iou"],
            "objects": float(np.mean(objects)), "ms": 1000 * float(np.mean(cpu)), "survey_s": survey_cpu}


def psimap(*args, log=None) -> float:
    """Run the CLI; its wall seconds."""
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "psimap", *map(str, args)], cwd=ROOT, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"psimap {' '.join(map(str, args))} failed:\n{r.stderr[-2000:]}")
    if log:
        log.write(r.stdout + r.stderr)
    return time.perf_counter() - t0


def scene_pq(ckpt: Path, data: Path) -> dict:
    """Class-agnostic scene-level PQ (ids consistent across frames) of a checkpoint's rendered labels."""
    from psimap.data import load
    from psimap.data.frames import ClassInfo
    from psimap.panoptic.labels import render_labels
    from psimap.scene import load_scene
    from psimap.threads import single_threaded

    scene = load_scene(ckpt)
    classes = [ClassInfo(int(c["id"]), str(c["name"]), bool(c["isthing"])) for c in scene.classes]
    seq = load(data)
    pairs, small = [], []
    with single_threaded():
        for i in range(len(seq)):
            f = seq[i]
            inst, sem = render_labels(scene, f.K, f.c2w, f.width, f.height)
            pred = agnostic(sem, inst, classes)
            pairs.append((*pred, *agnostic(f.gt_semantic, f.gt_instance, seq.classes)))
            small.append((*pred, *agnostic(*small_only(f.gt_semantic, f.gt_instance, seq.classes), seq.classes)))
    r = things_pq(pairs)
    return {"pq_things": r["pq"], "small_pq_things": things_pq(small)["pq"], "floor_iou": r["floor_iou"],
            "wall_iou": r["wall_iou"]}


def run_train(scene: Path, work: Path, log) -> dict:
    """Train on the generator's noisy labels and on the segmenter's (a copy whose labels the segmenter
    replaces, --force), same options."""
    out = {}
    seg = work / (scene.name + "_seg")
    shutil.copytree(scene, seg)
    t_seg = psimap("segment", seg, "--no-preview", "--force", log=log)
    for label, data in (("noisy", scene), ("segment", seg)):
        ckpt = work / f"{scene.name}_{label}.ckpt"
        wall = psimap("train", data, "--out", ckpt, log=log)
        out[label] = scene_pq(ckpt, scene) | {"train_s": wall}
    out["segment_s"] = t_seg
    return out


def run_chess(work: Path, frames: int) -> dict | None:
    """The shared 7-Scenes chess frames (a scratch copy): frames/s and what the segmenter finds."""
    if not CHESS.is_dir():
        return None
    copy = work / "chess"
    copy.mkdir()
    for p in sorted(CHESS.iterdir()):
        if p.name.startswith("frame-") and int(p.name[6:12]) >= frames:
            continue
        shutil.copy2(p, copy / p.name)
    from psimap.segment.capture import segment_capture

    sheet = work / "chess_sheet.png"
    c0 = time.process_time()
    # a small sheet (three frames, low resolution): it is committed beside RESULTS.md
    s = segment_capture(copy, preview=str(sheet), progress=False, preview_frames=3, preview_dpi=40)
    s["cpu_s"] = time.process_time() - c0
    s["sheet"] = sheet
    return s


def plot(rows):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    names = [r["capture"] for r in rows]
    x = np.arange(len(rows))
    ax[0].bar(x - 0.2, [r["pq_frame"] for r in rows], 0.4, label="psimap segment")
    ax[0].bar(x + 0.2, [r["ref_pq_frame"] for r in rows], 0.4, label="generator's noisy labels")
    ax[0].set_xticks(x, names, rotation=20, fontsize=7)
    ax[0].set_ylabel("things PQ per frame (class-agnostic)")
    ax[0].set_ylim(0, 1)
    ax[0].legend(fontsize=7)
    ax[1].bar(x, [r["ms"] for r in rows])
    ax[1].set_xticks(x, names, rotation=20, fontsize=7)
    ax[1].set_ylabel("segmenter CPU ms / frame")
    fig.tight_layout()
    return fig


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one room, one tabletop, 24 frames; no chess")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--train", action="store_true", help="also train on both label sets (rooms and tabletops "
                                                         "of --train-seeds: ~15 s per training)")
    ap.add_argument("--train-seeds", type=int, nargs="+", default=None,
                    help="seeds of the captures --train trains on (default: the first of --seeds)")
    ap.add_argument("--train-from", default="", help="JSON of an earlier --train run's results (printed as "
                                                     "'train: {...}'): reuse them instead of training")
    ap.add_argument("--chess-frames", type=int, default=150)
    ap.add_argument("--no-write", action="store_true", help="print only")
    args = ap.parse_args(argv)
    from psimap.data.synthetic import generate

    work = Path(tempfile.mkdtemp(prefix="psimap_bench_segment_"))
    frames = 24 if args.quick else 60
    seeds = args.seeds[:1] if args.quick else args.seeds
    rows, caps = [], {}
    try:
        for layout in ("room", "tabletop"):
            for seed in seeds:
                path = work / f"{layout}{seed}"
                generate(path, seed=seed, frames=frames, layout=layout, progress=False)
                caps[(layout, seed)] = path
                rows.append({"capture": f"{layout} {seed}"} | run_capture(path))
                print(rows[-1], flush=True)
        # the same room in a Y-up world (a phone capture's frame): the labels must not change much
        turned = work / "room0_yup"
        rotate_capture(caps[("room", seeds[0])], turned, np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]))
        rows.append({"capture": f"room {seeds[0]} Y-up"} | run_capture(turned))
        print(rows[-1], flush=True)
        train = json.loads(Path(args.train_from).read_text()) if args.train_from else {}
        if args.train and not train:
            with open(work / "train.log", "w") as log:
                for layout in ("room", "tabletop"):
                    for seed in args.train_seeds or seeds[:1]:
                        path = caps.get((layout, seed))
                        if path is None:
                            path = work / f"{layout}{seed}"
                            generate(path, seed=seed, frames=frames, layout=layout, progress=False)
                        train[f"{layout} {seed}"] = run_train(path, work, log)
                        print(layout, seed, train[f"{layout} {seed}"], flush=True)
            print("train:", json.dumps(train), flush=True)
        chess = None if args.quick else run_chess(work, args.chess_frames)
        report(rows, train, chess, args, seeds, frames)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def report(rows, train, chess, args, seeds, frames) -> None:
    table = markdown_table(
        ["capture", "frames", "size", "things PQ/frame: segment", "noisy labels", "small things: segment",
         "noisy labels", "floor IoU", "wall IoU", "objects/frame", "CPU ms/frame"],
        [[r["capture"], r["frames"], r["size"], f"{r['pq_frame']:.3f}", f"{r['ref_pq_frame']:.3f}",
          f"{r['small_pq_frame']:.3f}", f"{r['ref_small_pq_frame']:.3f}",
          f"{r['floor_iou']:.3f}", f"{r['wall_iou']:.3f}", f"{r['objects']:.1f}", f"{r['ms']:.0f}"] for r in rows])
    gen = [r for r in rows if "Y-up" not in r["capture"]]
    mean = {k: float(np.mean([r[k] for r in gen]))
            for k in ("pq_frame", "ref_pq_frame", "small_pq_frame", "ref_small_pq_frame", "ms")}
    body = [table, "",
            f"Generated captures ({frames} frames, 160x120, seeds {seeds}, 15 % label noise on the reference), "
            "every frame segmented in process. Things PQ is class-agnostic: every GT thing instance (furniture "
            "included) against the object clusters; the segmenter's support (table and counter tops with "
            "what hangs from them) is stuff, so a table counts as a miss. Small things: the same with the "
            "GT furniture (table, chair, shelf, cabinet) made void. CPU ms per frame excludes loading "
            f"and the capture-wide survey. Mean over the generated captures: segment {mean['pq_frame']:.3f}, "
            f"noisy labels {mean['ref_pq_frame']:.3f}; small things {mean['small_pq_frame']:.3f} vs "
            f"{mean['ref_small_pq_frame']:.3f}; {mean['ms']:.0f} ms/frame."]
    heads = [("things PQ/frame (generated, class-agnostic)",
              f"{mean['pq_frame']:.3f} (noisy labels {mean['ref_pq_frame']:.3f})"),
             ("small things PQ/frame (furniture void)",
              f"{mean['small_pq_frame']:.3f} (noisy labels {mean['ref_small_pq_frame']:.3f})")]
    if train:
        body += ["", "### PQ^scene after `psimap train` (class-agnostic, ids consistent across frames)", "",
                 markdown_table(["capture", "trained on", "things PQ^scene", "small things PQ^scene", "floor IoU",
                                 "wall IoU", "train s (wall)"],
                                [[lay, lab, f"{v[lab]['pq_things']:.3f}", f"{v[lab]['small_pq_things']:.3f}",
                                  f"{v[lab]['floor_iou']:.3f}", f"{v[lab]['wall_iou']:.3f}", f"{v[lab]['train_s']:.0f}"]
                                 for lay, v in train.items() for lab in ("noisy", "segment")]),
                 "", "The checkpoint's rendered labels of every frame against GT, scene level (a GT instance is "
                     "the union of its pixels over all frames, a predicted one likewise): what training made "
                     "consistent of per-frame ids. Same data, same default training options; the segmenter's "
                     "labels replace the generator's (`psimap segment --force` on a copy)."]
        small = {lab: float(np.mean([v[lab]["small_pq_things"] for v in train.values()])) for lab in ("noisy", "segment")}
        body += ["", f"Mean over the {len(train)} trained captures: small things PQ^scene {small['segment']:.3f} on "
                     f"the segmenter's labels, {small['noisy']:.3f} on the generator's noisy ones."]
        heads.append((f"small things PQ^scene after training on segment labels (mean of {len(train)} captures)",
                      f"{small['segment']:.3f} (noisy labels {small['noisy']:.3f})"))
    if chess:
        fps = chess["frames"] / max(chess["cpu_s"] - chess["survey_seconds"], 1e-9)
        body += ["", f"### 7-Scenes chess ({chess['frames']} real Kinect frames, 640x480, scratch copy)", "",
                 f"`segment_capture` {chess['seconds_per_frame'] * 1000:.0f} ms per frame ({fps:.1f} frames/s CPU, "
                 f"survey {chess['survey_seconds']:.1f} s); up {chess['up']} (auto), floor "
                 f"{chess['floor']} m, cameras at {chess['camera_height']} m; per frame "
                 f"{chess['planes_per_frame']:.1f} stuff planes ({', '.join(f'{k} {v}' for k, v in sorted(chess['stuff_planes'].items()))} "
                 f"over all frames) and {chess['objects_per_frame']:.1f} objects (median {chess['objects_median']:.0f})."]
        heads.append(("7-Scenes chess 640x480", f"{chess['seconds_per_frame'] * 1000:.0f} ms/frame"))
    text = "\n".join(body)
    if args.no_write:
        print(text)
        return
    png = save_plot(plot(rows), "segment")
    write_section("segment", "Model-free pseudo-labels (psimap segment)", text, headlines=heads, plot=png)
    if chess:
        dest = ROOT / "benchmarks" / "plots" / "segment-chess.png"
        shutil.copy2(chess["sheet"], dest)
        os.chmod(dest, 0o644)


if __name__ == "__main__":
    main()
