"""The scans of a log taken at given times (for judging trajectories by the log's own scans:
:mod:`submapslam.evaluation.scan_consistency`)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..errors import SubmapSlamError
from ..trajectory import nearest_stamps
from .registry import open_log


def scans_at(log: str | Path, timestamps: Iterable[float], *, max_time_diff: float = 1e-3) -> dict[float, NDArray[np.float64]]:
    """The scans of ``log`` taken within ``max_time_diff`` [s] of ``timestamps``: timestamp -> ``(N, 3)`` points.

    Points are in the robot's base frame, as :func:`~submapslam.io.registry.open_log` gives
    them. Planar (2D laser) logs only: the measures that use them compare scans as lines of beams
    in x-y. Raises :class:`SubmapSlamError` for a 3D log or when none of the timestamps is in it.
    """
    wanted = np.unique(np.asarray(list(timestamps), dtype=np.float64))
    found: dict[float, NDArray[np.float64]] = {}
    for scan in open_log(log):
        if not scan.planar:
            raise SubmapSlamError(f"{log} holds 3D scans: judging a trajectory by its scans needs a 2D laser log")
        if wanted.size and nearest_stamps(wanted, [scan.timestamp], max_time_diff)[0] >= 0:
            found[float(scan.timestamp)] = scan.points
    if not found:
        raise SubmapSlamError(f"no scan of {log} is within {max_time_diff} s of the {wanted.size} times asked for")
    return found


def scans_read_once(log: str | Path, timestamps: Iterable[float], *,
                    max_time_diff: float = 1e-3) -> Callable[[NDArray[np.float64]], dict[float, NDArray[np.float64]]]:
    """:func:`scans_at` of ``log`` at ``timestamps``, read now and handed out for every later ask
    (a :data:`~submapslam.evaluation.scan_consistency.ScanSource` for measures that ask only for
    some of those times: the log is read once, not once per measure)."""
    taken = scans_at(log, timestamps, max_time_diff=max_time_diff)
    return lambda _times: taken
