"""Renderer benchmark: speed beside the error it costs, on a synthetic surfel room, in one run.

Per resolution: forward and forward+backward time of the torch reference (and the native backend
when it is built), tile pairs with the bounding-circle baseline vs the precise AABB (the same image:
the max pixel difference is printed next to it), and Top-K (K = 4, 8, 16) feature error against full
blending. Writes its section of benchmarks/RESULTS.md and its plot (benchmarks/plots/render.png);
a --quick smoke run prints its table and leaves both alone (its picture goes to bench_out/).

    python benchmarks/render.py            # ~50k surfels, 320x240 and 640x480, C = 32
    python benchmarks/render.py --quick    # small smoke run
"""
from __future__ import annotations

import argparse
import math
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import markdown_table, save_plot, write_section  # noqa: E402

from psimap.render import rasterize  # noqa: E402
from psimap.transforms import rotmat_to_quat  # noqa: E402

OUT_DIR = Path(__file__).resolve().parents[1] / "bench_out"


def room_surfels(n: int, channels: int, seed: int = 0):
    """~n surfels covering a 6 x 5 x 3 m room (Z up) with boxes on the floor.

    Each planar patch gets surfels in proportion to its area; scale ~ the sample spacing so the
    surfels overlap into a closed surface. Returns float32 tensors (means, quats, scales, opacities,
    colors, features [n, channels]).
    """
    rng = np.random.default_rng(seed)
    # Patches: (origin, edge_a, edge_b, colour); the normal is edge_a x edge_b.
    patches = []

    def quad(o, a, b, col):
        patches.append((np.array(o, float), np.array(a, float), np.array(b, float), np.array(col, float)))

    X, Y, Z = 6.0, 5.0, 3.0
    quad([-X / 2, -Y / 2, 0], [X, 0, 0], [0, Y, 0], [0.55, 0.45, 0.35])          # floor
    quad([-X / 2, -Y / 2, Z], [0, Y, 0], [X, 0, 0], [0.9, 0.9, 0.88])            # ceiling
    quad([-X / 2, Y / 2, 0], [X, 0, 0], [0, 0, Z], [0.7, 0.75, 0.8])             # back wall
    quad([-X / 2, -Y / 2, 0], [0, 0, Z], [X, 0, 0], [0.7, 0.75, 0.8])            # front wall
    quad([-X / 2, -Y / 2, 0], [0, Y, 0], [0, 0, Z], [0.8, 0.7, 0.6])             # left wall
    quad([X / 2, -Y / 2, 0], [0, 0, Z], [0, Y, 0], [0.8, 0.7, 0.6])              # right wall
    boxes = [(-1.5, 1.0, 1.0, 0.8, 0.7, [0.8, 0.2, 0.2]), (0.8, 1.5, 1.2, 0.6, 1.0, [0.2, 0.6, 0.3]),
             (1.8, -0.2, 0.6, 0.6, 0.5, [0.2, 0.3, 0.8]), (-0.3, 0.2, 0.5, 0.4, 0.4, [0.9, 0.8, 0.2])]
    for cx, cy, sx, sy, sz, col in boxes:
        x0, y0 = cx - sx / 2, cy - sy / 2
        quad([x0, y0, sz], [sx, 0, 0], [0, sy, 0], col)                             # top
        quad([x0, y0, 0], [0, 0, sz], [sx, 0, 0], col)                              # -y face
        quad([x0, y0 + sy, 0], [sx, 0, 0], [0, 0, sz], col)                         # +y face
        quad([x0, y0, 0], [0, sy, 0], [0, 0, sz], col)                              # -x face
        quad([x0 + sx, y0, 0], [0, 0, sz], [0, sy, 0], col)                         # +x face
    areas = np.array([np.linalg.norm(np.cross(a, b)) for _, a, b, _ in patches])
    counts = rng.multinomial(n, areas / areas.sum())
    spacing = math.sqrt(areas.sum() / n)
    feat_basis = rng.normal(size=(len(patches), channels))
    means, normals, tangents, colors, feats = [], [], [], [], []
    for (o, a, b, col), k, fb in zip(patches, counts, feat_basis):
        st = rng.random((k, 2))
        means.append(o + st[:, :1] * a + st[:, 1:] * b)
        nrm = np.cross(a, b)
        nrm /= np.linalg.norm(nrm)
        normals.append(np.repeat(nrm[None], k, 0))
        ang = rng.random(k) * 2 * np.pi
        ea, eb = a / np.linalg.norm(a), np.cross(nrm, a / np.linalg.norm(a))
        tangents.append(np.cos(ang)[:, None] * ea + np.sin(ang)[:, None] * eb)
        shade = 0.08 * np.sin(7 * st[:, :1] + 5 * st[:, 1:]) + 0.03 * rng.normal(size=(k, 3))
        colors.append(np.clip(col + shade, 0, 1))
        feats.append(fb + 0.3 * np.sin(3 * st[:, :1] * np.arange(1, channels + 1)))
    means, normals, tangents = map(np.concatenate, (means, normals, tangents))
    bitangents = np.cross(normals, tangents)
    rot = np.stack([tangents, bitangents, normals], axis=-1)          # columns = axes
    quats = rotmat_to_quat(rot)
    scales = spacing * (0.5 + 0.3 * rng.random((n, 2)))
    opacities = 0.6 + 0.35 * rng.random(n)
    as_t = lambda x: torch.tensor(np.asarray(x), dtype=torch.float32)  # noqa: E731
    return (as_t(means), as_t(quats), as_t(scales), as_t(opacities), as_t(np.concatenate(colors)),
            as_t(np.concatenate(feats)))


def look_at_viewmat(eye, target, up=(0, 0, 1)) -> torch.Tensor:
    """World-to-camera [4, 4] (OpenCV: x right, y down, z forward)."""
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, y, z], axis=1)
    c2w[:3, 3] = eye
    return torch.tensor(np.linalg.inv(c2w), dtype=torch.float32)


def intrinsics(width: int, height: int, hfov_deg: float = 75.0) -> torch.Tensor:
    f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
    return torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], dtype=torch.float32)


def timed(fn, repeats: int) -> tuple[str, object]:
    """Best of `repeats` calls as "wall / cpu" seconds (cpu = process time over all threads, less
    sensitive than wall time to other jobs on a shared machine), and the last result."""
    best, res = (float("inf"), float("inf")), None
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        res = fn()
        best = min(best, (time.perf_counter() - t0, time.process_time() - c0))
    return f"{best[0]:.3g} / {best[1]:.3g}", res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="small smoke run (3k surfels, 96x72 and 160x120; RESULTS.md untouched)")
    ap.add_argument("--surfels", type=int, default=None)
    ap.add_argument("--repeats", type=int, default=None)
    args = ap.parse_args(argv)
    n = args.surfels or (3_000 if args.quick else 50_000)
    repeats = args.repeats or (1 if args.quick else 2)
    resolutions = [(96, 72), (160, 120)] if args.quick else [(320, 240), (640, 480)]
    channels = 32

    try:
        from psimap.render.native import rasterize_native  # noqa: F401
        backends = ["reference", "native"]
    except Exception:
        backends = ["reference"]

    scene = room_surfels(n, channels)
    leaves = [t.clone().requires_grad_(True) for t in scene]
    viewmat = look_at_viewmat([-2.2, -2.0, 1.6], [1.0, 1.8, 0.8])
    rows, images = [], {}
    first_res = f"{resolutions[0][0]}x{resolutions[0][1]}"
    for width, height in resolutions:
        K = intrinsics(width, height)
        res = f"{width}x{height}"

        def render(tiles="precise", topk=None, backend="reference", grad=False):
            with torch.set_grad_enabled(grad):
                src = leaves if grad else scene
                return rasterize(*src[:5], viewmat, K, width, height, features=src[5], topk=topk,
                                 tiles=tiles, backend=backend)

        def fwd_bwd(**kw):
            out = render(grad=True, **kw)
            loss = (out.rgb.sum() + out.depth.sum() + out.normal.sum() + out.distortion.sum()
                    + out.features.square().mean(-1).sum())
            loss.backward()
            return out

        full = None
        for backend in backends:
            for tiles in ("circle", "precise"):
                reps = repeats if backend != "reference" else 1     # the reference is slow on CPU
                t_f, out = timed(lambda: render(tiles, backend=backend), reps)
                t_fb, _ = timed(lambda: fwd_bwd(tiles=tiles, backend=backend), reps)
                if full is None:
                    full = out
                diff = max(float((getattr(out, k) - getattr(full, k)).abs().max())
                           for k in ("rgb", "alpha", "depth", "features"))
                rows.append([res, backend, tiles, "all", t_f, t_fb, out.stats["tile_pairs"],
                             round(out.stats["pairs_per_tile"], 1), out.stats["evaluated"], f"{diff:.1e}", "0", "0"])
            ref_pairs = [r for r in rows if r[0] == res and r[1] == backend]
            circle, precise = ref_pairs[-2][6], ref_pairs[-1][6]
            print(f"{res} {backend}: tile pairs circle {circle} -> precise {precise} "
                  f"({100 * (1 - precise / circle):.1f}% fewer)")
        images[res] = full
        fmask = full.alpha > 0.5
        fref = full.features[fmask]
        for k in (4, 8, 16):
            for backend in backends:
                reps = repeats if backend != "reference" else 1
                t_f, out = timed(lambda: render("precise", topk=k, backend=backend), reps)
                # The torch reference's Top-K backward is timed at the first resolution only (slow CPU).
                t_fb = (timed(lambda: fwd_bwd(tiles="precise", topk=k, backend=backend), reps)[0]
                        if backend != "reference" or res == first_res else "-")
                err = (out.features[fmask] - fref).abs()
                rel = float(err.mean() / fref.abs().mean())
                rows.append([res, backend, "precise", f"K={k}", t_f, t_fb,
                             out.stats["tile_pairs"], round(out.stats["pairs_per_tile"], 1),
                             out.stats["evaluated"], "-",
                             f"{float(err.mean()):.2e}", f"{100 * rel:.2f}%"])

    header = ["res", "backend", "tiles", "features", "fwd s (wall / cpu)", "fwd+bwd s (wall / cpu)",
              "tile pairs", "pairs/tile",
              "evaluated", "max |diff| vs first", "feat mean abs err", "feat rel err"]
    peak_gib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
    reductions = []
    for width, height in resolutions:
        res = f"{width}x{height}"
        c = next(r[6] for r in rows if r[0] == res and r[2] == "circle")
        p = next(r[6] for r in rows if r[0] == res and r[2] == "precise")
        reductions.append(f"{res}: {100 * (1 - p / c):.1f}%")
    notes = (f"Synthetic room, {n} surfels, C = {channels} features, float32, CPU threads = "
             f"{torch.get_num_threads()}, native: best of {repeats}, reference: one run. Times are wall / cpu "
             f"seconds (cpu = process time over all threads; the machine is shared with other jobs, so wall "
             f"times are inflated). Precise AABB vs bounding-circle tile pairs: "
             f"{', '.join(reductions)} fewer, same image (max |diff| column, vs the first row of the "
             f"resolution). Top-K error is over pixels with alpha > 0.5 against full feature blending "
             f"(relative = mean abs err / mean |feature|). Peak RSS {peak_gib:.2f} GiB.")
    fig = plot(images)
    if args.quick:   # a smoke run prints its table but leaves RESULTS.md alone
        print(markdown_table(header, rows))
        print(notes)
        OUT_DIR.mkdir(parents=True, exist_ok=True)
        fig.savefig(OUT_DIR / "render.png", dpi=80)
        print(f"wrote {OUT_DIR / 'render.png'}")
        return 0
    write_section("render", "Surfel rasterizer (reference" + (" + native" if len(backends) > 1 else "") + ")",
                  markdown_table(header, rows) + "\n\n" + notes, headlines=headlines(rows, resolutions),
                  plot=save_plot(fig, "render", dpi=80))
    return 0


def headlines(rows, resolutions) -> list[tuple[str, str]]:
    """Summary rows: native vs reference fwd+bwd CPU time and the precise tiles' pair saving, at the
    largest resolution."""
    res = "{}x{}".format(*resolutions[-1])

    def cpu(backend, tiles, features="all"):
        r = next((r for r in rows if r[:4] == [res, backend, tiles, features]), None)
        return None if r is None or r[5] == "-" else float(r[5].split(" / ")[1])

    c, p = (next(r[6] for r in rows if r[0] == res and r[2] == t) for t in ("circle", "precise"))
    out = [(f"precise tiles vs bounding circle, {res}", f"{100 * (1 - p / c):.1f} % fewer tile pairs, same image")]
    native, ref = cpu("native", "precise"), cpu("reference", "precise")
    if native and ref:
        out.insert(0, (f"fwd+bwd CPU s at {res}, native vs torch reference",
                       f"{native:.3g} vs {ref:.3g} s ({ref / native:.0f}x)"))
    return out


def plot(images: dict):
    """RGB, depth, normal and distortion of the last resolution (the figure, not yet saved)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    res, out = list(images.items())[-1]
    fig, ax = plt.subplots(1, 4, figsize=(16, 3.4))
    ax[0].imshow(out.rgb.detach().clamp(0, 1).numpy())
    ax[0].set_title(f"rgb {res}")
    ax[1].imshow(out.depth.detach().numpy(), cmap="viridis")
    ax[1].set_title("expected depth")
    ax[2].imshow((0.5 - 0.5 * out.normal.detach()).clamp(0, 1).numpy())
    ax[2].set_title("normal (camera)")
    ax[3].imshow(out.distortion.detach().numpy(), cmap="magma")
    ax[3].set_title("distortion")
    for a in ax:
        a.axis("off")
    fig.tight_layout()
    return fig


if __name__ == "__main__":
    raise SystemExit(main())
