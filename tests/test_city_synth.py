"""The city along a KITTI path (datasets_synth.city) and the aliased two-block world."""

from collections import Counter

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from datasets_synth import generate, generate_kitti_drive
from datasets_synth.city import kitti_city, read_kitti_path
from datasets_synth.motion import open_path
from datasets_synth.sensors import Lidar3D, RayCaster
from datasets_synth.streets import StreetStyle
from datasets_synth.worlds import (
    ALIASED_BLOCK_LENGTH,
    aliased,
    aliased_offset,
    box_footprint,
    densify,
)
from submapslam.cli import app
from submapslam.errors import InputError, SubmapSlamError
from submapslam.geometry import matrix_to_se2
from submapslam.io.cloud_folder import read_cloud
from submapslam.io.trajectory import read_kitti, read_tum

from .conftest import shared_data
from .test_cli import one_line_error

ROAD = StreetStyle().road_half_width


def kitti_path(seq: str = "00"):
    return shared_data("trajectories", "kitti_gt", f"{seq}.txt.xz")


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    path = kitti_path()
    root = tmp_path_factory.mktemp("kitti")
    a = generate_kitti_drive(path, root / "a", rings=16, seed=3, max_scans=30)
    b = generate_kitti_drive(path, root / "b", rings=16, seed=3, max_scans=30)
    c = generate_kitti_drive(path, root / "c", rings=16, seed=4, max_scans=30)
    return path, a, b, c


@pytest.fixture(scope="module")
def city00():
    return kitti_city(read_kitti_path(kitti_path()), seed=0)


def test_kitti_drive_is_deterministic_and_seed_dependent(drive):
    _, a, b, c = drive
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert len([f for f in files if f.parts[0] == "scans"]) == 30
    for name in files:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    assert (a / "scans/000010.ply").read_bytes() != (c / "scans/000010.ply").read_bytes()
    pts, t = read_cloud(a / "scans" / "000010.ply")
    assert len(pts) > 8000 and t is not None and 0.0 <= t.min() and t.max() <= 1.0
    assert np.linalg.norm(pts, axis=1).max() < 100.0


def test_kitti_ground_truth_is_the_planar_kitti_path(drive):
    path, a, _, _ = drive
    meta = yaml.safe_load((a / "meta.yaml").read_text())
    kitti = read_kitti(path).poses[:30]
    gt = read_tum(a / "groundtruth_tum.txt")
    assert len(gt) == 30 and meta["n_scans"] == 30 and not meta["planar"]
    np.testing.assert_allclose(np.diff(gt.timestamps), 0.1, atol=1e-6)
    # world x = camera z (forward), world y = -camera x (left), at the Velodyne's mount height
    np.testing.assert_allclose(gt.positions[:, 0], kitti[:, 2, 3], atol=1e-6)
    np.testing.assert_allclose(gt.positions[:, 1], -kitti[:, 0, 3], atol=1e-6)
    np.testing.assert_allclose(gt.positions[:, 2], 1.73, atol=1e-9)
    # heading: the camera's forward axis in the plane; it follows the direction of travel
    yaw = matrix_to_se2(gt.poses)[:, 2]
    forward = np.arctan2(-kitti[:, 0, 2], kitti[:, 2, 2])
    np.testing.assert_allclose(np.angle(np.exp(1j * (yaw - forward))), 0.0, atol=1e-6)
    step = np.diff(gt.positions[:, :2], axis=0)
    travel = np.arctan2(step[:, 1], step[:, 0])
    assert np.median(np.abs(np.angle(np.exp(1j * (yaw[1:] - travel))))) < np.deg2rad(3.0)
    planar = float(np.linalg.norm(np.diff(kitti[:, [0, 2], 3], axis=0), axis=1).sum())
    assert meta["path_length_m"] == pytest.approx(planar, abs=1e-3) and meta["loop_length_m"] == meta["path_length_m"]
    assert planar == pytest.approx(gt.path_length(), rel=1e-6) and planar > 10.0
    assert meta["source_path"] == "00.txt.xz" and meta["sensor"]["rings"] == 16
    np.testing.assert_allclose(read_kitti(a / "groundtruth_kitti.txt").poses, gt.poses, atol=1e-6)


def test_full_path_conversion_keeps_length_and_start():
    xyt = read_kitti_path(kitti_path())
    assert len(xyt) == 4541
    np.testing.assert_allclose(xyt[0], 0.0, atol=1e-9)
    length = float(np.linalg.norm(np.diff(xyt[:, :2], axis=0), axis=1).sum())
    assert 3600.0 < length < 3750.0  # ~3.7 km (the dropped elevation changes it by < 1%)


def test_no_obstacle_inside_the_road_corridor(city00):
    from scipy.spatial import cKDTree

    tree = cKDTree(densify(city00.waypoints, 0.25))
    outlines = np.vstack([densify(np.vstack([f, f[:1]]), 0.25)
                          for f in (box_footprint(b) for b in city00.oriented_boxes)])
    assert tree.query(outlines)[0].min() >= ROAD - 0.15
    x, y, r, _ = city00.cylinders.T
    assert (tree.query(np.stack([x, y], 1))[0] - r).min() >= ROAD - 0.15
    counts = Counter(city00.box_labels)
    assert counts["building"] > 150 and counts["car"] > 150 and len(city00.cylinders) > 200


def test_horizontal_rays_from_the_road_hit_nothing_closer_than_the_kerb():
    xyt = read_kitti_path(kitti_path())[:500]
    world = kitti_city(xyt, seed=1)
    caster = RayCaster(world.mesh())
    az = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    dirs = np.stack([np.cos(az), np.sin(az), np.zeros_like(az)], axis=1)
    nearest = np.inf
    hits = 0
    for x, y, _ in xyt[::5]:
        T = np.eye(4)
        T[:3, 3] = (x, y, 0.6)  # above the rough ground, at car-body height
        r = caster.ranges(T, dirs)
        hits += np.isfinite(r).sum()
        nearest = min(nearest, r.min())
    assert hits > 10000  # the street is lined with things
    assert nearest >= ROAD - 0.2


def test_buildings_repeat_from_a_small_catalogue(city00):
    b = city00.oriented_boxes[city00.box_labels == "building"]
    sizes = Counter(map(tuple, np.round(b[:, [3, 4, 6]], 3)))  # length, depth, height
    assert len(sizes) <= 5 and max(sizes.values()) >= 20
    unique = kitti_city(read_kitti_path(kitti_path())[:800], seed=0, repeated_buildings=False)
    ub = unique.oriented_boxes[unique.box_labels == "building"]
    assert len(ub) > 20 and len(set(map(tuple, np.round(ub[:, [3, 4, 6]], 3)))) == len(ub)


def test_aliased_world_has_two_identical_blocks_far_apart():
    w = aliased()
    offset = aliased_offset()
    assert np.linalg.norm(offset) > 90.0
    L = ALIASED_BLOCK_LENGTH

    def block(origin):
        local_boxes = w.oriented_boxes.copy()
        local_boxes[:, :2] -= origin
        inside = (local_boxes[:, 0] > -2) & (local_boxes[:, 0] < L + 2) & (np.abs(local_boxes[:, 1]) < 40)
        local_cyl = w.cylinders.copy()
        local_cyl[:, :2] -= origin
        cin = (local_cyl[:, 0] > -2) & (local_cyl[:, 0] < L + 2) & (np.abs(local_cyl[:, 1]) < 40)
        return local_boxes[inside], w.box_labels[inside], local_cyl[cin]

    (ba, la, ca), (bb, lb, cb) = block(np.zeros(2)), block(offset)
    assert (la == "building").sum() >= 4 and (la == "car").sum() >= 6 and len(ca) >= 3
    np.testing.assert_allclose(ba, bb, atol=1e-9)
    assert list(la) == list(lb)
    np.testing.assert_allclose(ca, cb, atol=1e-9)
    # the connecting street's buildings are all different from the blocks' and from each other
    sizes = np.round(w.oriented_boxes[w.box_labels == "building"][:, [3, 4, 6]], 3)
    assert len(set(map(tuple, sizes))) == len(sizes) - (la == "building").sum()
    # the same views: upper rings from corresponding poses see the same block to the millimetre
    caster = RayCaster(w.mesh())
    lidar = Lidar3D(rings=8, fov_down_deg=1.0, fov_up_deg=15.0, columns=720)
    dirs, _ = lidar.directions()
    for x in (10.0, 22.0, 30.0):
        Ta, Tb = np.eye(4), np.eye(4)
        Ta[:3, 3] = (x, 0.0, 1.73)
        Tb[:3, 3] = (x + offset[0], offset[1], 1.73)
        ra, rb = caster.ranges(Ta, dirs), caster.ranges(Tb, dirs)
        hit = dirs * np.where(np.isfinite(ra), ra, 0.0)[:, None] + Ta[:3, 3]
        in_block = np.isfinite(ra) & (hit[:, 0] > 1.0) & (hit[:, 0] < L - 1.0) & (np.abs(hit[:, 1]) < 35)
        assert in_block.sum() > 300
        np.testing.assert_allclose(ra[in_block], rb[in_block], atol=1e-3)


def test_aliased_path_drives_a_then_b_and_never_returns():
    w = aliased()
    offset = aliased_offset()
    p = open_path(w.waypoints, 0.8, w.corner_radius)
    assert 130 <= len(p) <= 160
    in_a = (p[:, 0] <= ALIASED_BLOCK_LENGTH) & (np.abs(p[:, 1]) < 1.0)
    in_b = p[:, 0] >= offset[0]
    ia, ib = np.flatnonzero(in_a), np.flatnonzero(in_b)
    assert len(ia) >= 40 and len(ib) >= 35 and ia.max() < ib.min()
    assert np.all(np.diff(p[:, 0]) > 0)  # always onwards: never back towards A
    # and the whole path keeps the road corridor clear
    from scipy.spatial import cKDTree

    tree = cKDTree(densify(p[:, :2], 0.25))
    outlines = np.vstack([box_footprint(b) for b in w.oriented_boxes])
    assert tree.query(outlines)[0].min() >= ROAD - 0.15


def test_generate_aliased_writes_an_open_path_log(tmp_path):
    out = generate("aliased", tmp_path / "al", laps=1, max_scans=6,
                   sensor_options={"rings": 16, "fov_up_deg": 15.0, "fov_down_deg": -15.0, "columns": 900})
    meta = yaml.safe_load((out / "meta.yaml").read_text())
    assert meta["world"] == "aliased" and meta["laps"] == 1 and meta["n_scans"] == 6
    assert meta["loop_length_m"] == pytest.approx(122.0, abs=0.5)
    gt = read_tum(out / "groundtruth_tum.txt")
    np.testing.assert_allclose(gt.positions[0], (6.0, 0.0, 1.7), atol=1e-6)


def test_kitti_bad_input_raises_clear_errors(tmp_path):
    with pytest.raises(InputError, match="no such KITTI pose file"):
        read_kitti_path(tmp_path / "missing.txt")
    bad = tmp_path / "bad.txt"
    bad.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match="bad.txt:2"):
        read_kitti_path(bad)
    bad.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 1 0 2 0 0 0 0 2 0\n")
    with pytest.raises(InputError, match="bad.txt:2: the 3x3 part is not a rotation"):
        read_kitti_path(bad)
    with pytest.raises(SubmapSlamError, match="rings must be 16, 64, 128 or livox, not 32"):
        generate_kitti_drive(bad, tmp_path / "o", rings=32)


runner = CliRunner()


def test_cli_synth_kitti(tmp_path):
    path = kitti_path()
    r = runner.invoke(app, ["synth", "kitti", "--path", str(path), "--rings", "16", "--out", str(tmp_path / "k"),
                            "--max-scans", "5", "--seed", "2"])
    assert r.exit_code == 0, r.output
    assert "5 scans along 00.txt.xz (16-ring LiDAR)" in r.output
    assert len(list((tmp_path / "k" / "scans").glob("*.ply"))) == 5


def test_cli_synth_kitti_bad_input_is_one_line(tmp_path):
    out = ["--out", str(tmp_path / "o")]
    one_line_error(runner.invoke(app, ["synth", "kitti", "--path", str(tmp_path / "none.txt.xz"), *out]),
                   "none.txt.xz", "no such KITTI pose file")
    bad = tmp_path / "bad.txt"
    bad.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 x 0 1 0 0 0 0 1 0\n")
    one_line_error(runner.invoke(app, ["synth", "kitti", "--path", str(bad), *out]), "bad.txt:2", "non-numeric")
    one_line_error(runner.invoke(app, ["synth", "kitti", "--path", str(bad), "--rings", "32", *out]),
                   "--rings must be 16, 64 or 128, not 32")
    one_line_error(runner.invoke(app, ["synth", "kitti", *out]), "needs --path")
    one_line_error(runner.invoke(app, ["synth", "kitti", "--path", str(bad), "--laps", "2", *out]),
                   "--laps not used by synth kitti")
    one_line_error(runner.invoke(app, ["synth", "rectangle", "--path", str(bad), *out]),
                   "--path is for the kitti world")
