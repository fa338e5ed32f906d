"""Core trajectory types: timestamped poses and relative-pose relations (no file I/O).

Readers and writers for TUM, KITTI and CARMEN files live in :mod:`submapslam.io.trajectory`
and return these types; metrics in :mod:`submapslam.evaluation.metrics` take them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Trajectory:
    """Timestamped poses: ``timestamps (N,)`` [s], ``poses (N, 4, 4)`` ``T_world_base``."""

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.poses):
            raise ValueError(f"{len(self.timestamps)} timestamps for {len(self.poses)} poses")

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def positions(self) -> np.ndarray:
        """``(N, 3)`` translations."""
        return self.poses[:, :3, 3]

    def subset(self, index: np.ndarray) -> Trajectory:
        return Trajectory(self.timestamps[index], self.poses[index])

    def path_length(self) -> float:
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum()) if len(self) > 1 else 0.0


@dataclass
class Relations:
    """Relative-pose relations (Kümmerle et al. 2009): ``T_a_b`` between poses stamped ``t_a``, ``t_b``."""

    t_a: np.ndarray
    t_b: np.ndarray
    T_a_b: np.ndarray  # (R, 4, 4)

    def __len__(self) -> int:
        return len(self.t_a)
