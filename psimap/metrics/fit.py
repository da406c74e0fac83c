"""How well a checkpoint fits the capture it came from: `psimap eval scene.ckpt DATA` on any capture.

A real capture has no ground truth, yet its user wants to know whether the map is any good before
exporting it. Every frame of DATA is rendered from the checkpoint at the frame's own camera and
compared with what the sensor recorded:
- depth: the render's median depth against the frame's depth where both exist (absolute error,
  share within 1 / 5 cm), the share of the sensor's pixels the map covers (alpha >= 0.5: what the
  map lost), and the share of the map's pixels where the sensor had no depth (what it added: black
  or glossy surfaces, or fill between views);
- colour: PSNR of the rendered colour against the frame's.
Training frames measure the fit, not generalisation: a map can fit its frames and still be wrong in
between. Frames are taken evenly, at most `max_frames`.
"""
from __future__ import annotations

import math

import numpy as np

FIT_KEYS = ("frames", "depth_mae_cm", "depth_median_cm", "depth_within_1cm", "depth_within_5cm",
            "coverage", "added", "psnr_db")
MIN_ALPHA = 0.5                 # a rendered pixel this opaque shows a surface of the map
ERROR_SAMPLES = 200_000         # per-pixel errors kept for the median (an even subsample)


def evaluate_fit(scene, seq, *, max_frames: int = 60, progress: bool = False, plot: str | None = None) -> dict:
    """Fit of `scene` (psimap.scene.Scene) to the frames of `seq` (psimap.data FrameSequence).
    Returns {FIT_KEYS..., "per_frame": [{name, depth_mae_cm, coverage, added, psnr_db}]}; a value
    no frame could give (no depth anywhere, no colour) is NaN."""
    from tqdm import tqdm

    from psimap.data.frames import evenly_spaced

    n = len(seq)
    idx = evenly_spaced(n, max_frames)
    err_sum = 0.0
    counts = {"both": 0, "valid": 0, "covered": 0, "added": 0, "within_1cm": 0, "within_5cm": 0}
    kept, per_frame, psnrs = [], [], []
    for i in tqdm(idx, desc="fit", disable=not progress, leave=False):
        f = seq[i]
        out = scene.render(np.asarray(f.K, np.float64), np.asarray(f.c2w, np.float64), f.width, f.height)
        alpha = np.asarray(out.alpha, np.float64).reshape(f.height, f.width)
        depth = np.asarray(out.median_depth, np.float64).reshape(f.height, f.width)
        sensor = np.asarray(f.depth, np.float64)
        valid = np.isfinite(sensor) & (sensor > 0)
        covered = (alpha >= MIN_ALPHA) & np.isfinite(depth) & (depth > 0)
        both = valid & covered
        err = np.abs(depth[both] - sensor[both])
        counts["both"] += int(both.sum())
        counts["valid"] += int(valid.sum())
        counts["covered"] += int(covered.sum())
        counts["added"] += int((covered & ~valid).sum())
        counts["within_1cm"] += int((err <= 0.01).sum())
        counts["within_5cm"] += int((err <= 0.05).sum())
        err_sum += float(err.sum())
        # each frame's errors at a stride that keeps ~ERROR_SAMPLES over all frames, for the median
        kept.append(err[::max(1, math.ceil(len(idx) * valid.size / ERROR_SAMPLES))])
        row = {"name": f.name or str(i),
               "depth_mae_cm": float(err.mean() * 100) if len(err) else math.nan,
               "coverage": float(both.sum() / valid.sum()) if valid.any() else math.nan,
               "added": float((covered & ~valid).sum() / covered.sum()) if covered.any() else math.nan,
               "psnr_db": math.nan}
        rgb = getattr(f, "rgb", None)
        if rgb is not None and np.size(rgb):
            pred = np.clip(np.asarray(out.rgb, np.float64).reshape(f.height, f.width, 3), 0.0, 1.0)
            mse = float(np.mean((pred - np.clip(np.asarray(rgb, np.float64), 0.0, 1.0)) ** 2))
            row["psnr_db"] = 10.0 * math.log10(1.0 / max(mse, 1e-12))
            psnrs.append(row["psnr_db"])
        per_frame.append(row)
    errs = np.concatenate(kept) if kept else np.zeros(0)
    both = counts["both"]
    result = {
        "frames": len(idx),
        "depth_mae_cm": err_sum / both * 100 if both else math.nan,
        "depth_median_cm": float(np.median(errs) * 100) if len(errs) else math.nan,
        "depth_within_1cm": counts["within_1cm"] / both if both else math.nan,
        "depth_within_5cm": counts["within_5cm"] / both if both else math.nan,
        "coverage": both / counts["valid"] if counts["valid"] else math.nan,
        "added": counts["added"] / counts["covered"] if counts["covered"] else math.nan,
        "psnr_db": float(np.mean(psnrs)) if psnrs else math.nan,
        "per_frame": per_frame,
    }
    if plot:
        plot_fit(result, plot)
    return result


def format_fit(r: dict) -> list[str]:
    """Lines of the readable table."""
    def num(x, fmt="{:.2f}", scale=1.0):
        return "n/a" if x is None or not math.isfinite(x) else fmt.format(x * scale)

    return ["fit to the capture (its own frames rendered from the map; no ground truth needed)",
            f"  depth error   {num(r['depth_mae_cm'])} cm mean, {num(r['depth_median_cm'])} cm median; "
            f"{num(r['depth_within_1cm'], '{:.1f}', 100)} % within 1 cm, "
            f"{num(r['depth_within_5cm'], '{:.1f}', 100)} % within 5 cm",
            f"  coverage      {num(r['coverage'], '{:.1f}', 100)} % of the sensor's depth pixels rendered; "
            f"{num(r['added'], '{:.1f}', 100)} % of the rendered pixels had no sensor depth",
            f"  colour        PSNR {num(r['psnr_db'])} dB",
            f"  frames        {r['frames']}"]


def plot_fit(r: dict, path) -> None:
    """Per-frame depth error and coverage (bars) and PSNR, written to `path` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from psimap.io_utils import save_figure

    rows = r["per_frame"]
    x = np.arange(len(rows))
    fig, (a, b) = plt.subplots(2, 1, figsize=(max(6.0, 0.25 * len(rows) + 3), 5), sharex=True)
    a.bar(x, [p["depth_mae_cm"] for p in rows], color="tab:blue")
    a.set_ylabel("depth error (cm, mean)")
    a.set_title(f"fit to the capture: {r['depth_mae_cm']:.2f} cm mean depth error, "
                f"{r['coverage'] * 100:.1f} % covered, PSNR {r['psnr_db']:.1f} dB")
    b.plot(x, [p["coverage"] * 100 for p in rows], "o-", color="tab:green", label="coverage %")
    b.set_ylabel("coverage (%)")
    b2 = b.twinx()
    b2.plot(x, [p["psnr_db"] for p in rows], "s--", color="tab:red", label="PSNR")
    b2.set_ylabel("PSNR (dB)")
    lines = b.get_lines() + b2.get_lines()
    b.legend(lines, [ln.get_label() for ln in lines], loc="lower left", fontsize=8)
    b.set_xticks(x, [p["name"] for p in rows], rotation=90, fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
