"""NEES of one EKF run's robot poses against ground truth, where the log has it."""

from __future__ import annotations

import numpy as np

from .landmark_compare import nees_series


def pose_nees_against_truth(times: np.ndarray, poses: np.ndarray, covs: np.ndarray, truth_times: np.ndarray,
                            truth_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """NEES per step of ``(N, 3)`` ``x, y, yaw`` estimates with ``(N, 3, 3)`` covariances at
    ``times (N,)`` against the truth ``(M, 3)`` at ``truth_times (M,)``, interpolated (yaw
    unwrapped). Steps outside the truth's time span are left out.

    Returns ``(times (K,), nees (K,))``; a consistent filter's NEES averages 3 (3 DOF).
    """
    t = np.asarray(times, dtype=np.float64)
    tt = np.asarray(truth_times, dtype=np.float64)
    keep = (t >= tt[0]) & (t <= tt[-1])
    t = t[keep]
    truth = np.stack([np.interp(t, tt, truth_poses[:, 0]), np.interp(t, tt, truth_poses[:, 1]),
                      np.interp(t, tt, np.unwrap(truth_poses[:, 2]))], axis=1)
    return t, nees_series(np.asarray(poses)[keep], np.asarray(covs)[keep], truth)
