"""The process's own memory figures (Linux): the true peak and the current resident set."""

from __future__ import annotations

import resource


def peak_memory_mb() -> float:
    """Peak resident set of this process so far [MiB] (Linux ``ru_maxrss`` is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def current_memory_mb() -> float:
    """Resident set of this process now [MiB] (``/proc/self/statm``; the peak where unavailable)."""
    try:
        with open("/proc/self/statm") as fh:
            resident_pages = int(fh.read().split()[1])
        return resident_pages * resource.getpagesize() / 2**20
    except (OSError, ValueError, IndexError):
        return peak_memory_mb()
