"""Worlds with movers and their labels; ``clean``'s free-space evidence, its parts and its command."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from datasets_synth import generate_kitti_drive
from submapslam.api import clean_log, evaluate_map_file
from submapslam.cli import app
from submapslam.io.labels import labelled_scans
from submapslam.io.ply import write_ply
from submapslam.mapping.dynamic_removal import (
    RangeImage,
    RemovalParams,
    VoxelAccumulator,
    co_observed_clusters,
    dynamic_clusters,
    ground_voxels,
    remove_dynamic_points,
    split_moved_clusters,
    voxel_keys,
)

from .cli_errors import assert_one_error_line
from .conftest import shared_data


def test_range_image_facing_keeps_every_centre_a_beam_can_pass():
    """facing(): the wedge of a narrow scan's columns, tested in the world frame, never drops a
    centre that passes() frees or hits; it drops most of those around; a wide scan drops none."""
    rng = np.random.default_rng(3)
    for trial, half_width in enumerate((0.2, 0.6, 1.2, 2.0)):  # [rad] the scan's azimuth half-width
        az = rng.uniform(-half_width, half_width, 5000) + rng.uniform(-np.pi, np.pi)
        el, r = rng.uniform(-0.6, 0.6, 5000), rng.uniform(0.5, 60.0, 5000)
        pts = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1) * r[:, None]
        image = RangeImage(pts, 0.5, 0.4)
        a, b = rng.uniform(-np.pi, np.pi, 2)
        T_world_sensor = np.eye(4)
        T_world_sensor[:3, :3] = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]) \
            @ np.array([[1, 0, 0], [0, np.cos(b / 4), -np.sin(b / 4)], [0, np.sin(b / 4), np.cos(b / 4)]])
        T_world_sensor[:3, 3] = rng.normal(size=3) * 20.0
        local = np.concatenate([pts[rng.integers(0, 5000, 3000)] * rng.uniform(0.3, 1.2, (3000, 1)),
                                rng.normal(size=(3000, 3)) * 30.0])
        world = local @ T_world_sensor[:3, :3].T + T_world_sensor[:3, 3]
        facing = image.facing(np.linalg.inv(T_world_sensor), world)
        _, free, hit = image.passes(local, 0.25, lambda r: np.maximum(0.5, 0.05 * r))
        assert not ((free | hit) & ~facing).any(), trial
        if half_width < 1.0:
            assert (~facing).mean() > 0.3, trial
        if half_width > 1.6:  # wider than 170 deg: no wedge
            assert facing.all(), trial


def test_range_image_frees_a_voxel_only_when_its_beam_ended_beyond_it():
    # one beam straight ahead ending at 10 m, one 90 deg to the left ending at 3 m
    image = RangeImage(np.array([[10.0, 0.0, 0.0], [0.0, 3.0, 0.0]]), 0.25, 0.2)
    centres = np.array([[5.0, 0.0, 0.0],     # the beam passed it and went on: free
                        [9.9, 0.0, 0.0],     # the beam ended there: hit
                        [5.0, 0.5, 0.0],     # no beam came near: neither
                        [0.0, 5.0, 0.0]])    # behind the 3 m return: neither
    r, free, hit = image.passes(centres, 0.05, lambda r: np.maximum(0.3, 0.05 * r))
    assert np.allclose(r, [5.0, 9.9, np.hypot(5.0, 0.5), 5.0])
    assert free.tolist() == [True, False, False, False]
    assert hit.tolist() == [False, True, False, False]


def test_voxels_keep_first_and_last_sighting():
    acc = VoxelAccumulator(0.1, merge_points=1)
    acc.add(np.array([[0.05, 0.05, 0.05], [1.05, 0.05, 0.05]]), 3)
    acc.add(np.array([[0.07, 0.05, 0.05]]), 9)
    keys, centroids, counts, first, last = acc.result()
    assert np.all(np.diff(keys) > 0)
    assert counts.tolist() == [2, 1] and first.tolist() == [3, 3] and last.tolist() == [9, 3]
    assert np.allclose(centroids[0], [0.06, 0.05, 0.05])


def test_clusters_join_neighbours_seen_together_only():
    pts = np.array([[0.05, 0.05, 1.05], [0.15, 0.05, 1.05], [0.25, 0.05, 1.05], [0.95, 0.05, 1.05]])
    keys = np.sort(voxel_keys(pts, 0.1))
    order = np.argsort(voxel_keys(pts, 0.1))
    first = np.array([0, 1, 40, 0])[order]
    last = np.array([2, 3, 45, 2])[order]
    cluster = co_observed_clusters(keys, first, last, np.ones(4, dtype=bool), slack=2)
    c = cluster[np.argsort(order)]
    assert c[0] == c[1]           # adjacent, seen at overlapping times
    assert c[2] != c[1]           # adjacent, but seen 40 scans later: another object
    assert c[3] not in (c[0], c[2])  # far away
    ground = ground_voxels(np.array([[0.5, 0.5, 0.0], [0.5, 0.6, 0.1], [0.5, 0.5, 0.5]]), 1.0, 0.15)
    assert ground.tolist() == [True, True, False]


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """80 scans of a 16-ring drive along KITTI 00 with 16 movers, and the same drive without movers."""
    path = shared_data("trajectories", "kitti_gt", "00.txt.xz")
    root = tmp_path_factory.mktemp("movers")
    with_movers = generate_kitti_drive(path, root / "movers", rings=16, max_scans=80, movers=16)
    return with_movers, path, root


def test_movers_are_labelled_per_point(drive):
    log, path, root = drive
    meta = yaml.safe_load((log / "meta.yaml").read_text())
    assert sum(meta["movers"].values()) == 16 and set(meta["movers"]) == {"car", "parked_car", "person"}
    classes = np.concatenate([labels & 0xFFFF for _, _, labels, _ in labelled_scans(log)])
    present = set(np.unique(classes).tolist())
    assert {252, 254}.issubset(present) and {40, 50}.issubset(present)
    assert present <= {10, 40, 50, 70, 80, 99, 252, 254}
    # without movers: the same city, nothing labelled moving
    static = generate_kitti_drive(path, root / "static", rings=16, max_scans=3)
    for _, points, labels, _ in labelled_scans(static):
        assert len(points) == len(labels) and not np.any((labels >= 252) & (labels <= 259))


def test_clean_removes_the_movers_and_keeps_the_city(drive, tmp_path):
    log, _, _ = drive
    s = clean_log(log, log / "groundtruth_tum.txt", tmp_path / "clean")
    files = json.loads((tmp_path / "clean" / "summary.json").read_text())
    assert files["points_removed"] == s["points_removed"] > 0 and s["points_kept"] > 5 * s["points_removed"]
    assert s["wall_time_s"] > 0 and s["peak_memory_mb"] > 0 and s["scans"] == 80
    scores = evaluate_map_file(tmp_path / "clean" / "map_static.ply", log)
    assert scores["SA"] >= 0.99 and scores["DA"] >= 0.8, scores
    # the removed points are the movers: the dynamic map scores the other way round
    removed = evaluate_map_file(tmp_path / "clean" / "map_dynamic.ply", log)
    assert removed["SA"] < 0.05 and removed["DA"] < 0.2
    # no removal at all keeps every mover
    everything = np.vstack([p @ T[:3, :3].T + T[:3, 3] for (_, p, _, _), T in
                            zip(labelled_scans(log), _poses(log))])
    write_ply(tmp_path / "all.ply", everything.astype(np.float32))
    assert evaluate_map_file(tmp_path / "all.ply", log)["DA"] == 0.0


def _poses(log):
    from submapslam.io.trajectory import read_tum

    return read_tum(log / "groundtruth_tum.txt").poses


def test_clean_cli_never_overwrites_and_checks_the_poses(drive, tmp_path):
    log, _, _ = drive
    runner = CliRunner()
    out = tmp_path / "out"
    out.mkdir()
    (out / "map_static.ply").write_text("mine")
    assert_one_error_line(runner.invoke(app, ["clean", str(log), "--poses", str(log / "groundtruth_tum.txt"),
                                              "--out", str(out)]), "holds files of yours")
    assert (out / "map_static.ply").read_text() == "mine"
    short = tmp_path / "short.txt"
    short.write_text("".join((log / "groundtruth_tum.txt").read_text().splitlines(keepends=True)[:50]))
    assert_one_error_line(runner.invoke(app, ["clean", str(log), "--poses", str(short), "--out",
                                              str(tmp_path / "o2")]), "50 poses")
    assert_one_error_line(runner.invoke(app, ["clean", str(log), "--poses", str(tmp_path / "nope.txt"), "--out",
                                              str(tmp_path / "o3")]), "no such trajectory file")


def test_planar_movers_label_the_carmen_beams_too(tmp_path):
    from datasets_synth import generate

    log = generate("rectangle", tmp_path / "rect", max_scans=120, movers=6)
    meta = yaml.safe_load((log / "meta.yaml").read_text())
    assert meta["movers"] == {"box": 2, "person": 4}
    lines = [ln.split() for ln in (log / "log.clf.labels").read_text().splitlines() if not ln.startswith("#")]
    flaser = [ln for ln in (log / "log.clf").read_text().splitlines() if ln.startswith("FLASER")]
    assert len(lines) == len(flaser) == 120
    seen = set()
    for (_, points, labels, planar), beams, row in zip(labelled_scans(log), lines, flaser):
        assert len(points) == len(labels)
        classes = np.array(beams[1:], dtype=np.uint32)
        assert planar and int(beams[0]) == len(classes) == int(row.split()[1])
        # the beams with a return are the scan's points, in order, with the same classes
        assert np.array_equal(classes[classes > 0], labels)
        ranges = np.array(row.split()[2:2 + len(classes)], dtype=float)
        assert np.all((ranges < 80.0) == (classes > 0))
        seen |= set(np.unique(labels).tolist())
    assert seen <= {50, 254, 259} and 50 in seen and seen & {254, 259}


def test_bench_tool_runs_clean_and_no_removal_side_by_side(drive, tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    log, _, _ = drive
    tool = Path(__file__).resolve().parents[1] / "tools" / "bench_dynamic.py"
    proc = subprocess.run([sys.executable, str(tool), str(log), "--methods", "clean,none", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    runs = {r["method"]: r for r in json.loads((tmp_path / "results.json").read_text())}
    assert runs["none"]["DA"] == 0.0 and runs["none"]["SA"] == 1.0
    assert runs["clean"]["DA"] >= 0.8 and runs["clean"]["SA"] >= 0.99
    assert all(r["seconds"] > 0 and r["peak_mb"] > 0 for r in runs.values())
    assert "| clean |" in proc.stdout and "| none |" in proc.stdout


def _ground_grid(half: float = 20.0, step: float = 0.25, z: float = -1.7) -> np.ndarray:
    g = np.arange(-half, half, step) + step / 2
    x, y = np.meshgrid(g, g)
    return np.column_stack([x.ravel(), y.ravel(), np.full(x.size, z)])


def _pitch(deg: float, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    a = np.deg2rad(deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = t
    return T


def test_scan_ground_is_decided_in_each_scans_own_frame():
    from submapslam.mapping.dynamic_removal import scan_ground_points

    ground = _ground_grid()
    # a car's side 6 m ahead: from 0.3 m above the road up, in columns that hold no road point
    side = np.array([[6.05, y, z] for y in np.arange(-0.9, 0.9, 0.1) for z in np.arange(-1.4, -0.2, 0.1)])
    ground_near_car = np.abs(ground[:, 0] - 6.5) < 1.5
    pts = np.vstack([ground[~ground_near_car], side])
    d = RemovalParams()
    flags = scan_ground_points(pts, d.scan_ground_cell, d.scan_ground_band, d.scan_ground_rise, d.scan_ground_slope)
    n = int((~ground_near_car).sum())
    assert flags[:n].all()          # the road, out to 28 m, is ground
    assert not flags[n:].any()      # the car's lowest points are not: they are 0.3 m above the road plane
    # the same flat road seen twice from each of two poses that disagree by 1.5 deg of pitch: in the
    # world the road is half a metre thick at 20 m, so a band over the lowest voxel keeps only part
    # of it; the per-scan ground keeps all of it, and the evidence frees none of it
    T = np.stack([np.eye(4), np.eye(4), _pitch(1.5, (0.5, 0.0, 0.0)), _pitch(1.5, (0.5, 0.0, 0.0))])
    scans = [ground] * 4
    band_only = remove_dynamic_points(lambda: iter(scans), T, params=RemovalParams(scan_ground=False))
    both = remove_dynamic_points(lambda: iter(scans), T)
    assert not band_only.ground.all() and both.ground.all() and not both.dynamic.any()


def _wall_scan(sensor: np.ndarray, through: list[np.ndarray], wall_x: float = 20.0) -> np.ndarray:
    """Sensor-frame points of a wall at x = wall_x seen from ``sensor`` (world, no rotation): a grid of
    beams plus one beam through each world point of ``through`` (they end on the wall behind)."""
    az, el = np.meshgrid(np.deg2rad(np.arange(-20, 20, 0.5)), np.deg2rad(np.arange(-10, 10, 0.5)))
    d = np.column_stack([np.cos(el.ravel()) * np.cos(az.ravel()), np.cos(el.ravel()) * np.sin(az.ravel()),
                         np.sin(el.ravel())])
    d = np.vstack([d] + [(p - sensor) / np.linalg.norm(p - sensor) for p in through])
    return d * ((wall_x - sensor[0]) / d[:, :1])


def test_a_mover_seen_as_one_voxel_in_one_scan_is_removed():
    # a car far away leaves one point in scan 0 (one voxel, no neighbour); five later scans see the
    # wall behind it through that place. A one-voxel cluster with a free vote is dynamic; the wall
    # (seen by every scan) and a pole beside the path that no beam passes through are not
    mover = np.array([10.05, 0.05, 0.05])
    pole = np.array([10.05, 3.05, 0.05])
    T = np.stack([np.eye(4)] * 6)
    scans = []
    for k in range(6):
        T[k, 0, 3] = 0.3 * k
        s = T[k, :3, 3]
        pts = _wall_scan(s, [mover] if k else [])
        extra = [mover - s] if k == 0 else []
        scans.append(np.vstack([pts, pole - s, *extra]))
    res = remove_dynamic_points(lambda: iter(scans), T, params=RemovalParams(scan_ground=False, ground_band=-1.0))
    mask = res.dynamic_mask(np.vstack([mover, pole, [20.0, 0.0, 0.0]]))
    assert mask.tolist() == [True, False, False]
    assert res.dynamic.sum() == 1
    # the earlier rule (a cluster needs two voted voxels) kept it
    old = remove_dynamic_points(lambda: iter(scans), T, params=RemovalParams(scan_ground=False, ground_band=-1.0,
                                                                            min_free=2))
    assert not old.dynamic.any()


def test_a_voxel_seen_occupied_again_is_not_removed_by_one_grazing_beam():
    # a pole 10 m ahead of a sensor standing still: scan 0's noisy return falls into the voxel in
    # front of it (P), scans 1-9 return 0.25 m behind (Q, within the margin: they hit P, not pass
    # it); scan 10, from 5 m to the left, grazes past the pole through P to a wall at 20 m. P has
    # one free vote against nine hits: it stays. The earlier rule (any free vote) removed it.
    P, Q = np.array([10.05, 0.05, 0.05]), np.array([10.30, 0.05, 0.05])
    T = np.stack([np.eye(4)] * 11)
    T[10, 1, 3] = 5.0
    s10 = T[10, :3, 3]
    wall = s10 + (P - s10) * (20.0 - s10[0]) / (P - s10)[0]
    scans = [P[None]] + [Q[None]] * 9 + [(wall - s10)[None]]
    params = RemovalParams(scan_ground=False, ground_band=-1.0)
    res = remove_dynamic_points(lambda: iter(scans), T, params=params)
    p = np.searchsorted(res.keys, voxel_keys(P[None], 0.1))[0]
    assert res.free_votes[p] == 1 and res.hit_votes[p] == 9
    assert not res.dynamic_mask(np.vstack([P, Q])).any()
    old = remove_dynamic_points(lambda: iter(scans), T, params=replace(params, hit_weight=0.0))
    assert old.dynamic_mask(np.vstack([P, Q])).tolist() == [True, False]


def test_a_moved_cluster_parts_from_the_parked_car_its_mover_touched():
    # a row of 30 voxels: a parked car (x 0-1.4 m) seen for scans 0-40, a car that drove past
    # right beside it (x 1.5-2.9 m) seen once each around scan 20. Their sightings overlap, so they
    # are one co-observed cluster, which the mover's votes carry; split by sighting duration, the
    # parked car (tested, not voted) stays and the mover goes
    pts = np.column_stack([np.arange(30) * 0.1 + 0.05, np.full(30, 0.05), np.full(30, 1.05)])
    keys = voxel_keys(pts, 0.1)
    assert np.all(np.diff(keys) > 0)
    parked = np.arange(30) < 15
    first = np.where(parked, 0, 20 + np.arange(30) % 2)
    last = np.where(parked, 40, 20 + np.arange(30) % 2)
    cluster = co_observed_clusters(keys, first, last, np.ones(30, dtype=bool), slack=2)
    assert len(np.unique(cluster)) == 1
    voted = np.where(parked, 0, 1).astype(np.int8)
    moved = dynamic_clusters(cluster, voted, 0.3, 1)
    assert moved.all()
    kept = split_moved_clusters(keys, first, last, moved, voted, slack=2, ratio=4.0, min_tested=5, fraction=0.3)
    assert kept.tolist() == (~parked).tolist()
    # a part with too few tested voxels keeps its cluster's decision
    few = np.where(parked & (np.arange(30) > 2), -1, voted).astype(np.int8)
    assert split_moved_clusters(keys, first, last, moved, few, slack=2, ratio=4.0, min_tested=5, fraction=0.3).all()
