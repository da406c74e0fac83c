"""The `psimap` command line: one entry point, one subcommand per stage.

Each subcommand's options are a dataclass in `psimap.options`; its implementation is imported only
when it runs, so `psimap --help` is instant.
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib
import re
import sys

from psimap import options as O

# name -> (options dataclass, "module:function", one-line help)
COMMANDS = {
    "demo": (O.DemoOptions, "psimap.demo:run", "embedded synthetic scene, end to end"),
    "generate": (O.GenerateOptions, "psimap.data.synthetic:cli_generate",
                 "write a synthetic scene with exact ground truth"),
    "train": (O.TrainOptions, "psimap.train:cli_train", "train a panoptic surfel map"),
    "mesh": (O.MeshOptions, "psimap.train:cli_mesh", "extract the whole-scene surface mesh"),
    "export": (O.ExportOptions, "psimap.exporters:cli_export",
               "export per-object assets (MJCF / USD / GLB)"),
    "eval": (O.EvalOptions, "psimap.cli:run_eval",
             "geometry, panoptic and object metrics against ground truth; a map's fit to its capture"),
    "labels": (O.LabelsOptions, "psimap.panoptic:cli_labels",
               "3D-consistent 2D panoptic labels (COCO panoptic)"),
    "segment": (O.SegmentOptions, "psimap.segment:cli_segment",
                "model-free per-frame pseudo-labels (planes + clusters) for a capture without masks"),
    "import-masks": (O.ImportMasksOptions, "psimap.data.masks_import:cli_import_masks",
                     "per-frame labels from a 2D segmenter's masks (COCO panoptic / instances, SAM)"),
    "batch": (O.BatchOptions, "psimap.batch:cli_batch",
              "many captures: train -> export -> check on a Dask cluster (local by default)"),
    "check": (O.CheckOptions, "psimap.sim.export_check:cli_check",
              "settle an export folder again in MuJoCo and / or Newton, without modifying it"),
}


def _add_options(parser: argparse.ArgumentParser, cls) -> None:
    for f in dataclasses.fields(cls):
        meta = dict(f.metadata)
        help_ = meta.pop("help", "")
        if meta.pop("positional", False):
            parser.add_argument(f.name, help=help_, **meta)
            continue
        flag = "--" + f.name.replace("_", "-")
        if f.type in ("bool", bool):
            parser.add_argument(flag, dest=f.name, action="store_true", help=help_)
            continue
        typ = {"int": int, "float": float, "str": str}.get(f.type, str) if isinstance(f.type, str) else f.type
        parser.add_argument(flag, dest=f.name, type=typ, default=f.default,
                            help=f"{help_} (default: {f.default})", **meta)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="psimap", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on error")
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (cls, _, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                       help="show full tracebacks on error")
        _add_options(p, cls)
    return parser


def _version() -> str:
    from psimap import __version__

    return f"psimap {__version__}"


def run_eval(opts) -> int:
    """`psimap eval`: the metrics stage's command (psimap.metrics.evaluate.cli_eval). With --objects on a
    checkpoint, the objects are extracted here, by the export stage, and passed in: a stage never
    imports a later one, an entry point may."""
    from pathlib import Path

    from psimap.metrics.evaluate import cli_eval

    objects = None
    if opts.objects and Path(opts.pred).suffix.lower() == ".ckpt":
        from psimap.api import predicted_objects

        def objects():      # called once DATA's object ground truth has been read and checked
            return predicted_objects(opts.pred, progress=True)
    return cli_eval(opts, objects=objects)


def _join_up_values(argv: list[str]) -> list[str]:
    """`--up -y` as `--up=-y`: argparse takes a value starting with '-' for an option and stops with
    "expected one argument"; an axis ("-y") or a vector ("-0.1,0.9,0") is what --up means there."""
    out, i = [], 0
    while i < len(argv):
        if argv[i] == "--up" and i + 1 < len(argv) and re.fullmatch(r"-(?:[xyz]|[0-9.][0-9.,eE+-]*)", argv[i + 1]):
            out.append(f"--up={argv[i + 1]}")
            i += 2
            continue
        out.append(argv[i])
        i += 1
    return out


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(_join_up_values(list(sys.argv[1:] if argv is None else argv)))
    if args.command is None:
        parser.print_help()
        return 2
    cls, target, _ = COMMANDS[args.command]
    debug = getattr(args, "debug", False)
    opts = cls(**{f.name: getattr(args, f.name) for f in dataclasses.fields(cls)})
    from psimap import PsimapError

    try:
        module, func = target.split(":")
        fn = getattr(importlib.import_module(module), func)
        rc = fn(opts)
        return int(rc or 0)
    except PsimapError as e:
        if debug:
            raise
        print(f"psimap {args.command}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"psimap {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # unexpected: still one line unless --debug
        if debug:
            raise
        print(f"psimap {args.command}: internal error: {type(e).__name__}: {e} (rerun with --debug)",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
