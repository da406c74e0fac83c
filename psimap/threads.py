"""Thread counts for the small per-view work of meshing and export.

torch's intra-op pool and the native kernels' OpenMP team spin-wait between parallel regions. On
a 2-core machine with other work running, that spinning is most of the cost: rendering the views
of the 10-object export benchmark took 48 s wall / 32 s CPU with 2 threads at load 7-8 and 9 s /
6 s with one (benchmarks/RESULTS.md). The per-view tensors are small, so one thread loses little
on an idle machine either.
"""
from __future__ import annotations

from contextlib import contextmanager


@contextmanager
def single_threaded():
    """Run the block with one torch intra-op thread and one native-kernel thread; restore after."""
    with limited_threads(1):
        yield


@contextmanager
def limited_threads(n: int):
    """Run the block with `n` torch intra-op threads and `n` native-kernel threads; restore after.
    (A batch task states its thread count with this: psimap.batch.)"""
    import torch

    from psimap.render.api import native_available

    native = None
    if native_available():
        from psimap.render import native
    t0 = torch.get_num_threads()
    n0 = native.get_num_threads() if native is not None else None
    torch.set_num_threads(n)
    if n0 is not None:
        native.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(t0)
        if n0 is not None:
            native.set_num_threads(n0)
