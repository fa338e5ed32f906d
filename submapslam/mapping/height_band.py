"""Obstacle points of a 3D scan for a 2D occupancy grid: the slice between two heights above
the ground, thinned to one point per grid cell.

A 3D LiDAR sees the ground all around; what blocks a robot is what stands on it. The ground
height under the sensor is either given (``ground_z``, sensor frame) or estimated per scan as
a low percentile of the heights of the points within ``ground_radius`` metres — robust to a
few points below the ground (reflections) and to slopes near the robot. Points between
``min_above_ground`` and ``max_above_ground`` above it become the scan's obstacle points; the
occupancy grid then traces rays to them in the plane, as for a 2D laser.
"""

from __future__ import annotations

import numpy as np

from ..registration.point_to_line import first_point_per_cell

GROUND_PERCENTILE = 2.0  # [%] of the nearby heights taken as the ground


def estimate_ground_z(points: np.ndarray, radius: float = 15.0) -> float | None:
    """Ground height [m] in the sensor frame from ``(N, 3)`` points, or None when no point lies
    within ``radius`` metres horizontally."""
    near = points[np.hypot(points[:, 0], points[:, 1]) <= radius, 2]
    if len(near) == 0:
        return None
    return float(np.percentile(near, GROUND_PERCENTILE))


def obstacle_points(points: np.ndarray, cell: float, min_above_ground: float = 0.3,
                    max_above_ground: float = 2.0, ground_z: float | None = None,
                    ground_radius: float = 15.0) -> np.ndarray:
    """The ``(K, 3)`` float32 points of ``(N, 3)`` sensor-frame ``points`` whose height above the
    ground lies in ``[min_above_ground, max_above_ground]``, one per ``cell`` x ``cell`` square.

    ``ground_z`` is the ground height in the sensor frame (e.g. ``-1.7`` for a sensor 1.7 m up);
    None estimates it from the scan. A scan with no ground near the sensor gives no points.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    ground = estimate_ground_z(points, ground_radius) if ground_z is None else ground_z
    if ground is None or len(points) == 0:
        return np.zeros((0, 3), dtype=np.float32)
    height = points[:, 2] - ground
    band = points[(height >= min_above_ground) & (height <= max_above_ground)]
    if len(band) == 0:
        return np.zeros((0, 3), dtype=np.float32)
    return band[first_point_per_cell(band[:, :2], cell)].astype(np.float32)


def ground_normal(points: np.ndarray, radius: float = 15.0, band: float = 0.5,
                  min_points: int = 50) -> np.ndarray | None:
    """Unit ``(3,)`` normal (pointing up) of the ground around the origin of ``(N, 3)`` points.

    The ground is taken as the points within ``radius`` m horizontally whose height is within
    ``band`` m of a low percentile of the heights there; a plane is fitted to them (PCA). None
    when too few points qualify or they do not lie on a plane (standard deviation across it
    above 0.1 m), e.g. for a sensor that sees no ground near itself.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    near = points[np.hypot(points[:, 0], points[:, 1]) <= radius]
    if len(near) < min_points:
        return None
    low = near[near[:, 2] <= np.percentile(near[:, 2], GROUND_PERCENTILE) + band]
    if len(low) < min_points:
        return None
    centred = low - low.mean(axis=0)
    w, V = np.linalg.eigh(centred.T @ centred / len(low))
    if np.sqrt(max(w[0], 0.0)) > 0.1 or w[1] < 1.0:  # not thin, or not spread in two directions
        return None
    normal = V[:, 0]
    return normal if normal[2] > 0 else -normal
