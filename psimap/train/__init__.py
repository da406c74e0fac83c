"""psimap.train: surfel initialisation from the SOGMM prior, joint optimisation, and the `psimap
train` / `psimap mesh` commands. Heavy imports happen inside the functions."""
from __future__ import annotations

__all__ = ["train", "TrainConfig", "cli_train", "cli_mesh"]


def __getattr__(name):
    if name == "train":
        from psimap.train.trainer import train

        return train
    if name == "TrainConfig":
        from psimap.train.config import TrainConfig

        return TrainConfig
    raise AttributeError(f"module 'psimap.train' has no attribute {name!r}")


def cli_train(opts) -> int:
    """`psimap train DATA --out scene.ckpt [--iters N] [--seed S] [--resume CKPT]`."""
    from pathlib import Path

    from psimap import PsimapError
    from psimap.checkpoint import save_checkpoint
    from psimap.train.config import TrainConfig
    from psimap.train.trainer import train

    if not Path(opts.data).exists():
        raise PsimapError(f"no such data folder: {opts.data}")
    if opts.iters < 0:
        raise PsimapError(f"--iters must be >= 0, got {opts.iters}")
    from psimap.io_utils import check_output_file

    check_output_file(opts.out, overwrite=opts.overwrite, what="--out")     # before training, not after
    cfg = TrainConfig(seed=opts.seed)
    if opts.iters:
        cfg.iters = opts.iters
    if getattr(opts, "no_prior", False):
        cfg.use_prior = False
    if getattr(opts, "no_lidar", False):
        cfg.lidar = False
    import sys

    from psimap.data import load

    # Say how the capture was understood (layout, frames, depth scale, poses, what was assumed)
    # before minutes of training on it.
    seq = load(opts.data)
    print(seq.describe(), file=sys.stderr)
    seq.root = str(opts.data)           # the checkpoint records the data path as typed, as before
    scene = train(seq, cfg, resume=opts.resume or None)
    save_checkpoint(opts.out, scene.state(), overwrite=opts.overwrite)
    print(f"wrote {opts.out}: {len(scene)} surfels, {scene.metrics['steps']} steps, "
          f"{scene.metrics['seconds']:.1f} s")
    return 0


def cli_mesh(opts) -> int:
    """`psimap mesh scene.ckpt --out mesh.ply`: TSDF of the rendered training views."""
    from pathlib import Path

    from psimap import PsimapError
    from psimap.io_utils import check_output_file, export_mesh_file
    from psimap.scene import load_scene

    out = Path(opts.out)
    if out.suffix.lower() not in (".ply", ".obj", ".glb", ".stl", ".off"):
        raise PsimapError(f"--out {out}: mesh file must end in .ply, .obj, .glb, .stl or .off")
    check_output_file(out, overwrite=opts.overwrite, what="--out")
    scene = load_scene(opts.ckpt)
    voxel = getattr(opts, "voxel", 0.0) or None
    import sys

    mesh = scene.mesh(voxel_size=voxel, progress=sys.stderr.isatty())
    if len(mesh.faces) == 0:
        raise PsimapError(f"{opts.ckpt}: the rendered depth fused into an empty mesh")
    export_mesh_file(mesh, out)
    info = mesh.metadata.get("tsdf", {})
    print(f"wrote {out}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces "
          f"(voxel {info.get('voxel_size', float('nan')) * 100:.2f} cm)")
    return 0
