"""Terrain, more sensors and irregular keyframes in the city along a KITTI path (datasets_synth)."""

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from datasets_synth import generate_kitti_drive
from datasets_synth.city import kitti_city, read_kitti_height, read_kitti_path
from datasets_synth.sensors import Lidar3D, LivoxLike, RayCaster
from datasets_synth.terrain import PathTerrain, keyframe_schedule, terrain_poses
from submapslam.cli import app
from submapslam.geometry import se2_array_to_matrices
from submapslam.io.cloud_folder import read_cloud
from submapslam.io.trajectory import read_tum

from .conftest import shared_data


def kitti_path(seq: str = "00"):
    return shared_data("trajectories", "kitti_gt", f"{seq}.txt.xz")


@pytest.fixture(scope="module")
def terrain_drive(tmp_path_factory):
    root = tmp_path_factory.mktemp("terrain")
    return generate_kitti_drive(kitti_path(), root / "t", rings=16, seed=1, max_scans=40, terrain=True)


def test_path_terrain_follows_a_ramp_and_is_smooth_off_the_path():
    s = np.arange(0.0, 400.0, 1.0)
    z = np.where(s < 200, 0.0, 0.05 * (s - 200))  # flat, then a 5 % climb
    terrain = PathTerrain(np.column_stack([s, np.zeros_like(s), z]))
    on = terrain.height(np.column_stack([s, np.zeros_like(s)]))
    assert np.abs(on[s < 170]).max() < 0.01 and np.abs(on[(s > 240) & (s < 350)] - z[(s > 240) & (s < 350)]).max() < 0.05
    off = terrain.height(np.column_stack([s, np.full_like(s, 30.0)]))  # 30 m beside the road: the road's height
    np.testing.assert_allclose(off, on, atol=0.05)
    normals = terrain.normal(np.array([[100.0, 0.0], [300.0, 0.0]]))
    assert normals[0] == pytest.approx([0, 0, 1], abs=1e-3)
    assert np.degrees(np.arctan2(-normals[1, 0], normals[1, 2])) == pytest.approx(np.degrees(np.arctan(0.05)), abs=0.1)
    # a vehicle on the ramp pitches nose up, keeps its heading and rides mount height above the ground
    T = terrain_poses(np.array([[300.0, 0.0, 0.0], [100.0, 0.0, np.pi / 2]]), terrain, 1.73)
    assert np.degrees(np.arcsin(T[0, 2, 0])) == pytest.approx(np.degrees(np.arctan(0.05)), abs=0.1)
    assert T[0, 2, 3] == pytest.approx(terrain.height(np.array([[300.0, 0.0]]))[0] + 1.73 * normals[1, 2], abs=1e-3)
    np.testing.assert_allclose(T[1, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-3)


def test_terrain_drive_follows_the_kitti_height(terrain_drive):
    meta = yaml.safe_load((terrain_drive / "meta.yaml").read_text())
    gt = read_tum(terrain_drive / "groundtruth_tum.txt")
    height = read_kitti_height(kitti_path())[:40]
    up = gt.poses[:, :3, 2]
    ground = gt.positions - 1.73 * up
    # the vehicle rides on the KITTI path's (smoothed) height, pitched with the road
    assert np.abs(ground[:, 2] - height).max() < 0.6
    assert np.ptp(ground[:, 2]) > 0.5 and meta["terrain"]["relief_m"] > 0.5
    assert np.degrees(np.arccos(up[:, 2])).max() > 0.5
    # seen from the sensor, the ground straight below is 1.73 m away along -z: the pose is on the surface
    world = kitti_city(read_kitti_path(kitti_path())[:40], seed=1,
                       terrain=PathTerrain(np.column_stack([read_kitti_path(kitti_path())[:, :2],
                                                            read_kitti_height(kitti_path())])))
    caster = RayCaster(world.mesh())
    down = caster.ranges(gt.poses[0], np.array([[0.0, 0.0, -1.0], [0.2, 0.0, -1.0] / np.hypot(0.2, 1.0)]))
    assert down[0] == pytest.approx(1.73, abs=0.2)
    pts, _ = read_cloud(terrain_drive / "scans" / "000020.ply")
    near = pts[np.hypot(pts[:, 0], pts[:, 1]) < 10.0]
    assert np.median(near[near[:, 2] < -1.0, 2]) == pytest.approx(-1.73, abs=0.15)


def test_terrain_objects_stand_on_the_ground():
    xyt = read_kitti_path(kitti_path())[:300]
    terrain = PathTerrain(np.column_stack([xyt[:, :2], 3.0 + 0.05 * np.arange(300)]))  # a steady climb
    world = kitti_city(xyt, seed=2, terrain=terrain)
    flat = kitti_city(xyt, seed=2)
    boxes, flat_boxes = world.grounded_boxes(), flat.grounded_boxes()
    np.testing.assert_array_equal(flat_boxes, flat.oriented_boxes)  # no terrain: unchanged
    np.testing.assert_array_equal(boxes[:, :5], flat_boxes[:, :5])
    centre = terrain.height(boxes[:, :2])
    building = world.box_labels == "building"
    assert building.sum() > 3 and (world.box_labels == "car").sum() > 3
    assert np.all(boxes[building, 5] < centre[building] - 0.4)  # sunk in: no gap under the downhill side
    np.testing.assert_allclose(boxes[building, 6], flat_boxes[building, 6] + centre[building])
    np.testing.assert_allclose(boxes[~building, 5], flat_boxes[~building, 5] + centre[~building])
    # a ray cast down from 50 m over a car's centre lands on its roof, at the roof's height over the local ground
    car = int(np.flatnonzero(world.box_labels == "car")[0])
    T = np.eye(4)
    T[:3, 3] = [boxes[car, 0], boxes[car, 1], 50.0]
    hit = 50.0 - RayCaster(world.mesh()).ranges(T, np.array([[0.0, 0.0, -1.0]]))[0]
    assert hit == pytest.approx(boxes[car, 6], abs=0.01)


def test_more_sensors_128_rings_and_livox(tmp_path):
    dev = Lidar3D.preset(128)
    d, t = dev.directions()
    assert len(d) == 128 * 1024 and np.degrees(np.arcsin(d[:, 2])).max() == pytest.approx(22.5)
    livox = LivoxLike()
    d0, t0 = livox.directions_at(0)
    d1, _ = livox.directions_at(1)
    az, el = np.degrees(np.arctan2(d0[:, 1], d0[:, 0])), np.degrees(np.arcsin(d0[:, 2]))
    assert np.abs(az).max() <= 35.3 and np.abs(az).max() > 33 and np.abs(el).max() <= 38.7
    assert np.all(d0[:, 0] > 0) and 0.0 <= t0.min() and t0.max() < 1.0
    # non-repetitive: the next scan looks in other directions, and together they cover more
    assert np.median(np.linalg.norm(d1 - d0, axis=1)) > 0.01
    def cells(d: np.ndarray) -> set:  # 0.2 x 0.2 deg pixels the rays fall in
        angles = np.column_stack([np.arctan2(d[:, 1], d[:, 0]), np.arcsin(d[:, 2])])
        return {tuple(c) for c in np.floor(np.degrees(angles) / 0.2).astype(int)}

    many = np.vstack([livox.directions_at(k)[0] for k in range(10)])
    assert len(cells(many)) > 3 * len(cells(d0))
    out = generate_kitti_drive(kitti_path(), tmp_path / "l", rings="livox", seed=0, max_scans=3)
    meta = yaml.safe_load((out / "meta.yaml").read_text())
    assert meta["sensor"]["type"] == "livox" and meta["sensor"]["fov_h_deg"] == pytest.approx(70.4)
    a, _ = read_cloud(out / "scans" / "000000.ply")
    b, _ = read_cloud(out / "scans" / "000001.ply")
    assert len(a) > 5000 and np.all(a[:, 0] > 0) and not np.array_equal(a[:100], b[:100])
    out = generate_kitti_drive(kitti_path(), tmp_path / "r", rings=128, seed=0, max_scans=2)
    pts, _ = read_cloud(out / "scans" / "000000.ply")
    assert len(pts) > 40000


def test_keyframe_schedule_has_gaps_and_still_stretches():
    index, times = keyframe_schedule(3000, 10.0, np.random.default_rng(0))
    gaps = np.diff(times)
    assert index[0] == 0 and index[-1] == 2999 and np.all(np.diff(index) >= 0) and np.all(gaps > 0)
    assert 0.2 <= np.median(gaps) <= 0.5
    assert gaps.max() >= 3.0 and (gaps > 2.0).sum() >= 3  # stops of seconds
    still = np.diff(index) == 0
    assert still.sum() >= 3 and np.all(gaps[~still] <= 0.5 + 1e-9)


def test_keyframes_log(tmp_path):
    kf = generate_kitti_drive(kitti_path(), tmp_path / "k", rings=16, seed=6, max_scans=200,
                              keyframes=True)  # seed 6: a stop of 9 s in the first 200 poses
    full = se2_array_to_matrices(read_kitti_path(kitti_path())[:200])
    full[:, 2, 3] = 1.73
    gt = read_tum(kf / "groundtruth_tum.txt")
    times = np.loadtxt(kf / "times.txt")
    assert len(gt) == len(times) == len(list((kf / "scans").glob("*.ply"))) < 100
    np.testing.assert_allclose(gt.timestamps, times, atol=1e-6)
    assert np.diff(times).max() > 5.0 and np.median(np.diff(times)) < 0.6
    # every keyframe is one of the drive's 10 Hz poses; the odometry stands still where the truth does
    d = np.linalg.norm(gt.positions[:, None] - full[None, :, :3, 3], axis=2).min(axis=1)
    assert d.max() < 1e-4
    odom = read_tum(kf / "odometry_tum.txt")
    still = np.linalg.norm(np.diff(gt.positions, axis=0), axis=1) < 1e-9
    assert still.any() and np.abs(np.diff(odom.positions, axis=0)[still]).max() < 1e-9
    meta = yaml.safe_load((kf / "meta.yaml").read_text())
    assert meta["keyframes"]["max_gap_s"] > 5.0 and meta["keyframes"]["still_scans"] == int(still.sum())


def test_cli_synth_kitti_terrain_and_livox(tmp_path):
    runner = CliRunner()
    r = runner.invoke(app, ["synth", "kitti", "--path", str(kitti_path()), "--terrain", "--keyframes",
                            "--sensor", "livox", "--max-scans", "30", "--out", str(tmp_path / "k")])
    assert r.exit_code == 0, r.output
    assert "Livox-like LiDAR, terrain relief" in r.output
    meta = yaml.safe_load((tmp_path / "k" / "meta.yaml").read_text())
    assert meta["sensor"]["type"] == "livox" and "terrain" in meta and "keyframes" in meta
    r = runner.invoke(app, ["synth", "rectangle", "--terrain", "--out", str(tmp_path / "r")])
    assert r.exit_code == 1 and "for the kitti world" in r.output


def test_movers_on_terrain_stand_on_the_ground(tmp_path):
    """Cars and pedestrians on a drive with terrain keep their height over the local ground, also
    where the road has climbed metres (KITTI 08: 16 m in its first 120 poses). Fails when movers
    are placed as on flat ground: buried where the road is high, floating where it is low."""
    from submapslam.io.labels import labelled_scans

    out = generate_kitti_drive(kitti_path("08"), tmp_path / "m", rings=16, seed=2, max_scans=120, terrain=True,
                               movers=40)
    path = read_kitti_path(kitti_path("08"))
    ground = PathTerrain(np.column_stack([path[:, :2], read_kitti_height(kitti_path("08"))]))
    truth = read_tum(out / "groundtruth_tum.txt")
    heights, grounds = [], []
    for k, points, labels, _ in labelled_scans(out):
        mover = (labels & 0xFFFF) >= 252
        if k % 4 or not mover.any():
            continue
        world = points[mover] @ truth.poses[k][:3, :3].T + truth.poses[k][:3, 3]
        grounds.append(ground.height(world[:, :2]))
        heights.append(world[:, 2] - grounds[-1])
    assert heights, "no mover seen: buried under the terrain?"
    heights, grounds = np.concatenate(heights), np.concatenate(grounds)
    assert len(heights) > 500 and (np.abs(grounds) > 2.0).sum() > 100, (len(heights), np.percentile(grounds, [1, 99]))
    assert np.percentile(heights, 1) > -0.2 and np.percentile(heights, 99) < 2.0, np.percentile(heights, [1, 50, 99])
