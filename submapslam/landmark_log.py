"""Core landmark-log types: the input of the stochastic map and the landmark factor graph.

A :class:`LandmarkLog` is a time-ordered list of :class:`Step` s, each a motion
``(dx, dy, dtheta)`` in the robot frame with its covariance followed by the range-bearing
observations made at the step's end (with known landmark ids when the log gives them).
Readers for MR.CLAM, Victoria Park and point-cloud logs live in :mod:`submapslam.io.landmark_logs`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Step:
    """Motion then observations. ``ranges_bearings (M, 2)``, ``ids`` per observation (or None)."""

    t: float
    motion: np.ndarray            # (3,) dx, dy, dtheta in the robot frame
    motion_cov: np.ndarray        # (3, 3)
    ranges_bearings: np.ndarray   # (M, 2)
    ids: list[int | None]


@dataclass
class LandmarkLog:
    name: str
    initial_pose: np.ndarray                  # (3,) world frame
    steps: list[Step]
    measurement_cov: np.ndarray               # (2, 2) range [m], bearing [rad]
    truth_times: np.ndarray | None = None     # ground truth (N,), (N, 3)
    truth_poses: np.ndarray | None = None
    truth_landmarks: dict[int, np.ndarray] = field(default_factory=dict)
    known_association: bool = True            # observations carry landmark ids
    max_range: float = np.inf                 # sensor model for unobserved predictions [m]
    fov: float = 2 * np.pi                    # [rad], centred on the robot's heading
    # ground truth of a changing world: landmark id -> (first, end) step times, the landmark
    # exists for first <= step.t < end (synthetic logs with landmarks that vanish or appear)
    truth_lifetimes: dict[int, tuple[float, float]] = field(default_factory=dict)
