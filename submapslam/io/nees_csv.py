"""``nees.csv``: the NEES of an EKF run's robot pose per step (``time,nees``), where truth is known."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_nees_csv(path: str | Path, times: np.ndarray, nees: np.ndarray) -> Path:
    """Write ``time,nees`` rows; return the path."""
    path = Path(path)
    rows = "".join(f"{t:.6f},{v:.6g}\n" for t, v in zip(times, nees))
    path.write_text("time,nees\n" + rows)
    return path


def read_nees_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``(times (K,), nees (K,))`` of a file :func:`write_nees_csv` wrote."""
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return data[:, 0], data[:, 1]
