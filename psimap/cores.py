"""How many cores this process may use: one answer for every stage that sizes a thread pool."""
from __future__ import annotations

import os


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity; os.cpu_count where that is unknown, as on
    macOS)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)
