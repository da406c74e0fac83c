"""psimap.batch: many captures through train -> export -> check on a Dask cluster (`psimap batch`).

The last stage: it runs the training and export stages as Dask tasks, one chain per capture
(docs/batch.md). `manifest` reads the list of captures (stdlib only), `stages` is the work a worker
does, `runner` the client's side: the cluster, the progress display, summary.json.
"""
from __future__ import annotations


def cli_batch(opts) -> int:
    """`psimap batch MANIFEST --out DIR [--scheduler ADDRESS] [--workers N] [--threads-per-worker T]`.
    Exit 0: every capture done and checked; 1: a capture failed (the others still ran); 2: every
    capture ran but a check or an export outcome failed."""
    import sys

    from psimap import PsimapError
    from psimap.batch.manifest import read_manifest
    from psimap.batch.runner import SUMMARY, check_batch_dir, run_batch

    if not opts.out:
        raise PsimapError("an output folder is required (--out DIR)")
    captures = read_manifest(opts.manifest)
    check_batch_dir(opts.out, captures)                 # a refusal before a cluster starts
    summary = run_batch(captures, opts.out, scheduler=opts.scheduler, workers=opts.workers,
                        threads_per_worker=opts.threads_per_worker, progress=sys.stderr.isatty())
    caps = summary["captures"].values()
    failed = [e for e in caps if e["status"] == "failed"]
    unchecked = [e for e in caps if e["status"] == "done" and not (e["check"]["passed"] and e["outcome_passed"])]
    n = summary["counts"]
    print(f"psimap batch: {n['done']} of {len(caps)} capture(s) done ({n['skipped']} earlier), "
          f"{n['failed']} failed, {len(unchecked)} with a failed check or outcome; "
          f"{summary['wall_s']:.1f} s -> {summary['out']}/{SUMMARY}")
    return 1 if failed else 2 if unchecked else 0
