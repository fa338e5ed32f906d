"""A spinning LiDAR logged at irregular keyframes (0.2-0.5 s and 1-6 m apart, with stops), as
MulRan's keyframes are: each scan enters KISS-ICP's local map 8 scans late at 10 Hz, but in such a
log 8 scans lay 20-40 m behind, and registering to a map that far back shrank the path by
0.15-0.2 %. A scan now also enters once the newest scan is ``odometry.movers_delay_s`` later."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from datasets_synth import generate_kitti_drive
from submapslam import open_log, run
from submapslam.config import PipelineConfig, with_updates
from submapslam.evaluation.metrics import ate
from submapslam.io.trajectory import read_tum
from submapslam.trajectory import Trajectory

from .conftest import shared_data


@pytest.fixture(scope="module")
def keyframed_drive(tmp_path_factory):
    """16 rings at irregular keyframes along the first 400 poses of KITTI 05 with terrain (119 scans)."""
    return generate_kitti_drive(shared_data("trajectories", "kitti_gt", "05.txt.xz"),
                                tmp_path_factory.mktemp("keyframed") / "log", rings=16, seed=11, max_scans=400,
                                terrain=True, keyframes=True)


def _ate(folder, config: PipelineConfig | None = None) -> float:
    result = run(open_log(folder), config=config)
    truth = read_tum(folder / "groundtruth_tum.txt")
    assert len(result.poses) == len(truth.poses)
    return float(ate(Trajectory(result.timestamps, result.poses), truth)["rmse"])


def test_a_keyframed_drive_is_not_shrunk_by_a_local_map_far_behind(keyframed_drive):
    """0.078 m at the defaults; 0.135 m when every scan waited 8 scans (its path 0.16 % short)."""
    assert np.median(np.diff(read_tum(keyframed_drive / "groundtruth_tum.txt").timestamps)) > 0.3
    error = _ate(keyframed_drive)
    by_count = _ate(keyframed_drive, with_updates(PipelineConfig(), {"odometry": {"movers_delay_s": None}}))
    assert error <= 0.10, f"ATE {error:.4f} m"
    assert error < 0.8 * by_count, f"ATE {error:.4f} m, {by_count:.4f} m by the count alone"


def test_a_folder_without_times_waits_by_the_count_alone(tmp_path):
    """A cloud folder without times.txt numbers its scans 0, 1, 2 ... as their timestamps: taken
    for seconds they would let every scan into the local map one scan late. Its scans say they
    carry no times, and wait the 8 scans, in this process and in the odometry's child process."""
    from submapslam.config import OdometryConfig
    from submapslam.odometry import Odometry, resolve_registration
    from submapslam.odometry_stage import InlineOdometry, OdometryProcess

    log = generate_kitti_drive(shared_data("trajectories", "kitti_gt", "00.txt.xz"), tmp_path / "log", rings=16,
                               seed=2, max_scans=12)
    (log / "times.txt").unlink()
    untimed = list(open_log(log))
    assert [s.timestamp for s in untimed[:3]] == [0.0, 1.0, 2.0] and not any(s.timed for s in untimed)
    config = resolve_registration(OdometryConfig(), untimed[0])

    def entered(scans) -> int:
        odometry = Odometry(config, planar=False)
        for scan in scans[:10]:
            odometry.register(scan)
        return odometry._scans_in_map

    timed_each_second = [dataclasses.replace(s, timed=True) for s in untimed]
    assert entered(untimed) == 2            # the first at once, the second when the tenth came
    assert entered(timed_each_second) == 9  # real times 1 s apart: each enters one scan late
    inline, child = InlineOdometry(config, False), OdometryProcess(config, False)
    try:
        for scan in untimed:
            inline.submit(scan)
            child.submit(scan)
            assert np.array_equal(inline.result().pose, child.result().pose)
    finally:
        child.close()
