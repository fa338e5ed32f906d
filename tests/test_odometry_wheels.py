"""Planar odometry when the wheel odometry is stale: the log's pose stands still for a few scans,
then jumps by all the rotation it missed (MIT CSAIL's FLASER poses)."""

import functools

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


@functools.cache
def _spin_scans() -> tuple[list[np.ndarray], list[np.ndarray]]:
    """A robot turning 12 deg a scan on the spot for 40 scans: the true ``(x, y, yaw)`` and the
    scans' points ``(N, 3)`` (ray-cast once for every test)."""
    truth = [np.array([0.0, -1.5, 0.0]) + [0.01 * k, 0.0, np.deg2rad(12.0) * k] for k in range(40)]
    points = [np.c_[pts, np.zeros(len(pts))] for pts in (wall_points(ROOM, xyt, max_range=12.0) for xyt in truth)]
    return truth, points


def _spin(config: OdometryConfig) -> tuple[np.ndarray, np.ndarray]:
    """The spin of :func:`_spin_scans`; the wheel pose is updated every 4th scan only. Returns the
    true and estimated ``(x, y, yaw)`` of the last scan relative to the first."""
    odo = Odometry(config, planar=True)
    truth, points = _spin_scans()
    wheel = truth[0]
    for k, (xyt, pts) in enumerate(zip(truth, points)):
        if k % 4 == 0:
            wheel = xyt  # stale in between, then the whole missed turn at once
        odo.register(Scan(k, 0.1 * k, pts, odometry=se2_to_matrix(*wheel), planar=True))
    return truth[-1] - truth[0], matrix_to_se2(odo.last_pose)


def _yaw_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    return abs(np.rad2deg(np.remainder(a[2] - b[2] + np.pi, 2 * np.pi) - np.pi))


def test_stale_wheel_odometry_is_overruled_by_the_better_fitting_guess():
    truth, est = _spin(OdometryConfig())
    assert _yaw_error_deg(truth, est) < 0.5 and np.linalg.norm(truth[:2] - est[:2]) < 0.05


def test_trusting_the_stale_wheels_loses_the_heading():
    """The same spin with the checks off (the behaviour before): ICP follows the wheels' jumps."""
    truth, est = _spin(OdometryConfig(wheel_check_deg=179.0, wheel_check_m=100.0, planar_previous_scan_check=False))
    assert _yaw_error_deg(truth, est) > 5.0


def test_the_previous_scan_alone_also_keeps_the_heading():
    """Without the wheel check, the scans after each stale stretch fit the last scans poorly, and
    their match to the previous scan (tests/test_previous_scan_check.py) wins the turn back."""
    truth, est = _spin(OdometryConfig(wheel_check_deg=179.0, wheel_check_m=100.0))
    assert _yaw_error_deg(truth, est) < 0.5 and np.linalg.norm(truth[:2] - est[:2]) < 0.05


def _drive(odo: Odometry, n: int = 30, astray_at: int | None = None, turn_deg: float = 60.0) -> tuple[np.ndarray, np.ndarray]:
    """A robot driving 5 cm a scan with true wheel odometry; at scan ``astray_at`` registration is
    made to end ``turn_deg`` off the wheels' guess (a wrong ICP minimum). Returns the true and
    estimated ``(x, y, yaw)`` of the last scan."""
    align = odo._align
    truth = [np.array([-2.0 + 0.05 * k, -1.5, np.deg2rad(0.3) * k]) for k in range(n)]
    for k, xyt in enumerate(truth):
        if k == astray_at:
            odo._align = lambda source, guess: guess @ se2_to_matrix(0.0, 0.0, np.deg2rad(turn_deg))
        pts = wall_points(ROOM, xyt, max_range=12.0)
        odo.register(Scan(k, 0.1 * k, np.c_[pts, np.zeros(len(pts))], odometry=se2_to_matrix(*xyt), planar=True))
        odo._align = align
    return truth[-1], matrix_to_se2(odo.last_pose) + truth[0]


def test_registration_far_from_agreeing_wheels_with_a_poor_fit_gives_way_to_them():
    """Wheels and motion model agree, registration ends 60 deg away (the point-to-line refinement
    cannot pull it back from there) and fits the last scans worse than usual (Intel's scan 11455
    on one CPU): the wheels' pose, refined, is kept. Without the check the scan keeps the 60 deg."""
    odo = Odometry(OdometryConfig(), planar=True)
    truth, est = _drive(odo, astray_at=20)
    checks = odo.checks()  # summary.json's odometry_checks
    assert checks["wheel_overruled"] == 0 and checks["registration_overruled"] == 1
    assert _yaw_error_deg(truth, est) < 0.5 and np.linalg.norm(truth[:2] - est[:2]) < 0.05


def test_a_turned_guess_that_fits_no_better_than_new_ground_does_not_win(monkeypatch):
    """Stale wheels and a poor fit start the search over turned guesses; a turned guess that fits
    better, but still worse than half the usual fit, is noise (a doorway's new ground): the scan
    keeps the better of the wheels' and the motion model's guesses. Registration and refinement
    are held to their guesses, and the fits are given, so only the choice is tested."""
    odo = Odometry(OdometryConfig(), planar=True)
    _drive(odo, n=20)
    before = matrix_to_se2(odo.last_pose)
    fits = []

    def fit(frame_down, xyt):  # wheels' guess 0.05, motion model's 0.1, every turned guess 0.3
        fits.append(xyt)
        return {1: 0.05, 2: 0.1}.get(len(fits), 0.3)

    monkeypatch.setattr(odo, "_fit", fit)
    monkeypatch.setattr(odo, "_align", lambda source, guess: guess)
    monkeypatch.setattr(odo, "_refine", lambda frame_down, pose, guess: matrix_to_se2(pose))
    odo._recent_fits.extend([0.9] * 10)  # usual fit 0.9: a turned guess would need 0.45
    last_truth = np.array([-2.0 + 0.05 * 19, -1.5, np.deg2rad(0.3) * 19])
    stale = se2_to_matrix(*last_truth) @ se2_to_matrix(0.0, 0.0, np.deg2rad(12.0))  # wheels: a 12 deg jump
    pts = wall_points(ROOM, last_truth + [0.05, 0.0, 0.0], max_range=12.0)
    odo.register(Scan(20, 2.0, np.c_[pts, np.zeros(len(pts))], odometry=stale, planar=True))
    assert len(fits) > 2 and odo.wheel_overruled == 1  # the turned guesses were tried
    assert _yaw_error_deg(matrix_to_se2(odo.last_pose), before) < 2.0  # the motion model's guess
