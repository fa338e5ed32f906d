"""Run the stochastic map over a landmark log and summarise the result."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..errors import DivergenceError
from ..landmark_log import LandmarkLog, Step
from .stochastic_map import CredibilityParams, StochasticMap


@dataclass
class EkfRun:
    times: np.ndarray        # (N,)
    poses: np.ndarray        # (N, 3) robot pose after each step
    pose_covs: np.ndarray    # (N, 3, 3)
    filter: StochasticMap
    seconds: float
    matched: int
    new: int
    unobserved: int
    removed: int
    associations: list[list[int | None]] | None = None  # per step, the feature id of each observation


def run_ekf(log: LandmarkLog, credibility: CredibilityParams | None = None, max_range: float | None = None,
            fov: float | None = None, known_association: bool | None = None,
            first_estimate_jacobians: bool = False) -> EkfRun:
    """Predict with each step's motion, then run the matching step on its observations.

    ``max_range``, ``fov`` (the sensor model for unobserved predictions) and
    ``known_association`` default to the log's; ``known_association=False`` forces gating.
    """
    t0 = time.perf_counter()
    max_range = log.max_range if max_range is None else max_range
    fov = log.fov if fov is None else fov
    if known_association is None:
        known_association = log.known_association
    ekf = StochasticMap(log.initial_pose, np.eye(3) * 1e-9, credibility, max_range=max_range, fov=fov,
                        first_estimate_jacobians=first_estimate_jacobians)
    times, poses, covs = [], [], []
    counts = dict(matched=0, new=0, unobserved=0, removed=0)
    associations: list[list[int | None]] = []
    for k, step in enumerate(log.steps):
        with np.errstate(over="ignore", invalid="ignore"):
            ekf.predict(step.motion, step.motion_cov)
        ids: list[int | None] = [None] * len(step.ranges_bearings)
        if len(step.ranges_bearings):
            with np.errstate(over="ignore", invalid="ignore"):
                rep = ekf.observe(step.ranges_bearings, log.measurement_cov, step.ids if known_association else None)
            if not (np.isfinite(ekf.x).all() and np.isfinite(ekf.P[:3, :3]).all()):  # NaN spreads through the robot block
                raise DivergenceError(f"{log.name}: the EKF diverged at step {k + 1} of {len(log.steps)} (t = {step.t:.2f})"
                                      + ("; the first-estimates Jacobians were too far off, run without them"
                                         if first_estimate_jacobians else ""))
            for m, fid in rep.matched + rep.new:
                ids[m] = fid
            counts["matched"] += len(rep.matched)
            counts["new"] += len(rep.new)
            counts["unobserved"] += len(rep.unobserved)
            counts["removed"] += len(rep.removed)
        associations.append(ids)
        times.append(step.t)
        poses.append(ekf.pose)
        covs.append(ekf.P[:3, :3].copy())
    return EkfRun(np.array(times), np.array(poses).reshape(-1, 3), np.array(covs).reshape(-1, 3, 3), ekf,
                  time.perf_counter() - t0, **counts, associations=associations)


def with_ekf_association(log: LandmarkLog, run: EkfRun) -> LandmarkLog:
    """``log`` with the ids the filter's gating gave each observation (ambiguous ones dropped),
    so a factor graph can solve the same data with the same data association."""
    from dataclasses import replace

    steps = []
    for step, ids in zip(log.steps, run.associations or []):
        keep = [m for m, fid in enumerate(ids) if fid is not None]
        steps.append(Step(step.t, step.motion, step.motion_cov, step.ranges_bearings[keep].reshape(-1, 2),
                          [ids[m] for m in keep]))
    return replace(log, steps=steps, known_association=True)


def landmark_rmse(estimates: dict[int, np.ndarray], truth: dict[int, np.ndarray]) -> tuple[float, int]:
    """RMSE [m] of estimated landmark positions against ground truth over shared ids."""
    common = sorted(set(estimates) & set(truth))
    if not common:
        return float("nan"), 0
    err = np.array([np.linalg.norm(estimates[k] - truth[k]) for k in common])
    return float(np.sqrt(np.mean(err**2))), len(common)


def landmark_errors_nearest(estimates: dict[int, np.ndarray], truth: dict[int, np.ndarray],
                            max_distance: float = 0.5) -> dict:
    """Errors when ids are not shared (unknown association): true landmarks and estimates that are
    each other's nearest neighbour within ``max_distance`` [m] form pairs.

    Returns ``rmse`` [m] over the pairs, how many true landmarks were ``found`` of ``total``, and
    ``spurious``: estimates in no pair (clutter the filter mapped, or landmarks far off).
    """
    E = np.array(list(estimates.values())).reshape(-1, 2)
    G = np.array(list(truth.values())).reshape(-1, 2)
    if len(E) == 0 or len(G) == 0:
        return {"rmse": float("nan"), "found": 0, "total": len(G), "spurious": len(E)}
    d = np.linalg.norm(G[:, None, :] - E[None, :, :], axis=2)  # (truth, estimates)
    best_e = d.argmin(axis=1)
    mutual = (d.argmin(axis=0)[best_e] == np.arange(len(G))) & (d[np.arange(len(G)), best_e] <= max_distance)
    errors = d[np.arange(len(G)), best_e][mutual]
    rmse = float(np.sqrt(np.mean(errors**2))) if len(errors) else float("nan")
    return {"rmse": rmse, "found": int(mutual.sum()), "total": len(G), "spurious": len(E) - int(mutual.sum())}


def trajectory_rmse(times: np.ndarray, poses: np.ndarray, truth_times: np.ndarray, truth_poses: np.ndarray) -> float:
    """Position RMSE [m] against ground truth interpolated at the estimate times (no alignment)."""
    x = np.interp(times, truth_times, truth_poses[:, 0])
    y = np.interp(times, truth_times, truth_poses[:, 1])
    return float(np.sqrt(np.mean((poses[:, 0] - x) ** 2 + (poses[:, 1] - y) ** 2)))
