import numpy as np
import pytest
import yaml

from datasets_synth import WORLDS, generate
from datasets_synth.motion import OdometryNoise, loop_path, wheel_odometry
from datasets_synth.sensors import Laser2D, RayCaster, measure
from datasets_synth.worlds import rectangle, rooms
from submapslam.errors import SubmapSlamError
from submapslam.geometry import inverse, se2_to_matrix
from submapslam.io.cloud_folder import read_cloud
from submapslam.io.registry import open_log
from submapslam.io.trajectory import read_kitti, read_tum


def box_mesh(half=5.0):
    from submapslam._deps import open3d

    o3d = open3d()
    box = o3d.geometry.TriangleMesh.create_box(2 * half, 2 * half, 3.0)
    box.translate((-half, -half, -1.0))
    return box


def test_ray_caster_matches_analytic_box_distances():
    caster = RayCaster(box_mesh(5.0))
    laser = Laser2D(beams=4, fov_deg=360.0)
    T = se2_to_matrix(1.0, -2.0, 0.0)
    T[2, 3] = 0.5
    r = caster.ranges(T, laser.directions())  # beams at -180, -90, 0, 90 deg
    np.testing.assert_allclose(r, [6.0, 3.0, 4.0, 7.0], atol=1e-4)
    # rotated sensor: beam 0 deg now points along +y
    T2 = se2_to_matrix(1.0, -2.0, np.pi / 2)
    T2[2, 3] = 0.5
    np.testing.assert_allclose(caster.ranges(T2, laser.directions())[2], 7.0, atol=1e-4)


def test_measure_applies_max_range_noise_and_dropouts():
    rng = np.random.default_rng(0)
    ranges = np.array([1.0] * 10000 + [np.inf] * 10 + [50.0] * 10)
    noisy, valid = measure(ranges, 30.0, 0.0, 0.1, rng)
    assert not valid[10000:].any()
    assert 0.08 < 1 - valid[:10000].mean() < 0.12
    noisy, valid = measure(ranges[:10000], 30.0, 0.02, 0.0, rng)
    assert abs(np.std(noisy - 1.0) - 0.02) < 0.002


def test_worlds_are_deterministic_and_seed_dependent():
    a, b, c = rectangle(seed=3), rectangle(seed=3), rectangle(seed=4)
    np.testing.assert_array_equal(a.segments, b.segments)
    assert a.segments.shape != c.segments.shape or not np.allclose(a.segments, c.segments)
    assert set(WORLDS) >= {"rectangle", "rooms", "figure8", "outdoor"}


def test_loop_path_closes_and_odometry_drifts_with_noise():
    path = loop_path(rectangle().waypoints, laps=2, step=0.1)
    assert np.linalg.norm(path[0, :2] - path[-1, :2]) < 0.2
    rng = np.random.default_rng(0)
    T = se2_to_matrix(*path[0])
    truth_rel = inverse(T) @ se2_to_matrix(*path[-1])
    perfect = wheel_odometry(path, OdometryNoise().scaled(0.0), rng)
    np.testing.assert_allclose(perfect[-1][:2, 3], truth_rel[:2, 3], atol=1e-6)
    small = wheel_odometry(path, OdometryNoise().scaled(0.5), np.random.default_rng(1))
    large = wheel_odometry(path, OdometryNoise().scaled(2.0), np.random.default_rng(1))
    e_small = np.linalg.norm(small[-1][:2, 3] - truth_rel[:2, 3])
    e_large = np.linalg.norm(large[-1][:2, 3] - truth_rel[:2, 3])
    assert 0 < e_small < e_large


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "rect"
    return generate("rectangle", out, seed=1, laps=1, max_scans=60)


def test_written_log_round_trips(small_log):
    meta = yaml.safe_load((small_log / "meta.yaml").read_text())
    assert meta["planar"] and meta["n_scans"] == 60
    gt_tum = read_tum(small_log / "groundtruth_tum.txt")
    gt_kitti = read_kitti(small_log / "groundtruth_kitti.txt")
    assert len(gt_tum) == 60
    np.testing.assert_allclose(gt_tum.poses, gt_kitti.poses, atol=1e-6)
    times = np.loadtxt(small_log / "times.txt")
    np.testing.assert_allclose(gt_tum.timestamps, times)
    pts, t = read_cloud(small_log / "scans" / "000010.ply")
    assert pts.shape[1] == 3 and len(pts) > 100 and t is not None and len(t) == len(pts)
    assert np.allclose(pts[:, 2], 0.0) and np.all(np.linalg.norm(pts, axis=1) < 30.0)
    scans = list(open_log(small_log))
    assert len(scans) == 60 and scans[0].planar and scans[0].odometry is not None


def test_carmen_copy_matches_the_folder(small_log):
    folder = list(open_log(small_log))
    carmen = list(open_log(small_log / "log.clf"))
    assert len(carmen) == len(folder)
    for a, b in zip(carmen[::15], folder[::15]):
        assert a.timestamp == pytest.approx(b.timestamp, abs=1e-6)
        np.testing.assert_allclose(a.odometry[:2, 3], b.odometry[:2, 3], atol=1e-5)
        # the same returns (CARMEN writes max range for no return, which the reader drops)
        assert abs(len(a.points) - len(b.points)) <= 2


def test_same_seed_same_bytes(tmp_path):
    a = generate("rectangle", tmp_path / "a", seed=5, laps=1, max_scans=5)
    b = generate("rectangle", tmp_path / "b", seed=5, laps=1, max_scans=5)
    c = generate("rectangle", tmp_path / "c", seed=6, laps=1, max_scans=5)
    for name in ("scans/000003.ply", "odometry_tum.txt", "log.clf"):
        assert (a / name).read_bytes() == (b / name).read_bytes()
    assert (a / "odometry_tum.txt").read_bytes() != (c / "odometry_tum.txt").read_bytes()


def test_rooms_world_repeats_identical_places():
    w = rooms()
    caster = RayCaster(w.mesh())
    laser = Laser2D(fov_deg=360.0, beams=360)
    # two places one room period (6 m) apart along the bottom hallway look the same
    T1, T2 = se2_to_matrix(10.5, 1.5, 0.0), se2_to_matrix(16.5, 1.5, 0.0)
    T1[2, 3] = T2[2, 3] = 0.3
    r1, r2 = caster.ranges(T1, laser.directions()), caster.ranges(T2, laser.directions())
    close = np.isfinite(r1) & np.isfinite(r2) & (r1 < 4) & (r2 < 4)
    assert close.sum() > 100
    np.testing.assert_allclose(r1[close], r2[close], atol=1e-3)


def test_unknown_world_and_sensor():
    with pytest.raises(SubmapSlamError, match="unknown world 'mars'"):
        generate("mars", "/tmp/never")
    with pytest.raises(SubmapSlamError, match="unknown sensor"):
        generate("rectangle", "/tmp/never", sensor="sonar")


def test_doors_are_deterministic_occlude_when_closed_and_are_labelled(tmp_path):
    from datasets_synth.movers import MOVING_OTHER, MoverCaster, door_tracks

    w = rooms()
    assert len(w.doorways) == 20  # one per room, on the hallway wall line
    a = door_tracks(w.doorways, 600, 10.0, 6, np.random.default_rng([4, 6007]))
    b = door_tracks(w.doorways, 600, 10.0, 6, np.random.default_rng([4, 6007]))
    c = door_tracks(w.doorways, 600, 10.0, 6, np.random.default_rng([5, 6007]))
    np.testing.assert_array_equal(a.present, b.present)
    np.testing.assert_array_equal(a.poses, b.poses)
    assert not np.array_equal(a.present, c.present) or not np.array_equal(a.poses, c.poses)
    assert set(a.kinds) == {"door"} and set(a.classes) == {MOVING_OTHER}  # 60 s: every door opens and closes
    # a door seen straight on from the hallway: closed, the ray stops in the doorway; open, it
    # goes on into the room behind (3 m deep)
    d = 0
    mid = a.poses[d, 0, :2]
    u = np.array([np.cos(a.poses[d, 0, 2]), np.sin(a.poses[d, 0, 2])])
    inward = np.array([-u[1], u[0]])  # into the hallway: towards the world's centre
    inward *= np.sign(inward @ (np.array([w.extent[2], w.extent[3]]) / 2 - mid))
    T = se2_to_matrix(*(mid + 1.5 * inward), np.arctan2(-inward[1], -inward[0]))
    T[2, 3] = 0.3
    forward = np.array([[1.0, 0.0, 0.0]])
    walls = RayCaster(w.mesh()).ranges(T, forward)[0]
    caster = MoverCaster(a, 30.0)
    k_closed, k_open = int(np.argmax(a.present[d])), int(np.argmin(a.present[d]))
    t_closed, cls_closed = caster.cast(k_closed, T, forward)
    t_open, cls_open = caster.cast(k_open, T, forward)
    assert t_closed[0] == pytest.approx(1.5 - 0.02, abs=1e-3) and cls_closed[0] == MOVING_OTHER
    assert np.isinf(t_open[0]) and cls_open[0] == 0 and walls == pytest.approx(4.5, abs=1e-3)
    # the written log: labels 259 only on the doorways' lines, and only while that door is closed
    log = generate("rooms", tmp_path / "doors", seed=4, laps=1, max_scans=150, doors=20)
    assert yaml.safe_load((log / "meta.yaml").read_text())["movers"] == {"door": 20}
    gt = read_tum(log / "groundtruth_tum.txt").poses
    doors = door_tracks(w.doorways, 150, 10.0, 20, np.random.default_rng([4, 6007]))
    on_doors = 0
    from submapslam.io.labels import labelled_scans

    for k, pts, labels, _ in labelled_scans(log):
        xy = pts[:, :2] @ gt[k][:2, :2].T + gt[k][:2, 3]
        door_hits = xy[(labels & 0xFFFF) == MOVING_OTHER]
        on_doors += len(door_hits)
        closed = doors.present[:, k]
        for p in door_hits:
            dist = np.linalg.norm(doors.poses[closed, k, :2] - p, axis=1)
            assert dist.size and dist.min() < 0.58  # on a closed door's leaf (0.5 m half width, range noise)
        assert not np.any((labels & 0xFFFF) == 254)
    assert on_doors > 100
    plain = generate("rooms", tmp_path / "plain", seed=4, laps=1, max_scans=150)
    assert (plain / "odometry_tum.txt").read_bytes() == (log / "odometry_tum.txt").read_bytes()  # same drive
    with pytest.raises(SubmapSlamError, match="no doorways"):
        generate("rectangle", tmp_path / "r", max_scans=5, doors=2)
    with pytest.raises(SubmapSlamError, match="21 doors asked for"):
        generate("rooms", tmp_path / "r2", max_scans=5, doors=21)
