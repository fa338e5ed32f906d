"""Real 3D logs end to end at the defaults: accuracy against their reference poses.

The two Livox sequences of ../shared/data/lidar3d (a hand-held narrow-field sensor, keyframes
irregular in time, no IMU used here) and MulRan KAIST03's first keyframes (a 64-ring spinning
LiDAR on a car): the guard that the 3D defaults hold on data they were not made on. KISS-ICP 1.3.0
at its defaults gets 0.83 m and 1.54 m on the Livox ones (SOURCE.txt), 0.029 m on MulRan's.
"""

from __future__ import annotations

import numpy as np

from submapslam import open_log, run
from submapslam.evaluation.metrics import ate
from submapslam.io.trajectory import read_kitti
from submapslam.trajectory import Trajectory

from .conftest import load_tool, shared_data


def _run_against_reference(name: str):
    folder = shared_data("lidar3d", name)
    result = run(open_log(folder / "scans"))
    stamps = np.loadtxt(folder / "scans" / "times.txt", ndmin=1)
    reference = read_kitti(folder / "reference_poses_kitti.txt", timestamps=stamps)
    return result, reference, _ate(result.timestamps, result.poses, reference)


def _ate(stamps: np.ndarray, poses: np.ndarray, reference: Trajectory) -> float:
    return float(ate(Trajectory(stamps, poses), reference, align="se3")["rmse"])


def _dynamic_share(result) -> float:
    """Share of the fused points that ``map_dynamic.ply`` would hold (the scenes are a campus with
    few movers: an upper bound on what a static world loses, which must stay <= 0.5 %)."""
    from submapslam.mapping.global_map import build_map_outputs

    maps = build_map_outputs(result)
    return len(maps.dynamic_points) / (len(maps.points) + len(maps.dynamic_points))


def test_livox_loop_is_closed_and_within_a_tenth_of_a_metre():
    result, reference, error = _run_against_reference("livox_hku_loop")
    assert len(result.poses) == 266
    assert error <= 0.08, f"ATE {error:.3f} m"
    last = len(result.submap_poses) - 1
    closing = [loop for loop in result.loops if loop.accepted and loop.i == 0 and loop.j >= last - 1]
    assert closing, "no closure accepted between the first and the last submaps"
    # the end lies where the scans put it: registering the last scan onto the first five
    # (placed by the reference) puts it 0.077 m from the first; the reference says 0.18 m
    end_to_start = np.linalg.norm(result.poses[-1][:3, 3] - result.poses[0][:3, 3])
    assert end_to_start < 0.15
    assert _dynamic_share(result) <= 0.005


def test_livox_main_building_within_a_tenth_of_a_metre_and_no_worse_than_its_odometry():
    """No closure, and ground seen under 2 of 8 anchors: too little to test the level priors' bet,
    so without a closure to vouch for them they go, and the run keeps its odometry (with them it
    had ended at 0.0625 m against the odometry's 0.0483 m)."""
    result, reference, error = _run_against_reference("livox_hku_main_building")
    assert len(result.poses) == 457
    assert error <= 0.10, f"ATE {error:.3f} m"
    odometry_error = _ate(result.timestamps, result.odometry_poses, reference)
    assert error <= odometry_error + 0.002, f"ATE {error:.4f} m, its odometry {odometry_error:.4f} m"
    assert result.ground_priors["level"] is None and result.ground_priors["kept"] is False
    assert _dynamic_share(result) <= 0.005


def _cut_against_reference(name: str, folder_out, start: int, step: int) -> float:
    """The ATE [m] of a run on every ``step``-th scan of real log ``name`` from scan ``start``
    (``tools/cut_cloud_log.py`` into ``folder_out``), against the reference poses of those scans."""
    cut = folder_out / "cut"
    kept = load_tool("cut_cloud_log").cut(shared_data("lidar3d", name), cut, start, step)
    stamps = np.loadtxt(cut / "scans" / "times.txt", ndmin=1)
    reference = read_kitti(cut / "reference_poses_kitti.txt", timestamps=stamps)
    result = run(open_log(cut / "scans"))
    assert len(result.poses) == kept
    return _ate(result.timestamps, result.poses, reference)


def test_livox_main_building_at_every_second_keyframe(tmp_path):
    """Twice the motion between scans (turns of 10-23 deg, steps up to 0.7 m): 0.28 m, where it was
    10.8 m before guesses turned by +-10 and +-20 deg were tried on a poor fit, and a result far
    from the prediction gave way to a near one fitting about as well (KISS-ICP 1.3.0: 21.8 m)."""
    error = _cut_against_reference("livox_hku_main_building", tmp_path, 0, 2)
    assert error <= 0.35, f"ATE {error:.3f} m"


def test_livox_loop_started_midway(tmp_path):
    """The loop from its 60th keyframe on (a start facing other walls): 0.033 m, where it was
    0.86 m before the same two checks (KISS-ICP 1.3.0: 0.75 m)."""
    error = _cut_against_reference("livox_hku_loop", tmp_path, 60, 1)
    assert error <= 0.06, f"ATE {error:.3f} m"


def test_livox_loop_from_its_hundredth_keyframe_where_more_inliers_fit_worse(tmp_path):
    """The loop from its 100th keyframe on: 0.097 m. An alignment with more inliers than another
    replaces it only if those inliers fit about as well (mean GICP cost within twice the other's);
    by inliers alone it ended 1.03 m off."""
    error = _cut_against_reference("livox_hku_loop", tmp_path, 100, 1)
    assert error <= 0.15, f"ATE {error:.3f} m"


def test_mulran_keyframes_of_a_64_ring_lidar_within_three_and_a_half_centimetres():
    """The first 21 keyframes of MulRan KAIST03 (an Ouster OS1-64 on a car, keyframes 0.2-0.7 s and
    1.0-1.4 m apart, 23 m) against SC-A-LOAM's pose-graph output for them (an estimate, not a
    survey): 0.029 m at the defaults, KISS-ICP 1.3.0 at its defaults 0.029 m on the same scans
    (tools/bench_regression.py --only real3d). A scan enters KISS-ICP's local map 8 scans late
    (``odometry.movers_delay``) or once the newest scan is 0.8 s later (``movers_delay_s``), here
    after 4: by the count alone the first scans registered against the first one alone, 0.036 m."""
    folder = shared_data("lidar3d", "mulran_kaist03")
    result = run(open_log(folder))
    assert len(result.poses) == 21
    stamps = np.loadtxt(folder / "times.txt.xz", ndmin=1)
    whole = read_kitti(folder / "optimized_poses.txt.xz", timestamps=stamps)
    reference = Trajectory(whole.timestamps[:21], whole.poses[:21])
    np.testing.assert_allclose(result.timestamps, reference.timestamps)
    error = _ate(result.timestamps, result.poses, reference)
    assert error <= 0.035, f"ATE {error:.4f} m"
    assert _dynamic_share(result) <= 0.005
