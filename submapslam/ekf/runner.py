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
    added_at: list[tuple[int, int]] | None = None      # (step index, feature id) of every new feature
    removed_at: list[tuple[int, int]] | None = None    # (step index, feature id) of every removal
    unobserved_at: list[list[int]] | None = None       # per step, the feature ids predicted in view but not seen


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
    added_at: list[tuple[int, int]] = []
    removed_at: list[tuple[int, int]] = []
    unobserved_at: list[list[int]] = []
    for k, step in enumerate(log.steps):
        with np.errstate(over="ignore", invalid="ignore"):
            ekf.predict(step.motion, step.motion_cov)
        ids: list[int | None] = [None] * len(step.ranges_bearings)
        missed: list[int] = []
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
            added_at += [(k, fid) for _, fid in rep.new]
            removed_at += [(k, fid) for fid in rep.removed]
            missed = rep.unobserved
        associations.append(ids)
        unobserved_at.append(missed)
        times.append(step.t)
        poses.append(ekf.pose)
        covs.append(ekf.P[:3, :3].copy())
    return EkfRun(np.array(times), np.array(poses).reshape(-1, 3), np.array(covs).reshape(-1, 3, 3), ekf,
                  time.perf_counter() - t0, **counts, associations=associations, added_at=added_at,
                  removed_at=removed_at, unobserved_at=unobserved_at)


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


def landmark_turnover(log: LandmarkLog, run: EkfRun) -> dict:
    """How the map followed a changing world: the log's ``truth_lifetimes`` (landmark id ->
    ``(first, end)`` step times, present for ``first <= t < end``) against the filter's
    removals and new features. The log's observation ids are the truth (the filter may have run
    without them, ``known_association=False``); a vanished landmark is the feature its last
    observation was associated with, a new one the feature its first observation was.

    Returns ``vanished`` (landmarks that left before the end), ``vanished_removed``,
    ``removal_delay_steps`` / ``removal_delay_m`` / ``removal_misses`` (per removed vanished
    landmark: steps from its disappearance to its removal, counting the step that removed it;
    metres the robot drove meanwhile, from the truth; how often the filter counted it unobserved
    meanwhile), ``static`` and ``static_removed`` (landmarks present from start to end that a
    removal left without a feature, and vanished ones so removed before they left: must be
    empty; ``duplicates_removed`` counts removals of a second feature of a landmark that kept
    another),
    ``appeared``, ``appeared_added`` (landmarks that entered the world and were founded as a
    feature of their own after they entered) and ``add_delay_steps`` (from entering to founding),
    ``spurious_left``: features alive at the end that no true landmark's observation ever matched
    (clutter the map kept).
    """
    if not log.truth_lifetimes:
        raise ValueError("the log has no landmark lifetimes (truth_lifetimes)")
    times = np.array([s.t for s in log.steps], dtype=np.float64)
    seen_as: dict[int, list[tuple[int, int]]] = {}  # true id -> (step index, feature id) of its observations
    for k, (step, fids) in enumerate(zip(log.steps, run.associations or [])):
        for tid, fid in zip(step.ids, fids):
            if tid is not None and fid is not None:
                seen_as.setdefault(tid, []).append((k, fid))
    removed = {}
    for k, fid in run.removed_at or []:
        removed.setdefault(fid, []).append(k)
    added: dict[int, int] = {}
    for k, fid in run.added_at or []:
        added.setdefault(fid, k)  # its first founding
    t_end_log = times[-1] + 1 if len(times) else 0.0
    travelled = None
    if log.truth_poses is not None:
        seg = np.linalg.norm(np.diff(log.truth_poses[:, :2], axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        travelled = lambda t0, t1: float(np.interp(t1, log.truth_times, cum) - np.interp(t0, log.truth_times, cum))  # noqa: E731
    real = {fid for tid, pairs in seen_as.items() if tid in log.truth_lifetimes for _, fid in pairs}
    lives: dict[int, list[list[float]]] = {}  # feature id -> [added, removed) step intervals
    for k, fid in sorted([(k, f) for k, f in run.added_at or []]):
        lives.setdefault(fid, []).append([k, np.inf])
    for k, fid in sorted(run.removed_at or []):
        open_ = [iv for iv in lives.get(fid, []) if iv[0] <= k and iv[1] == np.inf]
        if open_:
            open_[-1][1] = k

    def alive(fid: int, k: int) -> bool:
        """Whether feature ``fid`` is in the map after step ``k``."""
        return any(a <= k < r for a, r in lives.get(fid, []))

    def seen_by(tid: int, fid: int, k: int) -> bool:
        """Whether an observation of true landmark ``tid`` was associated with ``fid`` by step ``k``."""
        return any(j <= k and f == fid for j, f in seen_as.get(tid, []))
    out = {"spurious_left": len([f for f in run.filter.ids if f not in real]), "duplicates_removed": 0, "vanished": 0, "vanished_removed": 0, "removal_delay_steps": [], "removal_delay_m": [],
           "removal_misses": [], "vanished_kept": [], "static": 0, "static_removed": [], "appeared": 0,
           "appeared_added": 0, "add_delay_steps": [], "add_delay_after_first_sighting": [],
           "appeared_missing": []}
    for tid, (first, end) in sorted(log.truth_lifetimes.items()):
        fids = {fid for _, fid in seen_as.get(tid, [])}
        fid = seen_as[tid][-1][1] if tid in seen_as else None  # the feature it was last seen as
        # removals that left it without a feature: of the feature it was seen as, with no other
        # feature it had been seen as still alive (removing a duplicate is no loss)
        gone = sorted(k for f in fids for k in removed.get(f, [])
                      if not any(g != f and alive(g, k) for g in fids if seen_by(tid, g, k)))
        out["duplicates_removed"] += sum(1 for f in fids for k in removed.get(f, [])) - len(gone)
        if end < t_end_log:  # left the world during the log
            out["vanished"] += 1
            early = [k for k in gone if times[k] < end]
            late = [k for k in removed.get(fid, []) if times[k] >= end]
            if early:
                out["static_removed"].append(tid)
            if late:
                k = late[0]
                first_absent = int(np.searchsorted(times, end))
                out["vanished_removed"] += 1
                out["removal_delay_steps"].append(k - first_absent + 1)
                out["removal_misses"].append(sum(fid in (run.unobserved_at or [])[j] for j in range(first_absent, k + 1)))
                if travelled is not None:
                    out["removal_delay_m"].append(travelled(times[first_absent - 1] if first_absent else times[0],
                                                            times[k]))
            else:
                out["vanished_kept"].append(tid)
        elif first <= times[0]:  # there from start to end
            out["static"] += 1
            if gone:
                out["static_removed"].append(tid)
        if first > times[0]:
            out["appeared"] += 1
            k_first_seen = seen_as[tid][0][0] if tid in seen_as else None
            fid = seen_as[tid][0][1] if tid in seen_as else None  # the feature its first sighting was
            if fid is not None and fid in added and times[added[fid]] >= first:
                out["appeared_added"] += 1
                out["add_delay_steps"].append(int(added[fid] - np.searchsorted(times, first)))
                out["add_delay_after_first_sighting"].append(int(added[fid] - k_first_seen))
            else:
                out["appeared_missing"].append(tid)
    return out


def turnover_summary(t: dict) -> dict:
    """The figures of :func:`landmark_turnover` for ``summary.json``: counts, and median / max of the delays."""

    def med_max(v: list) -> dict | None:
        return {"median": float(np.median(v)), "max": float(max(v))} if v else None

    return {"vanished": t["vanished"], "vanished_removed": t["vanished_removed"],
            "removal_delay_steps": med_max(t["removal_delay_steps"]),
            "removal_delay_m": med_max(t["removal_delay_m"]), "removal_misses": med_max(t["removal_misses"]),
            "vanished_not_removed": t["vanished_kept"], "static": t["static"],
            "static_removed": t["static_removed"], "appeared": t["appeared"], "appeared_added": t["appeared_added"],
            "add_delay_steps": med_max(t["add_delay_steps"]),
            "add_delay_after_first_sighting": med_max(t["add_delay_after_first_sighting"]),
            "appeared_not_added": t["appeared_missing"], "spurious_left": t["spurious_left"],
            "duplicates_removed": t["duplicates_removed"]}
