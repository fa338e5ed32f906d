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


def nearest_stamps(times: np.ndarray, queries: np.ndarray, max_diff: float) -> np.ndarray:
    """``(M,)`` index into ``times`` ``(N,)`` [s] (any order) of the stamp nearest each of ``queries``
    ``(M,)`` [s], -1 where none lies within ``max_diff`` [s]; on a tie the earlier stamp."""
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    queries = np.asarray(queries, dtype=np.float64).reshape(-1)
    if not len(times):
        return np.full(len(queries), -1, dtype=np.int64)
    order = np.argsort(times, kind="stable")
    sorted_ts = times[order]
    k = np.clip(np.searchsorted(sorted_ts, queries), 1, max(len(sorted_ts) - 1, 1))
    if len(sorted_ts) == 1:
        best = np.zeros(len(queries), dtype=np.int64)
    else:
        best = np.where(np.abs(sorted_ts[k - 1] - queries) <= np.abs(sorted_ts[k] - queries), k - 1, k)
    idx = order[best]
    idx[np.abs(times[idx] - queries) > max_diff] = -1
    return idx
