"""The sensor mounting readers apply to a scan; :class:`Scan` itself is a core type (re-exported)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..scan import Scan

__all__ = ["Scan", "apply_mounting", "check_transform"]


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
