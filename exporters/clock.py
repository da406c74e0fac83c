"""Wall, user and system seconds of the export's steps (timings.json).

Every step `name` adds its wall seconds to `name_s` (as before) and the process's CPU seconds, all
threads, to `name_user_s` and `name_sys_s`. A step whose system time comes near its user time does
its work in the kernel, not in its own code: thread pools spinning (sched_yield, futex storms) or
memory churn (page faults of large temporaries freed and allocated again). The rotated 7-Scenes
export spent 116 s of system time that way: a full SVD built a P x P matrix per fitted axis.
"""
from __future__ import annotations

import resource
import time
from contextlib import contextmanager

SUFFIXES = ("_s", "_user_s", "_sys_s")


def now() -> tuple[float, float, float]:
    """(wall, user, system) seconds: perf_counter and this process's CPU, all threads."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return time.perf_counter(), r.ru_utime, r.ru_stime


def add(timings: dict, name: str, start: tuple[float, float, float]) -> None:
    """Add what passed since `start` (a `now()`) to timings[name_s / name_user_s / name_sys_s]."""
    for suffix, a, b in zip(SUFFIXES, start, now()):
        timings[name + suffix] = timings.get(name + suffix, 0.0) + (b - a)


@contextmanager
def step(timings: dict, name: str):
    """Time the block into `timings` (wall, user and system, `add`), also when it raises."""
    start = now()
    try:
        yield
    finally:
        add(timings, name, start)


def steps(timings: dict) -> list[str]:
    """Names of the steps in `timings` that carry all three clocks."""
    return sorted(k[:-len("_user_s")] for k in timings if k.endswith("_user_s")
                  and k[:-len("_user_s")] + "_sys_s" in timings and k[:-len("_user_s")] + "_s" in timings)
