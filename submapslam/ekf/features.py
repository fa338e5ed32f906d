"""Point features for the stochastic map, extracted from range scans: poles.

A pole is a small, compact cluster of returns standing apart from its neighbours: in a planar
scan a short run of consecutive beams bounded by range jumps; in a 3D scan a small cluster of
the points in a height band above the ground. Each becomes a range-bearing observation of the
pole's centre (the cluster centre pushed back by the pole radius) in the sensor frame.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from ..geometry import inverse, matrix_to_se2
from ..landmark_log import LandmarkLog, Step
from ..trajectory import Trajectory

PLANAR_POLE_RANGE = 15.0  # [m] how far the pole detectors look (and the EKF expects to see poles)
SPATIAL_POLE_RANGE = 30.0


def poles_from_planar_scan(points: np.ndarray, *, max_width: float = 0.22, min_points: int = 3,
                           jump: float = 0.3, max_range: float = PLANAR_POLE_RANGE, radius: float = 0.1) -> np.ndarray:
    """``(N, 3)`` planar points in beam order -> ``(K, 2)`` range-bearing of pole centres.

    Consecutive points closer than ``jump`` form a segment; a segment narrower than
    ``max_width`` whose both neighbours lie behind it (a foreground object) is a pole.
    """
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    if len(xy) < min_points:
        return np.zeros((0, 2))
    r = np.hypot(xy[:, 0], xy[:, 1])
    gaps = np.linalg.norm(np.diff(xy, axis=0), axis=1) > jump
    starts = np.r_[0, np.nonzero(gaps)[0] + 1]
    ends = np.r_[starts[1:], len(xy)]
    out = []
    for a, b in zip(starts, ends):
        seg = xy[a:b]
        if len(seg) < min_points or np.linalg.norm(seg[-1] - seg[0]) > max_width:
            continue
        rng_seg = r[a:b].mean()
        if rng_seg > max_range:
            continue
        before = r[a - 1] if a > 0 else np.inf
        after = r[b] if b < len(r) else np.inf
        if before < rng_seg + jump or after < rng_seg + jump:  # must stand in front of both neighbours
            continue
        c = seg.mean(axis=0)
        c = c * (1 + radius / max(np.linalg.norm(c), 1e-6))
        out.append((np.hypot(*c), np.arctan2(c[1], c[0])))
    return np.array(out).reshape(-1, 2)


def poles_from_3d_scan(points: np.ndarray, *, z_band: tuple[float, float] = (-1.0, 0.5), cell: float = 0.25,
                       max_width: float = 0.6, min_points: int = 5, max_range: float = SPATIAL_POLE_RANGE) -> np.ndarray:
    """``(N, 3)`` points (sensor frame, z up) -> ``(K, 2)`` range-bearing of pole-like clusters.

    Points in the height band are binned on a 2D grid; connected occupied cells form clusters
    (scipy.ndimage.label); clusters no wider than ``max_width`` are poles.
    """
    from scipy import ndimage

    p = np.asarray(points, dtype=np.float64)
    p = p[(p[:, 2] > z_band[0]) & (p[:, 2] < z_band[1]) & (np.hypot(p[:, 0], p[:, 1]) < max_range)]
    if len(p) < min_points:
        return np.zeros((0, 2))
    ij = np.floor(p[:, :2] / cell).astype(int)
    lo = ij.min(axis=0)
    ij -= lo
    grid = np.zeros(ij.max(axis=0) + 1, dtype=np.int32)
    np.add.at(grid, (ij[:, 0], ij[:, 1]), 1)
    labels, n = ndimage.label(grid > 0, structure=np.ones((3, 3)))
    lab = labels[ij[:, 0], ij[:, 1]]
    out = []
    for k in range(1, n + 1):
        cl = p[lab == k, :2]
        if len(cl) < min_points:
            continue
        if np.ptp(cl[:, 0]) > max_width or np.ptp(cl[:, 1]) > max_width:
            continue
        c = cl.mean(axis=0)
        out.append((np.hypot(*c), np.arctan2(c[1], c[0])))
    return np.array(out).reshape(-1, 2)


def landmark_log_from_scans(scans: Iterable, name: str, *, fov_deg: float = 360.0, truth: Trajectory | None = None,
                            truth_landmarks: dict[int, np.ndarray] | None = None, sigma_range: float = 0.05,
                            sigma_bearing: float = 0.02,
                            odometry_sigma: tuple[float, float, float] = (0.05, 0.02, 0.03)) -> LandmarkLog:
    """Scans with wheel odometry -> a :class:`LandmarkLog` of pole observations (no file access).

    Each scan needs ``timestamp``, ``points (N, 3)``, ``planar`` and ``odometry`` (``(4, 4)``
    ``T_odom_base``): motion comes from the wheel odometry (the same input the submap pipeline
    gets), its covariance grows with the distance; association is unknown (ids None), so the
    filter's gating does it. ``fov_deg`` is a planar laser's field of view; ``truth`` (poses in
    the world frame) sets the initial pose and the ground-truth path, ``truth_landmarks`` the
    true poles (world frame).
    """
    steps = []
    prev = None
    planar = True
    for scan in scans:
        planar = scan.planar
        if prev is None:
            motion = np.zeros(3)
        else:
            motion = matrix_to_se2(inverse(prev) @ scan.odometry)
        prev = scan.odometry
        d = float(np.hypot(motion[0], motion[1])) + 1e-3
        # random-walk drift: variances grow with the distance (sigma per square-root metre)
        cov = np.diag([odometry_sigma[0] ** 2 * d + 1e-8, odometry_sigma[1] ** 2 * d + 1e-8,
                       odometry_sigma[2] ** 2 * d + (0.02 * motion[2]) ** 2 + 1e-8])
        obs = poles_from_planar_scan(scan.points) if scan.planar else poles_from_3d_scan(scan.points)
        steps.append(Step(scan.timestamp, motion, cov, obs, [None] * len(obs)))
    init = np.zeros(3)
    truth_times = truth_poses = None
    if truth is not None:
        init = matrix_to_se2(truth.poses[0])
        truth_times, truth_poses = truth.timestamps, matrix_to_se2(truth.poses)
    return LandmarkLog(name, init, steps, np.diag([sigma_range**2, sigma_bearing**2]),
                       truth_times, truth_poses, dict(truth_landmarks or {}),
                       known_association=False, max_range=PLANAR_POLE_RANGE if planar else SPATIAL_POLE_RANGE,
                       fov=np.deg2rad(float(fov_deg)) if planar else 2 * np.pi)
