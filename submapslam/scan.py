"""The unit every reader yields and the pipeline, odometry and localization consume: one scan;
and a manual loop hint, two scans taken at the same place.

A core type: readers in :mod:`submapslam.io` build it, nothing here reads files.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray


@dataclass
class Scan:
    """One range scan.

    Attributes:
        index: 0-based position of the scan in its log.
        timestamp: the time the log gives this scan [s] (CARMEN: the line's ``ipc_timestamp``).
        points: ``(N, 3)`` float64 points [m] in the robot's base frame when the log gives the
            sensor mounting (``T_base_sensor``: meta.yaml, a bag's /tf_static), else in the
            sensor frame; planar scans have z = 0.
        point_times: ``(N,)`` float64 per-point times normalised to [0, 1] over the sweep,
            or ``None`` when the log does not give them.
        odometry: ``(4, 4)`` wheel-odometry pose ``T_odom_base`` at the scan time, or ``None``.
        planar: True for 2D laser scans (all z = 0).
        source: where the scan came from, e.g. ``"intel.clf.bz2:1234"``, for error messages.
        no_returns: ``(M, 3)`` float64, planar scans: where the beams that returned nothing
            (reading at the laser's maximum range) end, at that range, in the frame of
            ``points``; free space up to there for the occupancy grid, never a point. None: not
            known.
        timed: False when the log gives no times and ``timestamp`` is the scan's index (a cloud
            folder without times.txt): nothing may read a rate from it.
    """

    index: int
    timestamp: float
    points: NDArray[np.float64]
    point_times: NDArray[np.float64] | None = None
    odometry: NDArray[np.float64] | None = None
    planar: bool = False
    source: str = ""
    no_returns: NDArray[np.float64] | None = None
    timed: bool = True

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        if self.no_returns is not None:
            self.no_returns = np.asarray(self.no_returns, dtype=np.float64).reshape(-1, 3)


@dataclass(frozen=True)
class LoopHint:
    """Two scans at the same place: scan indices when ``by_index``, else timestamps [s];
    ``line``: where the hint was given (1-based line of its file), for messages."""

    a: float
    b: float
    by_index: bool
    line: int | None = field(default=None, compare=False)
