"""Point features for the stochastic map, extracted from range scans: poles.

A pole is a small, compact cluster of returns standing apart from its neighbours: in a planar
scan a short run of consecutive beams bounded by range jumps; in a 3D scan a small cluster of
the points in a height band above the ground. Each becomes a range-bearing observation of the
pole's centre (the cluster centre pushed back by the pole radius) in the sensor frame.
"""

from __future__ import annotations

import numpy as np

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


def landmark_log_from_cloud_log(path, sigma_range: float = 0.05, sigma_bearing: float = 0.02,
                                odometry_sigma: tuple[float, float, float] = (0.05, 0.02, 0.03)):
    """A point-cloud log folder (scans + odometry_tum.txt) -> a LandmarkLog of pole observations.

    Motion comes from the log's wheel odometry (the same input the submap pipeline gets);
    association is unknown (ids None), so the filter's gating does it.
    """
    from pathlib import Path

    import yaml

    from ..errors import InputError
    from ..geometry import inverse, matrix_to_se2
    from ..io.landmark_logs import LandmarkLog, Step
    from ..io.registry import open_log
    from ..io.trajectory import read_tum

    reader = open_log(Path(path), "cloud_folder")
    meta_file = Path(path) / "meta.yaml"
    try:
        meta = yaml.safe_load(meta_file.read_text()) if meta_file.is_file() else {}
    except yaml.YAMLError as exc:
        raise InputError(meta_file, f"not valid YAML ({str(exc).splitlines()[0]})") from None
    sensor = (meta or {}).get("sensor", {}) if isinstance(meta, dict) else {}
    if reader.odometry is None:
        raise InputError(path, "the log has no odometry_tum.txt: the EKF needs odometry")
    gt_file = Path(path) / "groundtruth_tum.txt"
    truth = read_tum(gt_file) if gt_file.is_file() else None
    steps = []
    prev = None
    planar = True
    for scan in reader:
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
    return LandmarkLog(f"poles from {Path(path).name}", init, steps, np.diag([sigma_range**2, sigma_bearing**2]),
                       truth_times, truth_poses, _truth_poles(Path(path) / "landmarks_groundtruth.csv"),
                       known_association=False, max_range=PLANAR_POLE_RANGE if planar else SPATIAL_POLE_RANGE,
                       fov=np.deg2rad(float(sensor.get("fov_deg", 360.0))) if planar else 2 * np.pi)


def _truth_poles(path) -> dict[int, np.ndarray]:
    """``landmarks_groundtruth.csv`` (``id,x,y``, world frame) written by the synthetic generator, if any."""
    from ..errors import InputError

    if not path.is_file():
        return {}
    out = {}
    for lineno, line in enumerate(path.read_text().splitlines()[1:], start=2):
        try:
            k, x, y = line.split(",")[:3]
            out[int(k)] = np.array([float(x), float(y)])
        except ValueError:
            raise InputError(path, f"expected id,x,y, got {line[:40]!r}", lineno) from None
    return out
