"""EKF (stochastic map) vs factor graph vs ground truth on one landmark log; the EKF's summary,
its NEES study and plots.

Trajectory errors are position RMSE in the world frame (both estimators start at the log's
initial pose, so no alignment); landmark errors are over shared ids; covariance agreement
compares each landmark's EKF covariance with the graph's marginal by the ratio of their
determinants' square roots (ellipse areas) and the symmetric KL divergence.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from ..backend.landmark_graph import GraphSolution
from ..ekf.runner import EkfRun, landmark_errors_nearest, landmark_rmse, trajectory_rmse
from ..errors import SubmapSlamError
from ..landmark_log import LandmarkLog


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
    if log.truth_landmarks and log.known_association:
        out["ekf_landmark_rmse_m"], _ = landmark_rmse(est, log.truth_landmarks)
        out["graph_landmark_rmse_m"], _ = landmark_rmse(sol.landmarks, log.truth_landmarks)
    elif log.truth_landmarks:  # ids are the filter's own: match each true landmark to the nearest
        out["ekf_landmark_rmse_m"] = landmark_errors_nearest(est, log.truth_landmarks)["rmse"]
        out["graph_landmark_rmse_m"] = landmark_errors_nearest(sol.landmarks, log.truth_landmarks)["rmse"]
    if log.truth_poses is not None:
        out["ekf_trajectory_rmse_m"] = trajectory_rmse(run.times, run.poses, log.truth_times, log.truth_poses)
        out["graph_trajectory_rmse_m"] = trajectory_rmse(run.times, sol.poses[1:], log.truth_times, log.truth_poses)
    return out


def ekf_summary(log: LandmarkLog, run: EkfRun, compare: bool = False, incremental: bool = False) -> dict:
    """What ``submapslam ekf`` reports (``summary.json``): counts of the matching step, time,
    landmark and trajectory errors against the log's ground truth where it has one, and with
    ``compare`` the factor graph solved on the same data (iSAM2 step by step with
    ``incremental``, else batch LM warm-started) as ``comparison``
    (:func:`compare_landmark_solutions`). Without ids in the log, the graph gets the filter's
    own data association and landmarks are matched to the truth by nearest neighbour."""
    est = {lm["id"]: np.array([lm["x"], lm["y"]]) for lm in run.filter.landmarks()}
    summary = {"log": log.name, "jacobians": "first estimates" if run.filter.fej else "current estimates",
               "steps": len(log.steps), "features": run.filter.n, "ekf_seconds": round(run.seconds, 3),
               "matched": run.matched, "new": run.new, "unobserved": run.unobserved, "removed": run.removed}
    if log.truth_landmarks and log.known_association:
        summary["ekf_landmark_rmse_m"], summary["landmarks_compared"] = landmark_rmse(est, log.truth_landmarks)
    elif log.truth_landmarks:
        near = landmark_errors_nearest(est, log.truth_landmarks)
        summary["ekf_landmark_rmse_m"], summary["landmarks_compared"] = near["rmse"], near["found"]
        summary["landmarks_total"], summary["spurious_features"] = near["total"], near["spurious"]
    if log.truth_poses is not None:
        summary["ekf_trajectory_rmse_m"] = trajectory_rmse(run.times, run.poses, log.truth_times, log.truth_poses)
    if log.truth_lifetimes:
        from ..ekf.runner import landmark_turnover, turnover_summary

        summary["turnover"] = turnover_summary(landmark_turnover(log, run))
    if compare:
        from ..backend.landmark_graph import solve_landmark_graph
        from ..ekf.runner import with_ekf_association

        graph_log = log if log.known_association else with_ekf_association(log, run)
        sol = solve_landmark_graph(graph_log, incremental=incremental, warm_start=True)
        summary["comparison"] = compare_landmark_solutions(log, run, sol)
    return summary


def nees_series(est: np.ndarray, covs: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """NEES per step of ``(N, 3)`` pose estimates with ``(N, 3, 3)`` covariances against ``(N, 3)`` truth."""
    e = np.asarray(est, dtype=np.float64) - truth
    e[:, 2] = (e[:, 2] + np.pi) % (2 * np.pi) - np.pi
    P = covs + np.eye(3) * 1e-12
    return np.einsum("ni,ni->n", e, np.linalg.solve(P, e[:, :, None])[:, :, 0])


def nees_study(trials: Iterable[tuple[LandmarkLog, np.ndarray]], with_graph: bool = True) -> dict:
    """Monte Carlo NEES of the robot pose: EKF, FEJ-EKF, smoother.

    ``trials``: ``(log, truth)`` per Monte Carlo run, ``truth`` ``(N, 3)`` the true ``x, y, yaw``
    of every pose in the log's frame (pose ``k`` is where the step with time ``k`` ends), all
    runs with the same number of steps.

    Returns ``{"ekf": (N,), "ekf_fej": (N,), "graph": (N,) or None, "band": (lo, hi), "runs": runs,
    "ekf_left_band_at": step or None, "ekf_fej_left_band_at": ..., "graph_left_band_at": ...}``:
    the per-step NEES averaged over the runs (the seed's EKF, the same filter with
    first-estimates Jacobians, and the factor graph's all-pose marginals), the two-sided 95 %
    chi-square band for that average (3 DOF), and the first step where a 10-step moving average
    of the mean NEES leaves the band.
    """
    from scipy.stats import chi2

    from ..backend.landmark_graph import solve_landmark_graph
    from ..ekf.runner import run_ekf
    from ..ekf.stochastic_map import CredibilityParams

    keep = CredibilityParams(b=1e9, remove_below=0.0)
    ekf_all, fej_all, fg_all = [], [], []
    for log, truth in trials:
        run = run_ekf(log, keep)
        at = truth[run.times.astype(int)]  # a step's time is the index of the pose it ends at
        ekf_all.append(nees_series(run.poses, run.pose_covs, at))
        fej = run_ekf(log, keep, first_estimate_jacobians=True)
        fej_all.append(nees_series(fej.poses, fej.pose_covs, at))
        if with_graph:
            sol = solve_landmark_graph(log, pose_covariances=True)
            fg_all.append(nees_series(sol.poses[1:], sol.pose_covs[1:], at))
    runs = len(ekf_all)
    if runs < 2:
        raise SubmapSlamError(f"a NEES study needs at least 2 runs, got {runs}")
    lo, hi = chi2.ppf(0.025, 3 * runs) / runs, chi2.ppf(0.975, 3 * runs) / runs

    def left(series: np.ndarray) -> int | None:
        smooth = np.convolve(series, np.ones(10) / 10, mode="valid")
        out = np.flatnonzero((smooth < lo) | (smooth > hi))
        return int(out[0]) + 1 if len(out) else None

    ekf, ekf_fej = np.mean(ekf_all, axis=0), np.mean(fej_all, axis=0)
    graph = np.mean(fg_all, axis=0) if fg_all else None
    return {"ekf": ekf, "ekf_fej": ekf_fej, "graph": graph, "band": (float(lo), float(hi)), "runs": runs,
            "ekf_left_band_at": left(ekf), "ekf_fej_left_band_at": left(ekf_fej),
            "graph_left_band_at": left(graph) if graph is not None else None}


def joint_landmark_nees(ids: list[int], est: np.ndarray, cov: np.ndarray, truth: dict[int, np.ndarray]) -> float:
    """NEES of all landmarks at once: ``e^T P^-1 e`` of the stacked ``(2L,)`` error of estimates
    ``est`` ``(2L,)`` (``x_i, y_i`` in the order of ``ids``) against ``truth`` (id -> ``(2,)``, same
    frame) with their joint ``(2L, 2L)`` covariance; chi-square with ``2L`` DOF when consistent.
    Landmarks of one run are correlated (they share the robot's error), so only the joint NEES is
    one sample; the runs are independent."""
    e = np.asarray(est, dtype=np.float64) - np.concatenate([truth[i] for i in ids])
    return float(e @ np.linalg.solve(cov, e))


def ekf_landmark_joint(run: EkfRun) -> tuple[list[int], np.ndarray, np.ndarray]:
    """``(ids, (2L,) estimates, (2L, 2L) joint covariance)`` of the stochastic map's features."""
    f = run.filter
    idx = np.concatenate([[3 + 2 * k, 4 + 2 * k] for k in range(f.n)]).astype(int)
    return list(f.ids), f.x[idx].copy(), f.P[np.ix_(idx, idx)].copy()


def covariance_agreement(run: EkfRun, sol: GraphSolution) -> dict:
    """How far the EKF's covariances are from the graph's marginals, per landmark and for the last
    pose (world frame): the largest symmetric KL divergence over the landmarks, and the ratio of
    ellipse areas (EKF / graph, square root of the determinants' ratio) at its smallest and largest."""
    ekf_cov = {lm["id"]: np.array([[lm["var_xx"], lm["var_xy"]], [lm["var_xy"], lm["var_yy"]]])
               for lm in run.filter.landmarks()}
    shared = sorted(set(ekf_cov) & set(sol.landmark_covs))
    area = np.array([np.sqrt(np.linalg.det(ekf_cov[k]) / np.linalg.det(sol.landmark_covs[k])) for k in shared])
    out = {"landmarks": len(shared), "landmark_sym_kl_max": max(_sym_kl(ekf_cov[k], sol.landmark_covs[k])
                                                               for k in shared),
           "landmark_area_ratio_min": float(area.min()), "landmark_area_ratio_max": float(area.max())}
    if sol.pose_covs is not None:
        P_e, P_g = run.pose_covs[-1], sol.pose_covs[-1]
        out["final_pose_sym_kl"] = _sym_kl_n(P_e, P_g)
        out["final_pose_sigma_ratio"] = (np.sqrt(np.diag(P_e) / np.diag(P_g))).tolist()  # x, y, yaw
    return out


def _sym_kl_n(A: np.ndarray, B: np.ndarray) -> float:
    """Symmetric KL divergence between zero-mean Gaussians with ``(n, n)`` covariances."""
    n = len(A)
    return float(0.5 * (np.trace(np.linalg.solve(B, A)) + np.trace(np.linalg.solve(A, B))) - n)


def landmark_consistency_study(trials: Iterable[tuple[LandmarkLog, np.ndarray]]) -> dict:
    """Monte Carlo over landmark worlds: the EKF and the graph against the truth and each other.

    Per run: the joint landmark NEES per DOF (:func:`joint_landmark_nees` / ``2L``) and the final
    pose's NEES (3 DOF) of both estimators, and :func:`covariance_agreement`. Returns the per-run
    lists, their means and the two-sided 95 % band of each mean (chi-square of the summed DOF over
    it: the runs are independent, so these bands are exact for consistent estimators), and the
    worst agreement over the runs.
    """
    from scipy.stats import chi2

    from ..backend.landmark_graph import solve_landmark_graph
    from ..ekf.runner import run_ekf
    from ..ekf.stochastic_map import CredibilityParams

    keep = CredibilityParams(b=1e9, remove_below=0.0)
    rows = []
    for log, truth in trials:
        run = run_ekf(log, keep)
        sol = solve_landmark_graph(log, pose_covariances=True, landmark_joint=True)
        ids, x, P = ekf_landmark_joint(run)
        order = np.argsort(ids)
        ids_s = [ids[i] for i in order]
        sel = np.concatenate([[2 * i, 2 * i + 1] for i in order])
        g_ids, g_cov = sol.landmark_joint_cov
        assert g_ids == ids_s, "the EKF and the graph hold different landmarks"
        g_est = np.concatenate([sol.landmarks[i] for i in g_ids])
        end = truth[int(run.times[-1])]
        rows.append({"dof": 2 * len(ids_s),
                     "ekf_landmark_nees": joint_landmark_nees(ids_s, x[sel], P[np.ix_(sel, sel)], log.truth_landmarks),
                     "graph_landmark_nees": joint_landmark_nees(g_ids, g_est, g_cov, log.truth_landmarks),
                     "ekf_final_nees": float(nees_series(run.poses[-1:], run.pose_covs[-1:], end[None])[0]),
                     "graph_final_nees": float(nees_series(sol.poses[-1:], sol.pose_covs[-1:], end[None])[0]),
                     **covariance_agreement(run, sol)})
    runs = len(rows)
    if runs < 2:
        raise SubmapSlamError(f"a consistency study needs at least 2 runs, got {runs}")
    dof = sum(r["dof"] for r in rows)
    out: dict = {"runs": runs, "landmark_dof": dof,
                 "landmark_nees_per_dof_band_95": [chi2.ppf(0.025, dof) / dof, chi2.ppf(0.975, dof) / dof],
                 "final_nees_band_95": [chi2.ppf(0.025, 3 * runs) / runs, chi2.ppf(0.975, 3 * runs) / runs]}
    for who in ("ekf", "graph"):
        out[f"{who}_landmark_nees_per_dof"] = sum(r[f"{who}_landmark_nees"] for r in rows) / dof
        out[f"{who}_final_nees_mean"] = float(np.mean([r[f"{who}_final_nees"] for r in rows]))
    out["landmark_sym_kl_max"] = max(r["landmark_sym_kl_max"] for r in rows)
    out["landmark_area_ratio_range"] = [min(r["landmark_area_ratio_min"] for r in rows),
                                        max(r["landmark_area_ratio_max"] for r in rows)]
    out["final_pose_sym_kl_max"] = max(r["final_pose_sym_kl"] for r in rows)
    out["per_run"] = rows
    return out


def nees_summary(study: dict) -> dict:
    """The figures of a :func:`nees_study` as plain JSON values (``nees.json``): the band, the
    fraction of steps the EKF's mean NEES lies inside it, where each estimator leaves it, and
    the per-step means."""
    lo, hi = study["band"]
    return {"runs": study["runs"], "band_95": [lo, hi],
            "ekf_fraction_inside": float(np.mean((study["ekf"] >= lo) & (study["ekf"] <= hi))),
            "ekf_left_band_at": study["ekf_left_band_at"], "ekf_fej_left_band_at": study["ekf_fej_left_band_at"],
            "graph_left_band_at": study["graph_left_band_at"],
            "ekf_mean_nees": study["ekf"].tolist(), "ekf_fej_mean_nees": study["ekf_fej"].tolist(),
            "graph_mean_nees": None if study["graph"] is None else study["graph"].tolist()}


def plot_nees(path: str | Path, study: dict) -> None:
    """Mean NEES per step with the 95 % band (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    lo, hi = study["band"]
    ax.axhspan(lo, hi, color="0.85", label="95 % band")
    ax.plot(np.arange(1, len(study["ekf"]) + 1), study["ekf"], label="EKF (filter)")
    if study.get("ekf_fej") is not None:
        ax.plot(np.arange(1, len(study["ekf_fej"]) + 1), study["ekf_fej"], label="FEJ-EKF (first-estimates Jacobians)")
    if study["graph"] is not None:
        ax.plot(np.arange(1, len(study["graph"]) + 1), study["graph"], label="factor graph (smoother)")
    ax.set_xlabel("step")
    ax.set_ylabel(f"mean NEES over {study['runs']} runs")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_stochastic_map(path: str | Path, run: EkfRun, truth_landmarks: dict[int, np.ndarray] | None = None,
                        truth_poses: np.ndarray | None = None) -> None:
    """Features with 3-sigma uncertainty ellipses coloured by credibility (seed fig. 5.39)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse

    fig, ax = plt.subplots(figsize=(8, 8))
    if truth_poses is not None:
        ax.plot(truth_poses[:, 0], truth_poses[:, 1], color="0.7", lw=0.8, label="ground truth path")
    ax.plot(run.poses[:, 0], run.poses[:, 1], "b-", lw=0.8, label="EKF path")
    cmap = plt.get_cmap("viridis")
    for lm in run.filter.landmarks():
        C = np.array([[lm["var_xx"], lm["var_xy"]], [lm["var_xy"], lm["var_yy"]]])
        w, V = np.linalg.eigh(C)
        angle = np.degrees(np.arctan2(V[1, 1], V[0, 1]))
        color = cmap(lm["credibility"])
        ax.add_patch(Ellipse((lm["x"], lm["y"]), 6 * np.sqrt(max(w[1], 0)), 6 * np.sqrt(max(w[0], 0)), angle=angle,
                             fill=False, color=color, lw=1.2))
        ax.plot(lm["x"], lm["y"], "+", color=color)
    if truth_landmarks:
        t = np.array(list(truth_landmarks.values()))
        ax.plot(t[:, 0], t[:, 1], "kx", ms=5, label="ground-truth landmarks")
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, 1))
    fig.colorbar(sm, ax=ax, label="credibility c_t", shrink=0.7)
    ax.set_aspect("equal")
    ax.legend(fontsize=8, loc="best")
    ax.set_title("stochastic map: features, 3-sigma ellipses, credibility")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
