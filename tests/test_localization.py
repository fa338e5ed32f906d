"""Localization in a fixed map: accuracy against ground truth, global initialisation, kidnapping,
the map left untouched, the 3D path, the CLI and its one-line input errors."""

import dataclasses
import hashlib
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from datasets_synth import generate
from submapslam import open_log
from submapslam.api import report_run, run_log
from submapslam.cli import app
from submapslam.errors import InputError
from submapslam.geometry import matrix_to_se2
from submapslam.io.trajectory import read_kitti, read_tum, read_tum_cov
from submapslam.localization import LocalizationConfig, Localizer, load_map, localize_log

from .report_pages import assert_layer_has_ink, assert_not_blank, figure_png

runner = CliRunner()
SIZE = (16.0, 10.0)  # a small rectangle of hallways: two laps map in a few seconds


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A map built by the pipeline (two laps), and a different run in the same world (slower,
    twice the odometry noise: other scan places, other noise), with its truth in the map frame."""
    root = tmp_path_factory.mktemp("loc")
    map_log = generate("rectangle", root / "map_log", seed=0, laps=2, size=SIZE)
    run_log(map_log, root / "map_run")
    loc_log = generate("rectangle", root / "loc_log", seed=0, laps=1, size=SIZE, speed=0.8, odometry_noise=2.0)
    # the map frame is the mapping run's first pose
    T_map_gt = np.linalg.inv(read_tum(map_log / "groundtruth_tum.txt").poses[0])
    truth = T_map_gt @ read_tum(loc_log / "groundtruth_tum.txt").poses
    return {"map_run": root / "map_run", "loc_log": loc_log, "truth": truth, "scans": list(open_log(loc_log))}


def position_errors(poses, truth):
    return np.linalg.norm(poses[:, :2, 3] - truth[:, :2, 3], axis=1)


def test_localizes_another_run_within_centimetres_and_leaves_the_map_alone(world):
    ply = world["map_run"] / "map.ply"
    digest = hashlib.sha256(ply.read_bytes()).hexdigest()
    points = load_map(world["map_run"])
    kept = points.copy()
    res = localize_log(world["scans"], points, initial_pose=world["truth"][0])
    err = position_errors(res.poses, world["truth"])
    assert res.n_scans == len(world["scans"]) > 400
    np.testing.assert_array_equal(res.timestamps, [s.timestamp for s in world["scans"]])
    assert np.sqrt(np.mean(err**2)) < 0.03 and err.max() < 0.06
    yaw_err = [abs(np.angle(np.exp(1j * (matrix_to_se2(a)[2] - matrix_to_se2(b)[2]))))
               for a, b in zip(res.poses, world["truth"])]
    assert np.rad2deg(max(yaw_err)) < 1.0
    assert not res.lost.any() and res.relocalisations == 0 and res.fitness.min() > 0.9
    # the map is fixed: neither the file nor the array changed
    assert hashlib.sha256(ply.read_bytes()).hexdigest() == digest
    np.testing.assert_array_equal(points, kept)


def test_constant_velocity_prediction_and_a_wrong_initial_pose(world):
    """Without wheel odometry, every 2nd scan (0.16 m apart): along a corridor the scene does not
    fix the position, so only a right constant-velocity prediction keeps the pose. A wrong initial
    pose (1.4 m off) is not kept: the robot is declared lost and found by the global
    search, and the scans before the fix are re-anchored on it."""
    res = localize_log(world["scans"][:240:2], world["map_run"], initial_pose=world["truth"][0],
                       config=LocalizationConfig(use_wheel_odometry=False))
    assert position_errors(res.poses, world["truth"][:240:2]).max() < 0.06 and not res.lost.any()
    off = world["truth"][150].copy()  # mid-corridor
    off[:2, 3] += [1.0, 1.0]
    res = localize_log(world["scans"][150:190], world["map_run"], initial_pose=off)
    assert res.lost[:5].all() and res.relocalisations == 1
    assert position_errors(res.poses, world["truth"][150:190]).max() < 0.06
    assert not res.lost[5:].any() and res.fitness[5:].min() > 0.9


def test_global_initialisation_finds_the_start_without_an_initial_pose(world):
    start = 150  # mid-corridor, far from the map origin: the identity would be metres off
    truth = world["truth"][start:start + 80]
    assert np.linalg.norm(truth[0][:2, 3]) > 5.0
    res = localize_log(world["scans"], world["map_run"], start=start, max_scans=80)
    assert res.global_searches >= 1 and res.initialised_at <= 5
    err = position_errors(res.poses, truth)
    assert err[res.initialised_at:].max() < 0.06
    assert not res.lost[res.initialised_at:].any()


def kidnapped(scans, a, jump, b):
    """Scans 0..a-1, then scans jump..jump+b-1 with the wheel odometry continuing smoothly, as if
    the robot had been carried away without its wheels noticing."""
    first, second = scans[:a], scans[jump:jump + b]
    step = np.linalg.inv(scans[a - 1].odometry) @ scans[a].odometry
    base = first[-1].odometry @ step @ np.linalg.inv(second[0].odometry)
    return first + [dataclasses.replace(s, odometry=base @ s.odometry) for s in second]


def test_kidnapped_robot_is_reported_lost_and_relocalised(world):
    a, jump, b = 120, 330, 120
    scans = kidnapped(world["scans"], a, jump, b)
    truth = np.concatenate([world["truth"][:a], world["truth"][jump:jump + b]])
    assert np.linalg.norm(truth[a][:2, 3] - truth[a - 1][:2, 3]) > 5.0  # a real kidnap
    cfg = LocalizationConfig()
    res = localize_log(scans, world["map_run"], initial_pose=truth[0], config=cfg)
    spans = res.lost_spans()
    assert len(spans) == 1 and spans[0][0] == a and spans[0][1] < a + cfg.lost_after + 2 * cfg.relocalize_every
    assert res.relocalisations == 1
    assert not res.lost[:a].any()
    err = position_errors(res.poses, truth)
    assert err[spans[0][1] + 1:].max() < 0.06  # tracking after the fix
    assert err[a:].max() < 0.1                  # the lost span re-anchored on the fix by dead reckoning
    s = res.summary()
    assert s["lost_scans"] == spans[0][1] - a + 1 and s["lost_spans"][0]["first_scan"] == a
    # without a gate the tracker would keep a pose metres away: the gate on the fitness over the
    # mapped area (beams passing through the map's walls) is what caught it
    assert res.fitness_mapped[a:a + cfg.lost_after].max() < cfg.min_fitness


def test_outdoor_3d_localization_and_global_search(tmp_path):
    """3D: a map built from a short outdoor route (ground-truth poses, saved as PCD), a faster run
    localised by GICP; then found by FPFH + RANSAC without an initial pose."""
    from submapslam._deps import open3d
    from submapslam.submaps import voxel_downsample

    sensor = {"rings": 16, "columns": 360}
    m = generate("outdoor", tmp_path / "m", seed=0, laps=1, max_scans=15, sensor_options=sensor)
    log = generate("outdoor", tmp_path / "l", seed=0, laps=1, max_scans=12, speed=6.5, odometry_noise=2.0,
                   sensor_options=sensor)
    gt_map, gt = read_tum(m / "groundtruth_tum.txt").poses, read_tum(log / "groundtruth_tum.txt").poses
    pts = voxel_downsample(np.vstack([s.points @ T[:3, :3].T + T[:3, 3] for s, T in zip(open_log(m), gt_map)]), 0.1)
    o3d = open3d()
    assert o3d.io.write_point_cloud(str(tmp_path / "map.pcd"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    points = load_map(tmp_path / "map.pcd")
    assert not Localizer(points).planar
    for init in (gt[0], None):
        res = localize_log(open_log(log), points, initial_pose=init)
        err = np.linalg.norm(res.poses[:, :3, 3] - gt[:, :3, 3], axis=1)
        assert not res.lost.any() and err.max() < 0.05, (init is None, err.max())
        # 3D covariances: positive definite, and the position error inside 3σ (point-to-point GICP
        # information over the inlier RMSE, plus the map's own error)
        assert np.linalg.eigvalsh(res.covariances).min() > 0
        e_body = np.einsum("nji,nj->ni", res.poses[:, :3, :3], gt[:, :3, 3] - res.poses[:, :3, 3])
        z = e_body**2 / res.covariances[:, 3:6, 3:6].diagonal(axis1=1, axis2=2)
        assert (z <= 9.0).mean() >= 0.9, z.mean(axis=0)
    assert res.global_searches == 1 and np.linalg.norm(gt[0][:2, 3]) > 50  # found 70 m from the origin


def test_cli_localize_writes_every_output(world, tmp_path):
    x, y, yaw = matrix_to_se2(world["truth"][0])
    out = tmp_path / "out"
    r = runner.invoke(app, ["localize", str(world["loc_log"]), "--map", str(world["map_run"]), "--out", str(out),
                            "--initial-pose", f"{x} {y} {yaw}", "--max-scans", "100"])
    assert r.exit_code == 0, r.output
    assert "100 scans, 0 lost" in r.output and "100% consistent with the map" in r.output
    tum = read_tum(out / "poses_tum.txt")
    np.testing.assert_allclose(tum.timestamps, [s.timestamp for s in world["scans"][:100]], atol=1e-6)
    assert position_errors(tum.poses, world["truth"][:100]).max() < 0.06
    assert len(read_kitti(out / "poses_kitti.txt")) == 100
    rows = (out / "localization.csv").read_text().splitlines()
    assert rows[0] == "timestamp,fitness,fitness_mapped,rmse,lost" and len(rows) == 101
    assert all(float(row.split(",")[1]) > 0.9 and float(row.split(",")[2]) > 0.9 and row.endswith(",0")
               for row in rows[1:])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scans"] == 100 and summary["lost_scans"] == 0 and summary["relocalisations"] == 0
    assert summary["scans_per_s"] > 0 and summary["wall_time_s"] > 0
    assert summary["localised"] is True and summary["consistent_fraction"] == 1.0
    # the uncertainty: poses_cov.txt (the poses of poses_tum.txt), a figure, and the report shows both
    traj, covs = read_tum_cov(out / "poses_cov.txt")
    np.testing.assert_allclose(traj.poses, tum.poses, atol=1e-6)
    assert covs.shape == (100, 6, 6) and (np.linalg.eigvalsh(covs[:, 2:5, 2:5]) > 0).all()
    assert summary["sigma_position_m"]["max"] == pytest.approx(np.sqrt(covs[:, 3:5, 3:5].diagonal(
        axis1=1, axis2=2).max()), abs=1e-4)
    import matplotlib.image as mpimg

    assert_not_blank(mpimg.imread(out / "uncertainty.png"), "uncertainty.png")
    html = report_run(out).read_text()
    assert_not_blank(figure_png(html, "uncertainty-sigma"), "σ along the path")
    assert_layer_has_ink(figure_png(html, "layer-uncertainty"), "pose ellipses")


def test_a_log_of_another_place_is_not_localised(world, tmp_path):
    """A log of the rooms world in the rectangle's map: the command says so (one line, exit 1),
    writes what it found, and does not run a global search on every scan."""
    other = generate("rooms", tmp_path / "rooms", seed=3, laps=1, max_scans=80)
    out = tmp_path / "out"
    r = runner.invoke(app, ["localize", str(other), "--map", str(world["map_run"]), "--out", str(out)])
    assert r.exit_code == 1, r.output
    assert "was not localised in" in r.stderr and "Traceback" not in r.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["localised"] is False and summary["consistent_fraction"] < 0.5
    assert summary["scans"] == 80
    cfg = LocalizationConfig()
    assert summary["global_searches"] <= cfg.global_scans + (80 - cfg.global_scans) // cfg.relocalize_every + 1


def only_line(result, *needles):
    assert result.exit_code == 1, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), result.output
    for n in needles:
        assert n in lines[0], lines[0]


def test_bad_maps_and_poses_give_one_line_errors(world, tmp_path):
    def loc(map_path, *extra):
        return runner.invoke(app, ["localize", str(world["loc_log"]), "--map", str(map_path),
                                   "--out", str(tmp_path / "o"), *extra])

    only_line(loc(tmp_path / "missing.ply"), "missing.ply", "no such file")
    (tmp_path / "run_without_map").mkdir()
    only_line(loc(tmp_path / "run_without_map"), "run_without_map", "no map.ply")
    empty = tmp_path / "empty.ply"
    empty.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                     "property float z\nend_header\n")
    only_line(loc(empty), "empty.ply", "no points")
    text = tmp_path / "notes.ply"
    text.write_text("these are not points\n")
    only_line(loc(text), "notes.ply", "not a PLY point cloud")
    only_line(loc(world["loc_log"] / "groundtruth_tum.txt"), "groundtruth_tum.txt", "not a point cloud")
    only_line(loc(world["map_run"], "--initial-pose", "1 2"), "expected three numbers")
    cfg = tmp_path / "c.yaml"
    cfg.write_text("localization:\n  min_fitness: 1.5\n")
    only_line(loc(world["map_run"], "--config", str(cfg)), "c.yaml", "localization.min_fitness")
    only_line(loc(world["map_run"], "--min-fitness", "-1"), "localize options", "min_fitness")
    assert not (tmp_path / "o").exists()  # nothing written on bad input
    with pytest.raises(InputError, match="no points"):
        load_map(empty)


def test_a_2d_log_in_a_3d_map_is_an_input_error(world, tmp_path):
    rng = np.random.default_rng(0)
    cloud = rng.uniform(-5, 5, size=(500, 3))
    with pytest.raises(InputError, match="2D scan cannot be localised in a 3D map"):
        localize_log(world["scans"][:3], cloud, initial_pose=np.eye(4))


def test_unmapped_part_of_the_world_is_not_a_loss(world):
    """A map of only part of the world (the map's points left of the middle cut away: a third of
    the hallways never mapped), then a lap that drives through the unmapped part and back. Seeing
    unmapped space is not being lost: the fitness over all scan points collapses there, the
    fitness over the mapped area (beams that reach a mapped wall) stays high, the scans are
    registered against the map plus the recent scans, nobody searches globally, and the pose is
    still within centimetres when the robot is back in the mapped part. (The old gate, fitness
    over all points below 0.5 for 5 scans, declared this lost and dead-reckoned.)"""
    points = load_map(world["map_run"])
    truth = world["truth"]
    x0, x1 = truth[:, 0, 3].min(), truth[:, 0, 3].max()
    cut = x0 + 0.35 * (x1 - x0)
    kept = points[points[:, 0] > cut]
    unmapped = truth[:, 0, 3] < cut - 1.0  # scans driven well inside the part the map lacks
    assert unmapped.sum() > 100 and not unmapped[0] and not unmapped[-1]
    res = localize_log(world["scans"], kept, initial_pose=truth[0])
    assert res.fitness[unmapped].min() < 0.3  # most scan points have no map point near them
    assert res.fitness_mapped[~unmapped].min() > LocalizationConfig().min_fitness
    assert not res.lost.any() and res.global_searches == 0
    err = position_errors(res.poses, truth)
    back = np.arange(len(err)) > np.flatnonzero(unmapped).max()
    assert err[unmapped].max() < 0.3 and err[back].max() < 0.06, (err[unmapped].max(), err[back].max())


def body_errors_and_variances(res, truth):
    """``(N, 3)`` error of each pose in its own frame (x, y, yaw) against the truth, and ``(N, 3)``
    the variances the result reports for them."""
    from submapslam.geometry import inverse

    e = np.array([matrix_to_se2(inverse(P) @ G) for P, G in zip(res.poses, truth)])
    C = res.covariances
    return e, np.stack([C[:, 3, 3], C[:, 4, 4], C[:, 2, 2]], axis=1)


def test_reported_sigma_matches_the_error_against_the_truth(world):
    """Each pose's covariance against its error in its own frame: per axis the mean (e/σ)² within a
    generous band around 1 (measured on this, the fit world: x 1.29, y 0.46, yaw 0.39) and at least
    90 % of the poses inside the 95 % χ²(1) bound; positive definite, roll/pitch/z pinned."""
    res = localize_log(world["scans"], world["map_run"], initial_pose=world["truth"][0])
    C = res.covariances
    assert C.shape == (res.n_scans, 6, 6) and np.allclose(C, np.transpose(C, (0, 2, 1)))
    assert (np.linalg.eigvalsh(C[:, 2:5, 2:5]) > 0).all() and C[:, [0, 1, 5], [0, 1, 5]].max() < 1e-8
    e, var = body_errors_and_variances(res, world["truth"])
    z = e**2 / var
    assert ((z.mean(axis=0) > 0.2) & (z.mean(axis=0) < 3.0)).all(), z.mean(axis=0)
    assert (np.mean(z <= 3.84, axis=0) >= 0.9).all(), np.mean(z <= 3.84, axis=0)
    s = res.summary()
    assert s["sigma_position_m"]["max"] == pytest.approx(np.sqrt(var[:, :2].max()), abs=1e-4)


def test_sigma_grows_where_the_map_gives_no_constraint(world):
    """The map cut as in the unmapped-part test: where the robot drives through the part the map
    lacks, the pose rests on the motion model and σ grows (median over 2.5x the mapped part's),
    still covering the error there; back in the mapped part it falls again."""
    points = load_map(world["map_run"])
    truth = world["truth"]
    x0, x1 = truth[:, 0, 3].min(), truth[:, 0, 3].max()
    cut = x0 + 0.35 * (x1 - x0)
    unmapped = truth[:, 0, 3] < cut - 1.0
    res = localize_log(world["scans"], points[points[:, 0] > cut], initial_pose=truth[0])
    e, var = body_errors_and_variances(res, truth)
    sig = np.sqrt(var)
    assert (np.median(sig[unmapped], axis=0) > 2.5 * np.median(sig[~unmapped], axis=0)).all()
    z = e[unmapped] ** 2 / var[unmapped]
    assert (z.mean(axis=0) < 3.0).all() and (np.mean(z <= 3.84, axis=0) >= 0.9).all(), z.mean(axis=0)
    back = np.arange(len(sig)) > np.flatnonzero(unmapped).max() + 20
    assert np.median(sig[back, 0]) < 0.5 * np.median(sig[unmapped, 0])
