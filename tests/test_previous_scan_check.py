"""Planar odometry checked against the previous scan (registration/previous_scan.py): a scan that
fits the last scans poorly is matched to the scan before it, and that pose is kept when it puts
clearly more of the scan on the previous scan's points (the wheels missed part of a turn)."""

import functools
import itertools

import numpy as np
import pytest

from submapslam.config import OdometryConfig
from submapslam.evaluation.metrics import associate
from submapslam.geometry import inverse, matrix_to_se2, se2_to_matrix
from submapslam.io.registry import open_log
from submapslam.io.trajectory import Trajectory, carmen_reference_trajectory
from submapslam.odometry import Odometry
from submapslam.registration.previous_scan import PreviousScan
from submapslam.scan import Scan

from .conftest import shared_data
from .planar_scenes import wall_points
from .test_odometry_wheels import ROOM, _yaw_error_deg


def test_the_previous_scan_finds_a_turn_the_prediction_missed():
    """Two scans of a room 15 deg and 0.2 m apart; the prediction says no turn. The correlative
    match finds the turn, and its pose is preferred over the prediction's but not over itself."""
    first, second = np.array([0.0, -1.5, 0.3]), np.array([0.2, -1.45, 0.3 + np.deg2rad(15.0)])
    previous = PreviousScan(wall_points(ROOM, first, max_range=12.0), first)
    scan = wall_points(ROOM, second, max_range=12.0)
    predicted = first + [0.2, 0.05, 0.0]  # the wheels: the step without the turn
    candidate = previous.candidate(scan, inverse(se2_to_matrix(*first)) @ se2_to_matrix(*predicted))
    assert candidate is not None
    assert _yaw_error_deg(candidate, second) < 1.0 and np.linalg.norm(candidate[:2] - second[:2]) < 0.05
    assert previous.share(scan, candidate) > 0.8 > 0.3 > previous.share(scan, predicted)
    assert previous.prefers(scan, candidate, predicted)
    assert not previous.prefers(scan, candidate, second)  # no clear gain over a pose as good


def test_a_match_that_fits_nothing_proposes_nothing():
    previous = PreviousScan(wall_points(ROOM, np.array([0.0, -1.5, 0.0]), max_range=12.0), np.zeros(3))
    clutter = np.random.default_rng(3).uniform(-6.0, 6.0, (300, 2))  # no wall, nothing of the room
    assert previous.candidate(clutter, np.eye(4)) is None


def test_the_search_leaves_out_points_beyond_its_reach():
    """Returns beyond SEARCH_REACH_M (a far facade) stay out of the grids; scans with nothing
    nearer propose nothing."""
    first, second = np.array([0.0, -1.5, 0.3]), np.array([0.2, -1.45, 0.3 + np.deg2rad(15.0)])
    far = np.c_[np.linspace(-40.0, 40.0, 200), np.full(200, 70.0)]  # 70 m away, in each scan's frame
    previous = PreviousScan(np.r_[wall_points(ROOM, first, max_range=12.0), far], first)
    candidate = previous.candidate(np.r_[wall_points(ROOM, second, max_range=12.0), far], np.eye(4))
    assert candidate is not None and _yaw_error_deg(candidate, second) < 1.0
    assert PreviousScan(far, first).candidate(far, np.eye(4)) is None


@functools.cache
def _missed_turn_scans() -> tuple[list[np.ndarray], list[np.ndarray]]:
    """30 scans, 5 cm and 0.3 deg apart; at scan 20 the robot turns 15 deg more, which the wheels
    miss: the true ``(x, y, yaw)`` and the scans' points ``(N, 3)`` (ray-cast once for every test)."""
    truth = [np.array([-2.0 + 0.05 * k, -1.5, np.deg2rad(0.3) * k + (np.deg2rad(15.0) if k >= 20 else 0.0)])
             for k in range(30)]
    points = [np.c_[pts, np.zeros(len(pts))] for pts in (wall_points(ROOM, xyt, max_range=12.0) for xyt in truth)]
    return truth, points


def _drive_with_a_missed_turn(config: OdometryConfig, monkeypatch) -> tuple[np.ndarray, np.ndarray, Odometry]:
    """The drive of :func:`_missed_turn_scans`, where registration stays at the wheels' guess at the
    missed turn (as FR079's scan 273 did at a third of its rate). Returns the true and estimated
    ``(x, y, yaw)`` of the last scan and the odometry."""
    odo = Odometry(config, planar=True)
    truth, points = _missed_turn_scans()
    align = odo._align
    for k, (xyt, pts) in enumerate(zip(truth, points)):
        wheel = xyt - [0.0, 0.0, np.deg2rad(15.0) if k >= 20 else 0.0]
        if k == 20:
            monkeypatch.setattr(odo, "_align", lambda source, guess: guess)
        odo.register(Scan(k, 0.1 * k, pts, odometry=se2_to_matrix(*wheel), planar=True))
        monkeypatch.setattr(odo, "_align", align)
    return truth[-1] - truth[0], matrix_to_se2(odo.last_pose), odo


def test_a_turn_the_wheels_missed_is_taken_from_the_previous_scan(monkeypatch):
    truth, est, odo = _drive_with_a_missed_turn(OdometryConfig(), monkeypatch)
    assert odo.previous_scan_preferred == 1 and odo.checks()["previous_scan_preferred"] == 1
    assert _yaw_error_deg(truth, est) < 0.5 and np.linalg.norm(truth[:2] - est[:2]) < 0.05


def test_without_the_check_the_missed_turn_stays(monkeypatch):
    truth, est, odo = _drive_with_a_missed_turn(OdometryConfig(planar_previous_scan_check=False), monkeypatch)
    assert odo.previous_scan_checked == 0
    assert _yaw_error_deg(truth, est) > 5.0  # the later scans win back only half of the 15 deg


@functools.cache
def _fr079_third_rate_scans(n: int) -> list[Scan]:
    """The first ``n`` scans of FR079 at a third of its rate (every third laser scan, the wheels'
    poses with them: 0.64 s between scans instead of 0.21), read once for every test."""
    return list(itertools.islice(open_log(shared_data("carmen", "fr079.clf.bz2")), 0, 3 * n, 3))


def _fr079_third_rate(config: OdometryConfig, n: int) -> tuple[Trajectory, Odometry]:
    """The planar odometry alone over :func:`_fr079_third_rate_scans`."""
    scans = _fr079_third_rate_scans(n)
    odo = Odometry(config, planar=True)
    stamps, poses = [], []
    for scan in scans:
        poses.append(odo.register(scan)[0])
        stamps.append(scan.timestamp)
    return Trajectory(np.array(stamps), np.array(poses)), odo


@pytest.mark.parametrize("check", [True, False], ids=["checked", "unchecked"])
def test_fr079_at_a_third_of_its_rate_keeps_its_turns(check):
    """Real data: at scan 273 of the cut the wheels turned -3 deg where the scans (and the
    corrected log) turned +15; without the check the odometry keeps the wheels' turn and every
    pose after it is 15 deg off. Measured as the worst turn error between consecutive reference
    poses over the first 300 scans."""
    est, odo = _fr079_third_rate(OdometryConfig(planar_previous_scan_check=check), 300)
    ref = carmen_reference_trajectory(shared_data("carmen", "corrected", "freiburg-079-corrected.log.gz"),
                                      shared_data("carmen", "fr079.clf.bz2"))
    i_e, i_r = associate(est, ref, 0.02)
    errors = [_yaw_error_deg(matrix_to_se2(inverse(est.poses[a]) @ est.poses[b]),
                             matrix_to_se2(inverse(ref.poses[c]) @ ref.poses[d]))
              for a, b, c, d in zip(i_e[:-1], i_e[1:], i_r[:-1], i_r[1:])]
    assert len(errors) > 250
    if check:
        assert odo.previous_scan_preferred >= 1 and max(errors) < 5.0
    else:
        assert max(errors) > 10.0
