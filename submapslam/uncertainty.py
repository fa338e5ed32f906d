"""The uncertainty a run reports: calibrated anchor covariances and per-scan pose covariances.

Covariances are ``(6, 6)`` in GTSAM's Pose3 tangent order ``(rx, ry, rz, tx, ty, tz)`` [rad, m],
right perturbations in the pose's own frame: ``T_true = T_est Exp(xi)``, ``xi ~ N(0, Sigma)``.

The graph's marginals are not calibrated: against the truth of the Monte Carlo worlds
(``tools/bench_calibration.py``) their variances are off by factors that differ per axis, and the
worlds disagree with the real logs. A run therefore reports ``D Sigma D``, ``D = diag(sqrt(scale))``,
``scale`` per axis chosen by one rule, a conservative envelope: the larger of the mean
``(e/sigma)^2`` of the anchors on the Monte Carlo worlds it was fitted on (2D: rectangle, 2 laps,
seeds 0-19; 3D: terrain city along KITTI 05, 200 scans, seeds 0-11) and the mean ``(e/sigma)^2``
of the raw covariances on a real log against its reference (2D: Intel against its corrected log;
3D: the Livox loop against FAST-LIO2): the most overconfident of them ends at 1, none above. The
synthetic 2D world is far easier than Intel (anchors 50-100x inside their raw sigma, Intel at
1.6-1.7 in x and y), so the real log sets the 2D scale; in 3D the Livox loop sets yaw and y.
Figures and the checks on worlds the scales were not fitted on: BENCHMARKS.md, "Calibrated
covariances". For a graph whose every factor's information were divided by a common per-axis
factor the estimate would not move and the marginals would scale the same way; with per-axis
factors and rotations between anchors this is an approximation (exact for yaw-only rotations when
x and y share one factor). The graph, its estimate and the gates that read its covariances are
untouched.
"""

from __future__ import annotations

import numpy as np

from .config import BackendConfig
from .geometry import rotation_angle

#: variance scale per axis (GTSAM order: roll, pitch, yaw, x, y, z) of planar runs. Rectangle
#: Monte Carlo: yaw 0.01, x 0.02, y 0.01; Intel raw: yaw 0.26, x 1.62, y 1.69 -> Intel's (roll,
#: pitch and z are pinned in planar runs and keep their pinned sigma)
COVARIANCE_SCALE_PLANAR = (1.0, 1.0, 0.26, 1.62, 1.69, 1.0)
#: variance scale per axis (GTSAM order) of 3D runs. Terrain city 05 Monte Carlo: roll 0.62, pitch
#: 2.35, yaw 0.005, x 0.36, y 0.03, z 2.28; Livox loop raw: roll 0.22, pitch 0.09, yaw 0.16, x 0.18,
#: y 0.96, z 0.25 -> yaw and y from the Livox loop, the rest from the Monte Carlo
COVARIANCE_SCALE_3D = (0.62, 2.35, 0.16, 0.36, 0.96, 2.28)


def covariance_scale(config: BackendConfig, planar: bool) -> np.ndarray:
    """``(6,)`` variance scale per axis (GTSAM order): the config's, else the fitted default."""
    if config.covariance_scale is not None:
        return np.asarray(config.covariance_scale, dtype=np.float64)
    return np.asarray(COVARIANCE_SCALE_PLANAR if planar else COVARIANCE_SCALE_3D, dtype=np.float64)


def calibrate(covariances: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """``(..., 6, 6)`` covariances (GTSAM order, each in its pose's frame) scaled per axis:
    ``D Sigma D`` with ``D = diag(sqrt(scale))``; correlations are kept."""
    d = np.sqrt(np.asarray(scale, dtype=np.float64))
    return np.asarray(covariances, dtype=np.float64) * np.outer(d, d)


def odometry_information(T_i_j: np.ndarray, distance: float, planar: bool, config: BackendConfig) -> np.ndarray:
    """Information ``(6, 6)`` (GTSAM order) of an odometry edge between consecutive anchors.

    Drift model of scan-to-map odometry: translation sigma ``odometry_drift`` of the distance
    travelled plus a floor; rotation sigma ``odometry_drift_deg_per_m`` per metre plus a
    fraction of the turned angle plus a floor (:meth:`BackendConfig.rotation_drift`). For planar
    logs z, roll and pitch are pinned (they are not observable and must not drift).
    """
    angle = rotation_angle(T_i_j)
    per_m, turn = config.rotation_drift(planar)
    s_t = config.odometry_sigma_floor_m + config.odometry_drift * distance
    s_r = np.deg2rad(config.odometry_sigma_floor_deg) + np.deg2rad(per_m) * distance + turn * angle
    sig = np.array([s_r, s_r, s_r, s_t, s_t, s_t])
    if planar:
        sig[[0, 1, 5]] = 1e-4
    return np.diag(1.0 / sig**2)


def within_submap_covariance(T_anchor_scan: np.ndarray, distance: float, planar: bool,
                             config: BackendConfig) -> np.ndarray:
    """``(6, 6)`` covariance (GTSAM order, scan frame) of a scan's pose relative to its anchor:
    the odometry edges' drift model over ``distance`` [m] travelled since the anchor
    (:func:`odometry_information`); zero at the anchor itself."""
    if distance <= 0.0 and np.allclose(T_anchor_scan, np.eye(4)):
        return np.zeros((6, 6))
    return np.linalg.inv(odometry_information(T_anchor_scan, distance, planar, config))


def scan_covariances(result) -> np.ndarray | None:
    """``(N, 6, 6)`` covariance of every scan pose of a :class:`~submapslam.result.SlamResult`
    (GTSAM order, each in its scan's frame, right perturbation of ``result.poses[k]``).

    Its anchor's reported marginal (already calibrated by the pipeline) carried to the scan, ``Ad(T_anchor_scan^-1) Sigma
    Ad(.)^T``, plus (except for the anchor's own scan) the drift model from the anchor to the scan,
    scaled by the same per-axis factors as the anchors (:func:`covariance_scale`). A scan shared
    by two submaps (the last of one is the anchor of the next) takes the later submap's, i.e. its
    anchor's. None when the run has no covariances (an empty run, a failed final optimisation).
    """
    from .geometry import adjoint, inverse

    covs = np.asarray(result.submap_covariances, dtype=np.float64)
    if len(covs) == 0 or not np.isfinite(covs).all():
        return None
    backend = result.config.backend
    scale = covariance_scale(backend, result.planar)
    out = np.full((len(result.poses), 6, 6), np.nan)
    for k, (idx, T_scans) in enumerate(zip(result.submap_scan_indices, result.submap_scan_poses)):
        steps = np.linalg.norm(np.diff(np.asarray(T_scans)[:, :3, 3], axis=0), axis=1)
        travelled = np.concatenate([[0.0], np.cumsum(steps)])
        for m, (s, T, dist) in enumerate(zip(idx, T_scans, travelled)):
            A = adjoint(inverse(T))
            if m == 0:  # the anchor's own scan (a refined 2D scan may sit a few mm off it): the anchor's
                out[s] = A @ covs[k] @ A.T
                continue
            rel = calibrate(within_submap_covariance(T, float(dist), result.planar, backend), scale)
            out[s] = A @ covs[k] @ A.T + rel
    return out
