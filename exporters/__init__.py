"""psimap.exporters: from a trained checkpoint to per-object, simulation-ready assets.

One module per step (docs/architecture.md data flow): instance meshes (TSDF) -> repair -> completion ->
decimation -> UV + texture -> collision geometry + mass -> the writer registry (exporters.formats:
MJCF / USD / GLB).
Installed as `psimap.exporters` (never as a top-level `exporters`).
"""


def cli_export(opts) -> int:
    """`psimap export CKPT --format FORMAT|all --out OUT [--completion auto|none] [--no-check]
    [--no-preview] [--static-classes a,b | --dynamic-all]` (formats: exporters.formats.FORMATS)."""
    import sys

    from psimap.exporters.pipeline import export_scene
    from psimap.io_utils import check_output_dir
    from psimap.scene import load_scene

    check_output_dir(opts.out, "export", overwrite=getattr(opts, "overwrite", False), what="--out")
    from psimap.geometry.gravity import parse_up

    parse_up(getattr(opts, "up", "auto"))           # a bad --up is an error before the work

    kw = {}
    if getattr(opts, "densities", ""):
        from psimap.exporters.physics import load_density_table

        kw["densities"] = load_density_table(opts.densities)
    from psimap.exporters.physics import parse_static_classes

    kw["static_classes"] = parse_static_classes(getattr(opts, "static_classes", ""),
                                                getattr(opts, "dynamic_all", False))
    if getattr(opts, "dynamic_all", False):
        kw["min_coverage"] = 0.0
    kw["pin_unstable"] = not (getattr(opts, "no_pin_unstable", False) or getattr(opts, "dynamic_all", False))
    scene = load_scene(opts.ckpt)
    import warnings

    from psimap.exporters.preview import PreviewWarning

    with warnings.catch_warnings():     # said below in one line, from the report
        warnings.simplefilter("ignore", PreviewWarning)
        report = export_scene(scene, opts.out, opts.format, completion=opts.completion,
                              check=not opts.no_check, progress=sys.stderr.isatty(),
                              overwrite=getattr(opts, "overwrite", False), up=getattr(opts, "up", "auto"),
                              min_dynamic=getattr(opts, "min_dynamic", 0.5),
                              check_engine=getattr(opts, "check_engine", "mujoco"),
                              preview=not getattr(opts, "no_preview", False), **kw)
    prev = report.get("preview")
    if prev is not None and not prev.get("image"):
        print(f"warning: no preview.png ({prev.get('reason')}); report.html has the table", file=sys.stderr)
    out = report["outcome"]
    # the line a user reads first: did the things come out as things that move?
    print(("" if out["passed"] else "FAILED: ") + out["summary"]
          + ("" if out["passed"] else f" (fewer than {out['min_dynamic']:.0%} dynamic; --static-classes "
                                      "names what you want static, --min-dynamic 0 accepts it)"))
    g = report.get("gravity")
    if g and g["source"] != "given" and g["rotation"] != [[1, 0, 0], [0, 1, 0], [0, 0, 1]]:
        print(f"gravity: up was {[round(v, 3) for v in g['input_up']]} in the capture; exported Z-up "
              f"(rotation in report.json)")
    env = report.get("environment")
    if env:
        print(f"static world: floor at {env['floor_z']:.3f} m" + ("" if env["floor_observed"] else " (not seen: a "
              "safety plane)") + ", colliders " + ", ".join(f"{n} {r}" for r, n in sorted(env["colliders"].items()))
              + f"; 95 % of its surface within {env['error_m'] * 100:.1f} cm of them")
        unseen = env.get("unseen_supports") or []
        if unseen:
            print(f"  {len(unseen)} slab(s) inferred under things standing on a support no camera saw: "
                  + ", ".join(u["thing"] for u in unseen))
    n, skipped = len(report["objects"]), len(report["skipped"])
    print(f"exported {n} object(s) to {opts.out} ({opts.format}); skipped {skipped}")
    for o in report["objects"]:
        c = o.get("collision", {})
        kind = "static" if o.get("static") else f"{o['physics']['mass_kg']:8.3f} kg"
        print(f"  {o['name']:<24} {kind:>11}  {c.get('kind', '-'):<13} "
              f"hulls {c.get('hull_count', 0)}  faces {o['faces_before']} -> {o['faces_after']}")
    for s in report["skipped"]:
        print(f"  skipped {s['name']}: {s['reason']}")
    chk = report.get("check")
    if chk is not None:
        status = "passed" if chk["passed"] else "FAILED: " + "; ".join(chk["failures"])
        print(f"simulation check {status} (min contact dist {chk['min_contact_dist'] * 1000:.2f} mm, "
              f"max drift {chk['max_drift'] * 100:.2f} cm, "
              f"{report['timings'].get('sim_seconds_per_wall_second', 0):.1f} sim s / wall s)")
        for name, reason in chk.get("pinned", {}).items():
            print(f"  {name} exported static: {reason}")
    nchk = report.get("check_newton")
    if nchk is not None:
        status = "passed" if nchk["passed"] else "FAILED: " + "; ".join(nchk["failures"])
        print(f"Newton check of scene.usda {status} (min contact dist {nchk['min_contact_dist'] * 1000:.2f} mm, "
              f"max drift {nchk['max_drift'] * 100:.2f} cm)")
    if any(c is not None and not c["passed"] for c in (chk, nchk)):
        return 2
    return 0 if out["passed"] else 2
