"""Logs without wheel odometry whose scans do not come at a steady rate: keyframes 0.2-0.5 s apart,
and scans lost (dropped frames, a recorder's hiccup). The motion model predicted one interval's
motion whatever the time since the last scan, and registration started metres off. Now the last
motion is carried on at its pace over the interval (``odometry.gap_ratio``), and after a gap
guesses along it, bent into arcs where the heading may have changed, are registered too and the
best kept."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from datasets_synth import generate, generate_kitti_drive
from submapslam import open_log
from submapslam.config import OdometryConfig
from submapslam.io.trajectory import read_tum
from submapslam.odometry import Odometry, resolve_registration

from .conftest import shared_data


def _without(log, lost: range) -> tuple[list, list[int], np.ndarray]:
    """The log's scans without wheel odometry, the indices kept (``lost`` left out), and the
    ground-truth poses ``(N, 4, 4)`` of every scan."""
    scans = [dataclasses.replace(s, odometry=None) for s in open_log(log)]
    kept = [i for i in range(len(scans)) if i not in lost]
    return scans, kept, read_tum(log / "groundtruth_tum.txt").poses


def _errors(config: OdometryConfig, planar: bool, scans: list, kept: list[int], truth: np.ndarray,
            after: int) -> tuple[float, float, dict]:
    """``(error [m] of the step over the gap into scan ``after``, error of the last pose relative to
    the first, the odometry's checks)`` of the odometry alone over the ``kept`` scans."""
    odometry = Odometry(resolve_registration(config, scans[0]), planar=planar)
    poses = [odometry.register(scans[i])[0] for i in kept]
    k = kept.index(after)
    step = np.linalg.inv(poses[k - 1]) @ poses[k]
    true_step = np.linalg.inv(truth[kept[k - 1]]) @ truth[after]
    end = np.linalg.inv(poses[0]) @ poses[-1]
    true_end = np.linalg.inv(truth[kept[0]]) @ truth[kept[-1]]
    return (float(np.linalg.norm(step[:3, 3] - true_step[:3, 3])),
            float(np.linalg.norm(end[:3, 3] - true_end[:3, 3])), odometry.checks())


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """16 rings along the first 120 poses of KITTI 05 with terrain, 10 Hz."""
    return generate_kitti_drive(shared_data("trajectories", "kitti_gt", "05.txt.xz"),
                                tmp_path_factory.mktemp("drive") / "log", rings=16, seed=3, max_scans=120,
                                terrain=True)


def test_a_lidar_drive_keeps_its_way_over_two_seconds_of_lost_scans(drive):
    """Scans 60-79 lost (2 s, 21 m at this speed): the step over the gap within 0.3 m and the end
    within 1 m (0.10 and 0.39 m); with the one-interval guess alone the step is 21 m off."""
    scans, kept, truth = _without(drive, range(60, 80))
    step, end, checks = _errors(OdometryConfig(), False, scans, kept, truth, after=80)
    assert step <= 0.3 and end <= 1.0, (step, end, checks)
    assert checks["gap_guesses_tried"] == 2 and checks["gap_guess_won"] == 2  # the gap and the scan after it
    step, end, _ = _errors(OdometryConfig(gap_ratio=None), False, scans, kept, truth, after=80)
    assert step > 5.0 and end > 5.0, (step, end)


def test_a_regular_log_is_registered_as_before(drive):
    """Without gaps (10 Hz) no scan is searched and the poses are those of the one-interval model."""
    scans, kept, truth = _without(drive, range(0))
    odometry = [Odometry(resolve_registration(config, scans[0]), planar=False)
                for config in (OdometryConfig(), OdometryConfig(gap_ratio=None))]
    for scan in scans[:40]:
        paced, plain = (o.register(scan)[0] for o in odometry)
        assert np.array_equal(paced, plain)
    assert odometry[0].checks()["gap_guesses_tried"] == 0


def test_a_laser_robot_that_turned_a_corner_while_scans_were_lost(tmp_path):
    """A 2D robot indoors, scans 300-319 lost while it turned 90 deg round a corner (1.7 m): the
    arcs find it (the step within 5 cm, the end within 0.5 m; 4 mm and 0.15 m); predicted one
    interval's motion, the step is 1.9 m off and the end 10 m."""
    log = generate("rooms", tmp_path / "log", seed=0, laps=1, max_scans=400)
    scans, kept, truth = _without(log, range(300, 320))
    turn = np.degrees(np.arctan2(*(np.linalg.inv(truth[299]) @ truth[320])[[1, 0], [0, 0]]))
    assert abs(turn) > 60.0  # the world still turns there
    step, end, checks = _errors(OdometryConfig(), True, scans, kept, truth, after=320)
    assert step <= 0.05 and end <= 0.5, (step, end, checks)
    step, end, _ = _errors(OdometryConfig(gap_ratio=None), True, scans, kept, truth, after=320)
    assert step > 1.0 and end > 5.0, (step, end)


def test_a_vehicle_at_keyframes_seen_through_a_narrow_field(tmp_path):
    """A Livox-like sensor at irregular keyframes along KITTI 06 at up to 12 m/s, no wheels (122
    scans): the odometry within 5 cm (0.008 m); predicted one interval's motion, 0.87 m."""
    from submapslam.evaluation.metrics import ate
    from submapslam.trajectory import Trajectory

    log = generate_kitti_drive(shared_data("trajectories", "kitti_gt", "06.txt.xz"), tmp_path / "log", rings="livox",
                               seed=0, max_scans=400, terrain=True, keyframes=True)
    scans, kept, truth = _without(log, range(0))
    times = np.array([s.timestamp for s in scans])
    errors = []
    for config in (OdometryConfig(), OdometryConfig(gap_ratio=None)):
        odometry = Odometry(resolve_registration(config, scans[0]), planar=False)
        assert odometry._gicp is not None  # the narrow field's registration
        poses = np.array([odometry.register(scan)[0] for scan in scans])
        errors.append(ate(Trajectory(times, poses), read_tum(log / "groundtruth_tum.txt"))["rmse"])
    assert errors[0] <= 0.05 and errors[1] > 0.4, errors


def _keyframes_with_a_stop(scans: list, truth: np.ndarray, gaps: np.ndarray, stop: int) -> tuple[list, list]:
    """Every ``gaps``-th scan in turn (keyframes), and after keyframe ``stop`` three more scans of
    its pose 3.4 s apart (a stop; the keyframes after it come 10.2 s later): ``(scans, poses (4, 4))``."""
    kept = [0] + [int(i) for i in np.cumsum(gaps) if i < len(scans)]
    log, poses = [], []
    for j, i in enumerate(kept):
        pause = 3 * 3.4 if j > stop else 0.0  # [s] the stop's three intervals come before
        log.append(dataclasses.replace(scans[i], timestamp=scans[i].timestamp + pause))
        poses.append(truth[i])
        if j == stop:
            log += [dataclasses.replace(scans[i], timestamp=scans[i].timestamp + 3.4 * r) for r in (1, 2, 3)]
            poses += [truth[i]] * 3
    return log, poses


def _step_and_end_errors(log: list, poses: list, k: int) -> tuple[float, float, dict]:
    """The odometry alone over ``log``: ``(error [m] of the step into scan k, of the end relative
    to the start, the odometry's checks)``."""
    odometry = Odometry(resolve_registration(OdometryConfig(), log[0]), planar=False)
    estimate = [odometry.register(scan)[0] for scan in log]
    step = np.linalg.inv(estimate[k - 1]) @ estimate[k]
    true_step = np.linalg.inv(poses[k - 1]) @ poses[k]
    end = np.linalg.inv(estimate[0]) @ estimate[-1]
    true_end = np.linalg.inv(poses[0]) @ poses[-1]
    return (float(np.linalg.norm(step[:3, 3] - true_step[:3, 3])),
            float(np.linalg.norm(end[:3, 3] - true_end[:3, 3])), odometry.checks())


def test_a_keyframed_drive_that_stood_still_goes_on_at_its_pace(drive):
    """Keyframes 0.2-0.5 s apart, and halfway a stop: three scans 3.4 s apart where the vehicle
    stood; the next keyframe is 4.3 m on. Registered from no motion (the last step), the scan after
    the stop came out 1.6-4.1 m off and the drive ended 40-58 m off (five of six keyframe draws);
    the motion before the stop, at its pace and slower, is guessed too: the step within 0.2 m, the
    end within 1 m (0.03 / 0.43 m and 0.10 / 0.38 m on the two draws here)."""
    scans, _, truth = _without(drive, range(0))
    for draw in (1, 6):
        gaps = np.random.default_rng(draw).integers(2, 6, 60)
        stop = (len(np.cumsum(gaps)[np.cumsum(gaps) < len(scans)]) + 1) // 2
        log, poses = _keyframes_with_a_stop(scans, truth, gaps, stop)
        restart = stop + 4
        assert np.linalg.norm((np.linalg.inv(poses[restart - 1]) @ poses[restart])[:3, 3]) > 4.0  # at speed there
        step, end, _ = _step_and_end_errors(log, poses, restart)
        assert step <= 0.2 and end <= 1.0, (draw, step, end)


def test_a_steady_keyframed_drive_that_stood_still_is_seen_to_stand(drive):
    """Keyframes every 0.4-0.5 s (a steady rate: a long interval is taken for scans lost while
    moving) with the same stop: at fourteen of twenty places along the street the stop was
    registered as 3-9 m of driving (the drive ended 54 and 64 m off at the two here). The registration
    from standing still is tried too, and wins where it puts 5 % more of the scan on the map (19 of
    20 places end within 0.5 m). Two of the places that failed: the first still scan within 0.2 m,
    the end within 1 m (0.03 / 0.40 m and 0.04 / 0.45 m)."""
    scans, _, truth = _without(drive, range(0))
    gaps = np.random.default_rng(0).integers(4, 6, 60)
    for stop in (7, 10):
        log, poses = _keyframes_with_a_stop(scans, truth, gaps, stop)
        step, end, checks = _step_and_end_errors(log, poses, stop + 1)
        assert step <= 0.2 and end <= 1.0 and checks["gap_stood_won"] == 1, (stop, step, end, checks)
