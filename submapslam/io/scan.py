"""The unit every reader yields: one scan, and the sensor mounting readers apply to it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError


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
    """

    index: int
    timestamp: float
    points: NDArray[np.float64]
    point_times: NDArray[np.float64] | None = None
    odometry: NDArray[np.float64] | None = None
    planar: bool = False
    source: str = ""

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)


def check_transform(T, where: Path, what: str = "T_base_sensor") -> np.ndarray:
    """A rigid ``(4, 4)`` transform as float64, else an :class:`InputError`."""
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(where, f"{what} is not a 4x4 matrix of numbers") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(where, f"{what} must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if (not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or abs(np.linalg.det(R) - 1.0) > 1e-6
            or not np.allclose(T[3], [0, 0, 0, 1])):
        raise InputError(where, f"{what} is not a rigid transform (rotation and translation)")
    return T


def apply_mounting(points: np.ndarray, T_base_sensor: np.ndarray, planar: bool) -> np.ndarray:
    """Sensor-frame points -> base frame (``T_base_sensor @ p``); planar scans keep z = 0."""
    out = points @ T_base_sensor[:3, :3].T + T_base_sensor[:3, 3]
    if planar:
        out[:, 2] = 0.0
    return out
