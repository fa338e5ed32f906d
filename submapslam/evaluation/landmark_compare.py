"""EKF (stochastic map) vs factor graph vs ground truth on one landmark log.

Trajectory errors are position RMSE in the world frame (both estimators start at the log's
initial pose, so no alignment); landmark errors are over shared ids; covariance agreement
compares each landmark's EKF covariance with the graph's marginal by the ratio of their
determinants' square roots (ellipse areas) and the symmetric KL divergence.
"""

from __future__ import annotations

import numpy as np

from ..backend.landmark_graph import GraphSolution
from ..ekf.runner import EkfRun, landmark_rmse, trajectory_rmse
from ..io.landmark_logs import LandmarkLog


def _sym_kl(A: np.ndarray, B: np.ndarray) -> float:
    """Symmetric KL divergence between zero-mean Gaussians with ``(2, 2)`` covariances."""
    return float(0.5 * (np.trace(np.linalg.solve(A, B)) + np.trace(np.linalg.solve(B, A))) - 2.0)


def compare_landmark_solutions(log: LandmarkLog, run: EkfRun, sol: GraphSolution) -> dict:
    """Figures for one log: a flat dict of floats/ints, ready for ``summary.json``."""
    est = {lm["id"]: np.array([lm["x"], lm["y"]]) for lm in run.filter.landmarks()}
    ekf_cov = {lm["id"]: np.array([[lm["var_xx"], lm["var_xy"]], [lm["var_xy"], lm["var_yy"]]])
               for lm in run.filter.landmarks()}
    shared = sorted(set(est) & set(sol.landmarks))
    out: dict = {"ekf_seconds": run.seconds, "graph_seconds": sol.seconds, "landmarks_shared": len(shared),
                 "graph_error": sol.error}
    if shared:
        d = np.array([np.linalg.norm(est[k] - sol.landmarks[k]) for k in shared])
        out["ekf_vs_graph_landmark_rms_m"] = float(np.sqrt(np.mean(d**2)))
        out["ekf_vs_graph_landmark_max_m"] = float(d.max())
    dp = run.poses[-1] - sol.poses[-1]
    out["ekf_vs_graph_final_position_m"] = float(np.hypot(dp[0], dp[1]))
    out["ekf_vs_graph_final_heading_deg"] = float(abs(np.rad2deg((dp[2] + np.pi) % (2 * np.pi) - np.pi)))
    with_cov = [k for k in shared if k in sol.landmark_covs]
    if with_cov:
        area = [np.sqrt(np.linalg.det(ekf_cov[k]) / np.linalg.det(sol.landmark_covs[k])) for k in with_cov]
        kl = [_sym_kl(ekf_cov[k], sol.landmark_covs[k]) for k in with_cov]
        out["cov_area_ratio_median"] = float(np.median(area))   # EKF ellipse area / graph ellipse area
        out["cov_sym_kl_median"] = float(np.median(kl))
    if log.truth_landmarks:
        out["ekf_landmark_rmse_m"], _ = landmark_rmse(est, log.truth_landmarks)
        out["graph_landmark_rmse_m"], _ = landmark_rmse(sol.landmarks, log.truth_landmarks)
    if log.truth_poses is not None:
        out["ekf_trajectory_rmse_m"] = trajectory_rmse(run.times, run.poses, log.truth_times, log.truth_poses)
        out["graph_trajectory_rmse_m"] = trajectory_rmse(run.times, sol.poses[1:], log.truth_times, log.truth_poses)
    return out
