"""What a report knows about one run: the contents of a results folder as core types.

Filled by :func:`submapslam.io.run_folder.read_run_folder`; the report code reads no files.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..trajectory import Trajectory


@dataclass
class GridImage:
    """An occupancy grid as written (``map.pgm``): ``image (rows, cols)`` uint8, row 0 = top
    (largest y), 0 occupied, 254 free, 205 unknown; ``origin`` ``(x, y)`` [m] of the lower-left
    cell's corner; ``resolution`` [m/cell]."""

    image: np.ndarray
    origin: np.ndarray
    resolution: float

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(x_min, x_max, y_min, y_max)`` [m] for ``imshow``."""
        rows, cols = self.image.shape
        x0, y0 = float(self.origin[0]), float(self.origin[1])
        return x0, x0 + cols * self.resolution, y0, y0 + rows * self.resolution


@dataclass
class RunRecord:
    """One results folder (``submapslam run`` or ``submapslam ekf``).

    Attributes:
        folder: the folder, as given.
        summary: ``summary.json``.
        config_text: ``config.yaml`` (the effective config) or None.
        provenance: ``input.json`` (file, size, SHA-256, scans, duration) or None.
        poses, odometry: ``poses_tum.txt`` and ``odometry_tum.txt`` (before loop closure).
        pose_covariances: ``poses_cov.txt``'s ``(N, 6, 6)`` covariance of each pose of ``poses`` (GTSAM
            order ``rx, ry, rz, x, y, z``, the pose's own frame), or None when the run wrote none.
        submaps: ``submaps.csv`` columns by name (``x``, ``y``, ``yaw``, ``sigma_x`` ... ``cov_xy``).
        loops: ``loops.csv`` rows by column name, as text.
        grid: ``map.pgm`` + ``map.yaml``; cloud: ``map.ply`` ``(M, 3)`` world frame (3D runs).
        landmarks: ``landmarks.csv`` rows (EKF runs: ``id, x, y, var_xx, var_xy, var_yy, credibility``).
        nees: ``nees.json`` (``ekf-nees``) when present.
        pose_nees: ``nees.csv`` ``(times (K,), NEES (K,))`` of an EKF run against its truth.
        truth_landmarks: ``landmarks_truth.csv`` ``(L, 2)`` x, y of the true landmarks (EKF runs of a
            log that knows them), in the run's frame.
    """

    folder: str
    summary: dict = field(default_factory=dict)
    config_text: str | None = None
    provenance: dict | None = None
    poses: Trajectory | None = None
    odometry: Trajectory | None = None
    pose_covariances: np.ndarray | None = None
    submaps: dict[str, np.ndarray] | None = None
    loops: list[dict[str, str]] = field(default_factory=list)
    grid: GridImage | None = None
    cloud: np.ndarray | None = None
    landmarks: list[dict[str, float]] | None = None
    nees: dict | None = None
    pose_nees: tuple[np.ndarray, np.ndarray] | None = None
    truth_landmarks: np.ndarray | None = None

    @property
    def kind(self) -> str:
        """``"ekf"`` for a stochastic-map run, else ``"submaps"``."""
        return "ekf" if self.landmarks is not None else "submaps"
