"""The cores this process may use: its affinity mask (a Dask worker pinned to its share, a
container's cpuset), not the machine's count, which sizes the stages' thread pools and the
Dask workers' thread budget alike."""

from __future__ import annotations

import os


def available_cores() -> int:
    """Cores this process may run on (its affinity mask, not the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1
