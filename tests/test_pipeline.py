"""End-to-end runs with the accuracy targets asserted on small inputs."""

import itertools
import json

import numpy as np
import pytest

from datasets_synth import generate
from submapslam import SubmapSLAM, open_log
from submapslam.api import run_log
from submapslam.config import PipelineConfig
from submapslam.evaluation.metrics import ate
from submapslam.geometry import inverse
from submapslam.io.scan import Scan
from submapslam.io.trajectory import Trajectory, read_tum
from submapslam.pipeline import run

from .conftest import shared_data

FALSE_CLOSURE_M = 1.0  # a closure whose transform is off by more than this is a false one


def loop_errors(result, gt):
    """Translation error of every accepted loop against the ground-truth anchor poses."""
    anchors = [gt.poses[idx[0]] for idx in result.submap_scan_indices]
    errs = []
    for lp in result.loops:
        if lp.accepted:
            true = inverse(anchors[lp.i]) @ anchors[lp.j]
            errs.append(float(np.linalg.norm((inverse(true) @ lp.T_i_j)[:3, 3])))
    return np.array(errs)


@pytest.fixture(scope="module")
def rectangle_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("rect")
    log = generate("rectangle", root / "log", seed=0, laps=2)
    result, paths = run_log(log, root / "out")
    return log, result, paths


def test_rectangle_two_laps_closes_loops_without_false_closures(rectangle_run):
    log, result, _ = rectangle_run
    gt = read_tum(log / "groundtruth_tum.txt")
    wheel = read_tum(log / "odometry_tum.txt")
    slam = ate(Trajectory(result.timestamps, result.poses), gt)["rmse"]
    assert result.loops_accepted >= 10
    assert np.all(loop_errors(result, gt) < FALSE_CLOSURE_M)
    assert slam <= ate(wheel, gt)["rmse"] / 5
    # Against the scan-matching odometry (no loop closure): the loop-closed error is a floor of
    # 6-7 mm on every seed, the odometry's 1-3 cm varies with the seed and with the CPU's
    # floating point (seed 0: 6.5x on the machine that first measured it, 4.8x on another), so
    # the ratio is asserted with a margin and the floor absolutely (BENCHMARKS.md has both).
    odo = ate(Trajectory(result.timestamps, result.odometry_poses), gt)["rmse"]
    assert slam <= odo / 3
    assert slam < 0.01


def test_run_writes_every_output(rectangle_run):
    _, result, paths = rectangle_run
    out = paths["poses_tum.txt"].parent
    for name in ("poses_tum.txt", "poses_kitti.txt", "graph.g2o", "map.ply", "config.yaml", "summary.json",
                 "loops.csv", "submaps.csv", "map.pgm", "map.yaml"):
        assert (out / name).stat().st_size > 0, name
    tum = read_tum(out / "poses_tum.txt")
    assert len(tum) == result.n_scans
    np.testing.assert_allclose(tum.timestamps, result.timestamps, atol=1e-6)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scans"] == result.n_scans and summary["loop_closures_accepted"] == result.loops_accepted
    assert set(summary["wall_time_s"]) >= {"odometry", "submaps", "optimisation", "loop_testing", "scan_refinement"}
    assert summary["scan_refinement"]["matches_kept"] > 0  # 2D: every scan refined after the submap solve
    checks = summary["odometry_checks"]  # 2D: how often the odometry's checks overruled a guess
    assert set(checks) == {"wheel_overruled", "registration_overruled", "previous_scan_checked",
                           "previous_scan_preferred", "gap_guesses_tried", "gap_guess_won", "wall_noise_m"}
    assert all(v >= 0 for v in checks.values()) and checks["gap_guesses_tried"] == 0  # wheels predict every scan
    assert 0.002 < checks["wall_noise_m"] < 0.012  # the synthetic laser's 1 cm of range noise, as measured
    for T_anchor, idx, T_anchor_scans in zip(result.submap_poses, result.submap_scan_indices,
                                             result.submap_scan_poses):  # the grid's scan poses are the refined ones
        np.testing.assert_allclose(T_anchor @ T_anchor_scans, result.poses[idx], atol=1e-9)
    lines = (out / "loops.csv").read_text().splitlines()
    assert len(lines) == len(result.loops) + 1
    g2o = (out / "graph.g2o").read_text()
    assert g2o.count("VERTEX_SE3:QUAT") == result.n_submaps
    assert g2o.count("EDGE_SE3:QUAT") == result.n_submaps - 1 + result.loops_accepted
    assert result.submap_covariances.shape == (result.n_submaps, 6, 6)
    assert np.all(np.linalg.eigvalsh(result.submap_covariances[-1]) > 0)


def test_rooms_world_accepts_no_false_closure(tmp_path):
    log = generate("rooms", tmp_path / "log", seed=0, laps=2, size=(36.0, 12.0))
    result, _ = run_log(log, None)
    gt = read_tum(log / "groundtruth_tum.txt")
    assert np.all(loop_errors(result, gt) < FALSE_CLOSURE_M)
    odo = ate(Trajectory(result.timestamps, result.odometry_poses), gt)["rmse"]
    slam = ate(Trajectory(result.timestamps, result.poses), gt)["rmse"]
    assert slam <= odo * 1.05


def test_streaming_api_gives_a_trajectory_at_any_time():
    path = shared_data("carmen", "intel.clf.bz2")
    slam = SubmapSLAM(PipelineConfig())
    for n, scan in enumerate(itertools.islice(open_log(path), 400), start=1):
        slam.process_scan(scan)
        if n in (50, 400):
            stamps, poses = slam.trajectory()
            assert len(stamps) == n and poses.shape == (n, 4, 4)
    assert len(slam.map_points()) > 100
    result = slam.finish()
    assert result.n_scans == 400 and result.n_submaps >= 1


def test_nan_points_and_empty_scans_are_survived():
    rng = np.random.default_rng(0)
    slam = SubmapSLAM(PipelineConfig())
    walls = np.c_[rng.uniform(-5, 5, 300), np.repeat([-2.0, 2.0], 150), np.zeros(300)]
    for k in range(30):
        pts = walls.copy()
        if k == 10:
            pts[::7] = np.nan
        if k == 20:
            pts = np.zeros((0, 3))
        slam.process_scan(Scan(index=k, timestamp=float(k), points=pts, planar=True))
    result = slam.finish()
    assert result.n_scans == 30 and np.all(np.isfinite(result.poses))
    assert slam.dropped_nan_points == 43 and slam.empty_scans == 1


def test_truncated_log_keeps_what_was_computed(tmp_path):
    log = generate("rectangle", tmp_path / "log", seed=2, laps=1, max_scans=120)
    text = (log / "log.clf").read_text().splitlines()
    cut = [i for i, line in enumerate(text) if line.startswith("FLASER")][100]
    (tmp_path / "cut.clf").write_text("\n".join(text[:cut] + [text[cut][:200]]) + "\n")
    result, paths = run_log(tmp_path / "cut.clf", tmp_path / "out")
    assert result.input_error is not None and "truncated" in result.input_error
    assert result.n_scans == 100
    assert len(read_tum(paths["poses_tum.txt"])) == 100


def test_manual_hint_closes_a_loop_the_graph_did_not_propose(tmp_path):
    """A hint pairs the first and the last scan of a lap; with spatial and appearance proposals
    switched off it is the only hypothesis, and it goes through the same correspondence test."""
    log = generate("rectangle", tmp_path / "log", seed=0, laps=1)
    n = len(read_tum(log / "groundtruth_tum.txt"))
    hints = tmp_path / "hints.txt"
    hints.write_text(f"# scan indices taken at the same place\n0 {n - 5}\n")
    cfg = PipelineConfig.model_validate({"loops": {"use_descriptor": False, "spatial_max_radius": 1e-3,
                                                   "spatial_min_radius": 1e-3}})
    result, _ = run_log(log, None, config=cfg, hints=hints)
    sources = {lp.source for lp in result.loops}
    assert sources == {"hint"}
    assert result.loops_accepted == 1
    gt = read_tum(log / "groundtruth_tum.txt")
    assert np.all(loop_errors(result, gt) < 0.3)
    bad = tmp_path / "bad.txt"
    bad.write_text("0 1 2\n")
    from submapslam.errors import InputError

    with pytest.raises(InputError, match=r"bad\.txt:1: expected two values"):
        run_log(log, None, hints=bad)


def test_hints_by_timestamp_and_bad_hint_lines(tmp_path):
    from submapslam.errors import InputError
    from submapslam.io.hints import read_hint_file

    p = tmp_path / "h.txt"
    p.write_text("3 900  # indices\n1000.0 1088.5\n")
    hints = read_hint_file(p)
    assert hints[0].by_index and (hints[0].a, hints[0].b) == (3.0, 900.0)
    assert not hints[1].by_index and hints[1].b == 1088.5  # 1000.0 is a time, not scan 1000
    p.write_text("3 1088.5\n")
    with pytest.raises(InputError, match=r"h\.txt:1: mixes a scan index with a timestamp"):
        read_hint_file(p)
    log = generate("rectangle", tmp_path / "log", seed=0, laps=1)
    gt = read_tum(log / "groundtruth_tum.txt")
    p.write_text(f"{gt.timestamps[0]:.3f} {gt.timestamps[-5]:.3f}\n")
    cfg = PipelineConfig.model_validate({"loops": {"use_descriptor": False, "spatial_max_radius": 1e-3,
                                                   "spatial_min_radius": 1e-3}})
    result, _ = run_log(log, None, config=cfg, hints=p)
    assert [lp.source for lp in result.loops] == ["hint"] and result.loops_accepted == 1


def test_a_map_bent_away_from_its_odometry_says_so(rectangle_run, tmp_path):
    """No ground truth at run time: the odometry edges' residuals after optimisation tell. The
    rectangle's run agrees with its odometry; the same result with one anchor turned by 5 degrees
    and moved 0.5 m (what a wrong loop does) is flagged, in summary.json and the HTML report."""
    import dataclasses

    from submapslam.evaluation.html_report import build_run_report
    from submapslam.geometry import se2_to_matrix
    from submapslam.io.run_folder import read_run_folder

    _, result, paths = rectangle_run
    ok = result.odometry_consistency()
    assert ok["odometry_edges"] == result.n_submaps - 1
    assert not ok["disagrees_with_odometry"] and ok["message"] is None and ok["odometry_chi2_max"] < 4.0
    assert json.loads(paths["summary.json"].read_text())["consistency"]["disagrees_with_odometry"] is False
    anchors = result.submap_poses.copy()
    k = result.n_submaps // 2
    anchors[k] = anchors[k] @ se2_to_matrix(0.5, 0.0, np.deg2rad(5.0))
    bent = dataclasses.replace(result, submap_poses=anchors).odometry_consistency()
    assert bent["disagrees_with_odometry"] and bent["worst_odometry_edge"][0] in (k - 1, k)
    assert "disagrees with the odometry" in bent["message"]
    summary = json.loads(paths["summary.json"].read_text())
    summary["consistency"] = bent
    run_dir = paths["summary.json"].parent
    rec = dataclasses.replace(read_run_folder(run_dir, with_cloud=False), summary=summary)
    assert "disagrees with the odometry" in build_run_report(rec)


def test_planar_covariances_stay_planar(rectangle_run):
    """A 2D log observes x, y and yaw: every anchor's marginal sigma in z, roll and pitch stays tiny
    (loops and registration-shaped odometry edges once let sigma_z reach metres), x/y do not."""
    from submapslam.graph_builder import pin_planar

    _, result, _ = rectangle_run
    assert result.planar
    sig = np.sqrt(np.diagonal(result.submap_covariances, axis1=1, axis2=2))  # (S, 6) GTSAM order
    assert sig[:, [0, 1, 5]].max() < 1e-2  # roll, pitch [rad], z [m]
    assert sig[1:, [3, 4]].max() > 1e-3  # x, y are uncertain
    loose = np.full((6, 6), 0.5) + np.eye(6)
    pinned = pin_planar(loose)
    assert pinned[5, 5] == 1e8 and pinned[5, 3] == 0.0 and pinned[3, 4] == 0.5


def test_run_writes_pose_covariances(rectangle_run):
    """poses_cov.txt: one pose and covariance per scan (the result's), positive definite; each
    anchor's scan carries its anchor's reported marginal (x, y, yaw)."""
    from submapslam.io.trajectory import read_tum_cov

    _, result, paths = rectangle_run
    traj, covs = read_tum_cov(paths["poses_cov.txt"])
    assert len(traj) == result.n_scans
    np.testing.assert_allclose(traj.poses, result.poses, atol=1e-7)
    np.testing.assert_allclose(covs, result.pose_covariances(), rtol=1e-6, atol=1e-14)
    assert np.all(np.linalg.eigvalsh(covs) > 0)
    for k, idx in enumerate(result.submap_scan_indices):
        want = result.submap_covariances[k, 2:5, 2:5]  # a refined anchor scan sits mm off its anchor:
        np.testing.assert_allclose(covs[idx[0], 2:5, 2:5], want, rtol=1e-3, atol=1e-3 * np.trace(want))


def test_covariance_scale_changes_only_the_reported_covariances(rectangle_run, tmp_path):
    """backend.covariance_scale scales the anchors' reported marginals per axis (D Sigma D) and
    nothing else: the same poses and loop decisions as the graph's raw marginals (scale 1)."""
    from submapslam.config import BackendConfig
    from submapslam.uncertainty import COVARIANCE_SCALE_PLANAR

    log = rectangle_run[0]
    raw, _ = run_log(log, None, max_scans=150, config=PipelineConfig(backend=BackendConfig(covariance_scale=[1] * 6)))
    cal, _ = run_log(log, None, max_scans=150)
    np.testing.assert_array_equal(cal.poses, raw.poses)
    assert [(lp.i, lp.j, lp.accepted) for lp in cal.loops] == [(lp.i, lp.j, lp.accepted) for lp in raw.loops]
    d = np.sqrt(np.array(COVARIANCE_SCALE_PLANAR))
    np.testing.assert_allclose(cal.submap_covariances, raw.submap_covariances * np.outer(d, d), rtol=1e-9, atol=1e-18)
    k = cal.submap_scan_indices[-1][0]  # the last anchor's own scan: its anchor's covariance, so scaled alike
    s = np.diagonal(cal.pose_covariances()[k]) / np.diagonal(raw.pose_covariances()[k])
    np.testing.assert_allclose(s[2:5], COVARIANCE_SCALE_PLANAR[2:5], rtol=1e-2)


def test_the_run_frame_is_rebased_on_the_first_scan_registered_again(tmp_path):
    """``odometry.startup_refit_scans``: the first scan, registered again against the 20 after it,
    re-bases the run. Every later pose moves by one rigid correction (the odometry between them is
    the same), the first keeps its pose, and the heading the first scans shared (rooms, seed 0:
    0.07 deg at scan 20) leaves the trajectory."""
    from submapslam.geometry import matrix_to_se2

    log = generate("rooms", tmp_path / "log", seed=0, laps=1, max_scans=60)
    truth = read_tum(log / "groundtruth_tum.txt").poses
    runs = {}
    for n in (0, 20):
        cfg = PipelineConfig.model_validate({"odometry": {"startup_refit_scans": n}, "loops": {"enabled": False}})
        runs[n] = run(open_log(log), cfg).odometry_poses
    off, on = runs[0], runs[20]
    assert len(on) == len(off) == 60 and np.array_equal(on[0], off[0])
    correction = on[1] @ inverse(off[1])
    moved = matrix_to_se2(correction)
    assert 0 < abs(moved[2]) < np.deg2rad(1.0)
    assert all(np.allclose(on[k], correction @ off[k], atol=1e-9) for k in range(1, 60))

    def heading_error(poses, k):  # of scan k relative to the first scan, against the truth
        return abs(matrix_to_se2(inverse(inverse(truth[0]) @ truth[k]) @ (inverse(poses[0]) @ poses[k]))[2])

    assert heading_error(on, 20) < 0.5 * heading_error(off, 20)


def test_a_3d_run_frame_is_rebased_on_the_first_scan_registered_against_the_settled_scans(tmp_path):
    """3D: a 16-ring LiDAR's first scans register against a young local map whose ground rings
    hold them near the first scan's rings (at the steep, bumpy start of a terrain drive along KITTI
    08 this seed's second scan came out 3 m and 3.5 deg off), while the scans after them agree.
    The first scan, registered again (GICP) against the scans 12-30, re-bases the run: every later
    pose moves by one rigid correction, and most of the error the run carried relative to its first
    scan leaves it."""
    from datasets_synth.city import generate_kitti_drive
    from submapslam.geometry import pose_difference

    log = generate_kitti_drive(shared_data("trajectories", "kitti_gt", "08.txt.xz"), tmp_path / "log", rings=16,
                               seed=310, max_scans=45, terrain=True)
    truth = read_tum(log / "groundtruth_tum.txt").poses
    runs = {}
    for n in (0, None):
        cfg = PipelineConfig.model_validate({"odometry": {"startup_refit_scans": n}, "loops": {"enabled": False}})
        runs[n] = run(open_log(log), cfg).odometry_poses
    off, on = runs[0], runs[None]
    assert len(on) == len(off) == 45 and np.array_equal(on[0], off[0])
    correction = on[1] @ inverse(off[1])
    assert all(np.allclose(on[k], correction @ off[k], atol=1e-9) for k in range(1, 45))

    def errors(poses):  # [deg], [m] of scans 20-44 relative to the first scan, against the truth
        e = np.array([pose_difference(inverse(inverse(truth[0]) @ truth[k]) @ (inverse(poses[0]) @ poses[k]))
                      for k in range(20, 45)])
        return np.degrees(np.linalg.norm(e[:, :3], axis=1)).mean(), np.linalg.norm(e[:, 3:], axis=1).mean()

    (turn_off, shift_off), (turn_on, shift_on) = errors(off), errors(on)
    assert turn_on < 0.5 * turn_off and shift_on < 0.5 * shift_off, (turn_on, turn_off, shift_on, shift_off)
