"""Planar odometry when the wheel odometry is stale: the log's pose stands still for a few scans,
then jumps by all the rotation it missed (MIT CSAIL's FLASER poses)."""

import numpy as np

from submapslam.config import OdometryConfig
from submapslam.geometry import matrix_to_se2, se2_to_matrix
from submapslam.odometry import Odometry
from submapslam.scan import Scan

from .planar_scenes import wall_points

# a room with a recess, a pillar and a side corridor: no rotational symmetry
ROOM = [(-4, -3, 6, -3), (6, -3, 6, 4), (6, 4, 1, 4), (1, 4, 1, 2.5), (1, 2.5, -1, 2.5), (-1, 2.5, -1, 4),
        (-1, 4, -4, 4), (-4, 4, -4, 1), (-4, 1, -7, 1), (-7, 1, -7, -1), (-7, -1, -4, -1), (-4, -1, -4, -3),
        (2, -0.5, 2.6, -0.5), (2.6, -0.5, 2.6, 0.2), (2.6, 0.2, 2, 0.2), (2, 0.2, 2, -0.5)]


def _spin(config: OdometryConfig) -> tuple[np.ndarray, np.ndarray]:
    """A robot turning 12 deg a scan on the spot for 40 scans; the wheel pose is updated every 4th
    scan only. Returns the true and estimated ``(x, y, yaw)`` of the last scan relative to the first."""
    odo = Odometry(config, planar=True)
    truth = [np.array([0.0, -1.5, 0.0]) + [0.01 * k, 0.0, np.deg2rad(12.0) * k] for k in range(40)]
    wheel = truth[0]
    for k, xyt in enumerate(truth):
        if k % 4 == 0:
            wheel = xyt  # stale in between, then the whole missed turn at once
        pts = wall_points(ROOM, xyt, max_range=12.0)
        odo.register(Scan(k, 0.1 * k, np.c_[pts, np.zeros(len(pts))], odometry=se2_to_matrix(*wheel), planar=True))
    return truth[-1] - truth[0], matrix_to_se2(odo.last_pose)


def _yaw_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    return abs(np.rad2deg(np.remainder(a[2] - b[2] + np.pi, 2 * np.pi) - np.pi))


def test_stale_wheel_odometry_is_overruled_by_the_better_fitting_guess():
    truth, est = _spin(OdometryConfig())
    assert _yaw_error_deg(truth, est) < 0.5 and np.linalg.norm(truth[:2] - est[:2]) < 0.05


def test_trusting_the_stale_wheels_loses_the_heading():
    """The same spin with the check off (the behaviour before): ICP follows the wheels' jumps."""
    truth, est = _spin(OdometryConfig(wheel_check_deg=179.0, wheel_check_m=100.0))
    assert _yaw_error_deg(truth, est) > 5.0
