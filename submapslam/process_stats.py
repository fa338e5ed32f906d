"""The process's own resources: its memory figures (Linux: the true peak and the current resident
set) and how many threads its BLAS libraries may use."""

from __future__ import annotations

import functools
import resource
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from threadpoolctl import threadpool_limits


def peak_memory_mb() -> float:
    """Peak resident set of this process so far [MiB] (Linux ``ru_maxrss`` is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def combined_peak_mb(main_peak_mb: float, main_peak_when_child_ended_mb: float, child_peak_mb: float,
                     grids: tuple[float, float] | None = None) -> float:
    """Peak [MiB] of this process and its child processes: the odometry child, which ended before
    this process's work was done (at most this process's peak when it ended plus the child's own
    peak, and after that, this process's peak alone), and the map fusion's grid child when one ran
    (``grids``: ``(this process's peak while it ran, its own peak)`` [MiB])."""
    pairs = [(main_peak_when_child_ended_mb, child_peak_mb)] + ([grids] if grids is not None else [])
    return max(main_peak_mb, *(main + child for main, child in pairs))


def peaks_by_process(main_peak_mb: float, main_peak_when_child_ended_mb: float, child_peak_mb: float,
                     grids: tuple[float, float] | None = None) -> dict:
    """``summary.json``'s ``peak_memory_mb_by_process``: the figures :func:`combined_peak_mb` adds up
    (``grids``: ``(this process's peak while the grid child ran, the child's peak)`` [MiB], when one ran)."""
    out = {"main": round(main_peak_mb, 1), "odometry": round(child_peak_mb, 1),
           "main_when_odometry_ended": round(main_peak_when_child_ended_mb, 1)}
    if grids is not None:
        out.update(grids=round(grids[1], 1), main_while_grids=round(grids[0], 1))
    return out


def memory_growth_mb_per_km(by_km: list[tuple[float, float]] | None, from_km: float = 1.0,
                            min_span_km: float = 1.0) -> float | None:
    """How fast the resident set grows with the distance travelled [MiB/km]: the least-squares
    slope through the ``(km, MiB)`` samples (``summary.json``'s ``memory_mb_by_km``) taken at
    ``from_km`` or later, past the start's imports and first submaps. None when those samples span
    less than ``min_span_km`` (too short a drive to tell growth from the spread between samples)."""
    samples = np.asarray(by_km if by_km is not None else [], dtype=np.float64).reshape(-1, 2)
    samples = samples[np.isfinite(samples).all(axis=1) & (samples[:, 0] >= from_km)]
    if len(samples) < 2 or np.ptp(samples[:, 0]) < max(min_span_km, 1e-9):
        return None
    return float(np.polyfit(samples[:, 0], samples[:, 1], 1)[0])


def current_memory_mb() -> float:
    """Resident set of this process now [MiB] (``/proc/self/statm``; the peak where unavailable)."""
    try:
        with open("/proc/self/statm") as fh:
            resident_pages = int(fh.read().split()[1])
        return resident_pages * resource.getpagesize() / 2**20
    except (OSError, ValueError, IndexError):
        return peak_memory_mb()


def release_free_memory() -> None:
    """Hand the memory the heap holds free back to the system (glibc's ``malloc_trim``; nothing
    elsewhere). Freed temporaries otherwise stay in the resident set, and a run's last step (fusing
    the map and the grid) adds its own peak on top of them."""
    try:
        _libc().malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


@functools.cache
def _libc():
    """The C library (``ctypes``); OSError where it cannot be loaded."""
    import ctypes
    import ctypes.util

    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")


_M_ARENA_MAX = -8  # glibc's mallopt parameter number (malloc.h)


def one_malloc_arena() -> bool:
    """Make every thread of this process allocate from glibc's main heap (``mallopt(M_ARENA_MAX,
    1)``; True when set, False elsewhere). Call it before threads start: arenas already made stay.

    Each thread that allocates while another holds the heap gets an arena of its own, and
    numpy's temporaries, freed in one thread's arena and needed in another's, stay resident as
    fragmentation. A run's threads take turns at the GIL anyway, so one arena costs no time:
    Intel's run 36.3 -> 35.5 s, its peak with the odometry process 282.3 -> 263.5 MiB. It is
    process-wide and permanent, so only the command line (a process of our own) calls it."""
    try:
        return bool(_libc().mallopt(_M_ARENA_MAX, 1))
    except (OSError, AttributeError):  # not glibc
        return False


def single_threaded_blas(load_scipy: bool = True) -> threadpool_limits:
    """Keep the BLAS libraries numpy and scipy load (OpenBLAS, MKL) to one thread
    (:mod:`threadpoolctl`): at once, and until the end of a ``with`` block when used as one
    (then the previous limits come back).

    Only libraries already loaded are limited: ``load_scipy`` first loads scipy's own OpenBLAS
    (it comes with ``scipy.linalg``); a process that never imports scipy (a planar run's odometry
    process) passes False.

    Our products are small (a scan's few hundred points by a 3x3 or 4x4). With a thread per core,
    OpenBLAS's threads spin between calls and take the CPU the run's own threads and odometry
    process need: Intel's whole run took 41 s and 61 s of CPU, one BLAS thread 34 s and 48 s,
    with the same poses."""
    from threadpoolctl import threadpool_limits

    if load_scipy:
        import scipy.linalg  # noqa: F401 - loads scipy's BLAS, to be limited with numpy's

    return threadpool_limits(limits=1, user_api="blas")
