"""What a log's own scans say of a trajectory: loop-pair misfit and scan-matched relations.

Two scans taken at the same place on two passes see the same walls. Under a good trajectory
their points fall on each other; under a bent or shifted one they part by the error. The
*loop-pair misfit* of a scan pair is the median distance from each point of the first scan,
placed by the trajectory, to the nearest point of the second: a few centimetres where the map
is consistent (range noise and the two viewpoints' sampling set that floor), tens of
centimetres where a loop was missed or closed wrong.

It scores any trajectory of the log against the log's own data, so a run and a reference (a
corrected log) can be compared on the *same* pairs: where the reference is no more consistent
than the run, the ATE against it measures the two maps' disagreement, not the run's error.

*Scan-matched relations* go one step further, as the benchmark's own relation files were made
(Kümmerle et al. 2009): the relative pose of each pair of a reference's relations is measured by
matching the two scans, kept only where scan matching fixes it, and any trajectory (the reference
included) is then scored on them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping

import numpy as np
from numpy.typing import NDArray

from ..errors import SubmapSlamError
from ..trajectory import Relations, Trajectory, nearest_stamps
from .metrics import worst_pose_times

#: the scans a log took at (at least) the given times: ``timestamps (K,) [s] -> {timestamp: (N, 2 or 3) points}``
#: in the trajectories' body frame (e.g. ``functools.partial(submapslam.io.scan_lookup.scans_at, log)``, or a
#: dict read once at every reference time: both measures ask only for reference times)
ScanSource = Callable[[NDArray[np.float64]], Mapping[float, NDArray[np.float64]]]

#: the share of an estimate's matched poses with the largest ATE whose loop pairs :func:`loop_pair_check`
#: also compares apart: where the estimate parts most from the reference
WORST_SHARE = 0.1

#: starts of a relation's scan matching, as offsets ``(dx [m], dy [m], dyaw [deg])`` from the
#: reference's relative pose: wider than any reference's local error (a few cm, under a degree)
MATCH_STARTS_OFFSETS = ((0.0, 0.0, 0.0), (0.1, 0.0, 2.0), (-0.1, 0.0, -2.0), (0.0, 0.1, -2.0), (0.0, -0.1, 2.0))


def loop_pairs(trajectory: Trajectory, *, radius_m: float = 2.0, max_turn_deg: float = 60.0,
               min_dt: float = 30.0) -> NDArray[np.float64]:
    """Pairs of poses of ``trajectory`` near each other on different passes: ``(K, 2)`` timestamps [s].

    A pair is two poses at most ``radius_m`` [m] apart with headings (yaw) within ``max_turn_deg``
    [deg], the second at least ``min_dt`` [s] after the first. Every such pair is kept, earlier
    time first, sorted by the first timestamp.
    """
    order = np.argsort(trajectory.timestamps, kind="stable")
    t, P = trajectory.timestamps[order], trajectory.poses[order]
    xy = P[:, :2, 3]
    yaw = np.arctan2(P[:, 1, 0], P[:, 0, 0])
    max_turn = np.deg2rad(max_turn_deg)
    pairs: list[tuple[float, float]] = []
    for a in range(len(t)):
        later = np.flatnonzero(t - t[a] >= min_dt)
        if later.size == 0:
            break
        near = later[np.linalg.norm(xy[later] - xy[a], axis=1) <= radius_m]
        turn = np.abs((yaw[near] - yaw[a] + np.pi) % (2 * np.pi) - np.pi)
        pairs.extend((float(t[a]), float(t[b])) for b in near[turn <= max_turn])
    return np.array(pairs, dtype=np.float64).reshape(-1, 2)


def pair_misfit(trajectory: Trajectory, scans: Mapping[float, NDArray[np.float64]], pairs: NDArray[np.float64],
                *, max_time_diff: float = 1e-3) -> NDArray[np.float64]:
    """Each pair's misfit [m] under ``trajectory``: ``(K,)``, NaN where a pose or scan is missing.

    ``scans`` maps a timestamp [s] to that scan's ``(N, 2 or 3)`` points in the trajectory's body
    frame; ``pairs`` is ``(K, 2)`` timestamps (e.g. from :func:`loop_pairs` on a reference). A pose
    is the trajectory's pose within ``max_time_diff`` [s] of the scan's time. The misfit is the
    median distance in x-y from the first scan's points to the nearest of the second's, both placed
    by the trajectory.
    """
    from ..registration.kdtree2d import KdTree2D

    pairs = np.asarray(pairs, dtype=np.float64).reshape(-1, 2)
    stamps = np.array(list(scans), dtype=np.float64)
    pose_of = nearest_stamps(trajectory.timestamps, pairs, max_time_diff).reshape(-1, 2)
    scan_of = nearest_stamps(stamps, pairs, max_time_diff).reshape(-1, 2)
    out = np.full(len(pairs), np.nan)
    for k in np.flatnonzero(((pose_of >= 0) & (scan_of >= 0)).all(axis=1)):
        placed = []
        for pose, stamp in zip(pose_of[k], scan_of[k]):
            pts = np.asarray(scans[float(stamps[stamp])], dtype=np.float64)[:, :2]
            T = trajectory.poses[pose]
            placed.append(pts @ T[:2, :2].T + T[:2, 3])
        if len(placed[0]) and len(placed[1]):
            dist, _ = KdTree2D(placed[1]).query(placed[0])
            out[k] = float(np.median(dist))
    return out


def loop_pair_comparison(estimate: Trajectory, reference: Trajectory, scans_at: ScanSource, *,
                         margin_m: float = 0.03, overlap_m: float = 0.1,
                         worst_at: NDArray[np.float64] | None = None) -> dict:
    """``estimate`` and ``reference`` scored on the same loop pairs (:func:`loop_pairs` of the reference)
    with the log's scans (``scans_at``: :data:`ScanSource`).

    Two scans of one place can still see different walls (a corner from both sides); their misfit
    is large under any trajectory and says nothing. Pairs are *compared* only where at least one
    trajectory makes them agree within ``overlap_m`` [m]. Returns ``{"pairs", "compared",
    "estimate_median_m", "reference_median_m", "estimate_worse", "reference_worse", "margin_m",
    "overlap_m"}``: the pairs both trajectories place, how many are compared, each trajectory's
    median misfit over the compared pairs [m], and how many compared pairs each places more than
    ``margin_m`` [m] worse than the other. Raises :class:`SubmapSlamError` when the reference has
    no loop pairs or no pair can be compared.

    ``worst_at``: timestamps [s] of the reference poses the estimate is farthest from (e.g. its
    largest ATE errors). Then ``"at_worst"`` holds the same figures (``compared``, both medians,
    both counts) over the compared pairs with an end at one of those times, or None when no
    compared pair touches them: where the two trajectories part most, which one do the scans
    side with?
    """
    pairs = loop_pairs(reference)
    if not len(pairs):
        raise SubmapSlamError("the reference never comes back near a place it passed 30 s before: no loop pairs")
    scans = scans_at(pairs.ravel())
    est, ref = pair_misfit(estimate, scans, pairs), pair_misfit(reference, scans, pairs)
    placed = np.isfinite(est) & np.isfinite(ref)
    compared = placed & (np.fmin(est, ref) <= overlap_m)
    if not compared.any():
        raise SubmapSlamError(f"none of the {len(pairs)} loop pairs is placed by both trajectories with its scans "
                              f"within {overlap_m} m under either")
    out = {"pairs": int(placed.sum()), **_misfit_figures(est[compared], ref[compared], margin_m),
           "margin_m": margin_m, "overlap_m": overlap_m}
    if worst_at is not None:
        touches = (nearest_stamps(np.asarray(worst_at, dtype=np.float64), pairs, 1e-6) >= 0).reshape(-1, 2).any(axis=1)
        near = compared & touches
        out["at_worst"] = _misfit_figures(est[near], ref[near], margin_m) if near.any() else None
    return out


def loop_pair_check(estimate: Trajectory, reference: Trajectory, scans_at: ScanSource, ate_figures: dict) -> dict:
    """:func:`loop_pair_comparison` with ``at_worst`` at the estimate's ``WORST_SHARE`` largest
    errors in ``ate_figures`` (:func:`~.metrics.ate` of ``estimate`` against ``reference``), and
    that share as ``"worst_share"``."""
    worst = worst_pose_times(ate_figures, WORST_SHARE)
    return {**loop_pair_comparison(estimate, reference, scans_at, worst_at=worst), "worst_share": WORST_SHARE}


def _misfit_figures(est: NDArray[np.float64], ref: NDArray[np.float64], margin_m: float) -> dict:
    """Both trajectories' misfits ``(K,)`` [m] on the same pairs: how many, each median, and how
    many pairs each places more than ``margin_m`` worse than the other."""
    return {"compared": len(est), "estimate_median_m": float(np.median(est)), "reference_median_m": float(np.median(ref)),
            "estimate_worse": int(np.count_nonzero(est > ref + margin_m)),
            "reference_worse": int(np.count_nonzero(ref > est + margin_m))}


def scan_matched_relations(reference: Trajectory, relations: Relations, scans_at: ScanSource, *,
                           agree_m: float = 0.002, agree_deg: float = 0.05, min_fitness: float = 0.6
                           ) -> tuple[Relations, dict]:
    """The relations measured by matching their two scans, as the benchmark's own relation files were
    made (Kümmerle et al. 2009: scan matching, then checked): ``(relations kept, counts)``.

    ``relations`` gives the pairs (e.g. :func:`~submapslam.evaluation.derived_relations.derive_relations`
    of ``reference``), ``reference`` the starts and ``scans_at`` the log's scans (:data:`ScanSource`).
    The later scan is registered to the earlier one
    (point-to-point ICP, then point-to-line) from the reference's relative pose and from starts
    10 cm / 2 deg off it (:data:`MATCH_STARTS_OFFSETS`). A relation is kept, at the matched pose,
    only where every start ends within ``agree_m`` [m] and ``agree_deg`` [deg] of the others (one
    basin: the scene fixes all three directions) and at least ``min_fitness`` of the later scan's
    points lie within 5 cm of the earlier scan's lines. The result depends on the log and the
    reference only, never on a trajectory being scored, so every trajectory is scored on the same
    relations; ``counts`` says how many were matched and why the others were dropped.
    """
    from scipy.spatial import cKDTree

    from ..geometry import inverse, matrix_to_se2, se2_to_matrix
    from ..registration.planar import icp_2d
    from ..registration.point_to_line import line_normals, point_to_line

    scans = scans_at(np.concatenate([relations.t_a, relations.t_b]))
    stamps = np.array(list(scans), dtype=np.float64)
    stamp_pairs = np.stack([relations.t_a, relations.t_b], axis=1)
    pose_of = nearest_stamps(reference.timestamps, stamp_pairs, 1e-3).reshape(-1, 2)
    scan_of = nearest_stamps(stamps, stamp_pairs, 1e-3).reshape(-1, 2)
    kept: list[tuple[float, float, np.ndarray]] = []
    counts = {"relations": len(relations), "matched": 0, "no_scan": 0, "ambiguous": 0, "poor_fit": 0}
    for (ta, tb), (ia, ib), (sa, sb) in zip(stamp_pairs.tolist(), pose_of.tolist(), scan_of.tolist()):
        if min(ia, ib, sa, sb) < 0:
            counts["no_scan"] += 1
            continue
        target = np.ascontiguousarray(np.asarray(scans[float(stamps[sa])])[:, :2], dtype=np.float64)
        source = np.ascontiguousarray(np.asarray(scans[float(stamps[sb])])[:, :2], dtype=np.float64)
        if len(target) < 20 or len(source) < 20:
            counts["no_scan"] += 1
            continue
        tree = cKDTree(target)
        normals = line_normals(target, tree)
        lined = np.isfinite(normals[:, 0])
        lines, line_normal = target[lined], normals[lined]
        if len(lines) < 10:
            counts["poor_fit"] += 1
            continue
        line_tree = cKDTree(lines)
        start = matrix_to_se2(inverse(reference.poses[ia]) @ reference.poses[ib])
        ends: list[np.ndarray] = []
        for dx, dy, dyaw in MATCH_STARTS_OFFSETS:
            guess = start + (dx, dy, np.deg2rad(dyaw))
            xyt, _, _ = icp_2d(source, target, guess, max_distance=0.5, min_distance=0.1, tree=tree)
            xyt, _ = point_to_line(source, xyt, line_tree, lines, line_normal, max_correspondence=0.1,
                                   kernel=0.02, iterations=20)
            if ends and (math.hypot(xyt[0] - ends[0][0], xyt[1] - ends[0][1]) > agree_m
                         or abs(math.remainder(xyt[2] - ends[0][2], 2 * math.pi)) > np.deg2rad(agree_deg)):
                break  # a second basin: the scene leaves a direction open
            ends.append(xyt)
        if len(ends) < len(MATCH_STARTS_OFFSETS):
            counts["ambiguous"] += 1
            continue
        T = se2_to_matrix(*ends[0])
        placed = source @ T[:2, :2].T + T[:2, 3]
        dist, idx = line_tree.query(placed, distance_upper_bound=0.05)
        near = dist < np.inf
        along_normal = np.abs(np.einsum("ij,ij->i", placed[near] - lines[idx[near]], line_normal[idx[near]]))
        if np.count_nonzero(along_normal <= 0.05) < min_fitness * len(source):
            counts["poor_fit"] += 1
            continue
        kept.append((ta, tb, T))
        counts["matched"] += 1
    if not kept:
        raise SubmapSlamError(f"none of the {len(relations)} relations could be measured by matching their scans "
                              f"({counts})")
    return (Relations(np.array([k[0] for k in kept]), np.array([k[1] for k in kept]),
                      np.array([k[2] for k in kept])), counts)
