"""`run` on drives with movers: the streaming mover test (mapping/moving_points.py), the odometry
that keeps movers out of KISS-ICP, and the run's map_dynamic.ply."""

from __future__ import annotations

import numpy as np
import pytest

from datasets_synth import generate_kitti_drive
from submapslam.api import evaluate_map_file, run_log
from submapslam.config import PipelineConfig, with_updates
from submapslam.evaluation.metrics import ate
from submapslam.io.labels import labelled_scans
from submapslam.io.run_folder import read_ply_points
from submapslam.io.trajectory import read_trajectory
from submapslam.mapping.dynamic_removal import co_observed_clusters, voxel_keys
from submapslam.mapping.moving_points import (
    MoverFilter,
    MoverParams,
    ViewStack,
    moving_in_scan,
    spatial_clusters,
)

from .conftest import shared_data

BOX = (np.array([9.0, -1.0, -1.4]), np.array([11.0, 1.0, 0.2]))  # a car-sized box 10 m ahead [m]


def cast(box: bool) -> np.ndarray:
    """A scan (sensor 1.7 m over flat ground) of a wall 20 m ahead, and of ``BOX`` when ``box``."""
    el, az = np.meshgrid(np.deg2rad(np.arange(-15.0, 15.01, 0.5)), np.deg2rad(np.arange(-30.0, 30.01, 0.4)))
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)
    t = np.full(len(d), np.inf)
    down = d[:, 2] < -1e-9
    t[down] = -1.7 / d[down, 2]                       # the ground
    t = np.minimum(t, np.where(d[:, 0] > 1e-9, 20.0 / np.maximum(d[:, 0], 1e-9), np.inf))  # the wall
    if box:  # slab test
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = (BOX[0] - 0.0) / d, (BOX[1] - 0.0) / d
        near = np.nanmax(np.minimum(t0, t1), axis=1)
        far = np.nanmin(np.maximum(t0, t1), axis=1)
        hit = (near <= far) & (near > 0)
        t = np.where(hit, np.minimum(t, near), t)
    keep = np.isfinite(t) & (t < 60.0)
    return d[keep] * t[keep, None]


def in_box(points: np.ndarray) -> np.ndarray:
    return np.all((points >= BOX[0] - 0.05) & (points <= BOX[1] + 0.05), axis=1)


def test_points_in_space_an_earlier_scan_saw_through_are_movers_and_the_rest_is_kept():
    params = MoverParams()
    views = ViewStack(2, params)
    views.add(0, np.eye(4), cast(box=False))     # the street was empty ...
    now = cast(box=True)                          # ... now a car stands in it
    moved = moving_in_scan(now, np.eye(4), views, views.slots(0, 0), params)
    car = in_box(now)
    assert car.sum() > 50
    assert moved[car].mean() > 0.9               # the car is dropped
    assert not moved[~car].any()                 # the wall and the ground are kept
    # the empty street tested against itself: nothing moved
    assert not moving_in_scan(cast(box=False), np.eye(4), views, views.slots(0, 0), params).any()


def test_a_scan_enters_the_local_map_late_without_what_later_scans_saw_through():
    filt = MoverFilter(history=3, delay=2, max_views=4)
    first = cast(box=True)                        # a parked car that then drives off
    assert filt.add(first, first, np.eye(4)) == []   # waits for later scans
    out = []
    for _ in range(3):
        empty = cast(box=False)
        out += filt.add(empty, empty, np.eye(4))
    points, pose = out[0]
    assert np.array_equal(pose, np.eye(4))
    assert in_box(first).sum() > 50 and not in_box(points).any()    # the car is not in the map
    assert len(points) == (~in_box(first)).sum()                    # everything else is
    # entering: the car seen again where the last scans saw the street empty is not registered
    again = cast(box=True)
    assert filt.entering(again, np.eye(4))[in_box(again)].mean() > 0.9


@pytest.mark.parametrize("gap_s, waits", [(0.1, 8), (0.4, 2), (0.25, 4), (None, 8), (100.0, 8)])
def test_a_scan_waits_eight_scans_or_a_time_whichever_comes_first(gap_s, waits):
    """At 10 Hz a scan enters the local map 8 scans late; in a keyframed log (scans 0.25-0.4 s
    apart) once the newest scan is 0.8 s later; without times, or with times that cannot be
    seconds (10 Hz in milliseconds: 100 apart), by the count alone."""
    filt = MoverFilter(delay=8, delay_s=0.8, test=False)
    scan = cast(box=False)
    entered_at = []
    for k in range(12):
        stamp = None if gap_s is None else 100.0 + k * gap_s
        for _, pose in filt.add(scan, scan, np.eye(4) + k * np.eye(4, k=3), timestamp=stamp):
            entered_at.append((round(pose[0, 3]), k))   # (the scan that entered, the scan that let it)
    assert entered_at[0] == (0, waits)
    assert all(later - scan_index == waits for scan_index, later in entered_at)


def test_numpy_clusters_are_the_26_connected_components():
    points = np.random.default_rng(1).uniform(0.0, 30.0, (3000, 3))
    keys = np.unique(voxel_keys(points, 0.4))
    zero = np.zeros(len(keys), dtype=np.int32)
    ours = spatial_clusters(keys)
    scipys = co_observed_clusters(keys, zero, zero, np.ones(len(keys), dtype=bool), 0)
    # the same partition: each of our clusters is one of scipy's and their numbers agree
    assert len(np.unique(ours)) == len(np.unique(scipys)) == len(np.unique(ours * len(keys) + scipys))
    assert 1 < len(np.unique(ours)) < len(keys)
    # each voxel is labelled with the smallest index of its component, also where a component
    # winds through the key order (a helix and a wall beside the random voxels)
    t = np.linspace(0.0, 12 * np.pi, 4000)
    helix = np.stack([15 + 6 * np.cos(t), 15 + 6 * np.sin(t), t / 2], axis=1)
    wall = np.stack(np.meshgrid(np.arange(0.0, 20.0, 0.3), [40.0], np.arange(0.0, 6.0, 0.3)), -1).reshape(-1, 3)
    keys = np.unique(voxel_keys(np.concatenate([points, helix, wall]), 0.4))
    zero = np.zeros(len(keys), dtype=np.int32)
    ours = spatial_clusters(keys)
    scipys = co_observed_clusters(keys, zero, zero, np.ones(len(keys), dtype=bool), 0)
    assert len(np.unique(ours)) == len(np.unique(scipys)) == len(np.unique(ours * len(keys) + scipys))
    smallest = np.full(len(keys), len(keys))
    np.minimum.at(smallest, scipys, np.arange(len(keys)))
    assert np.array_equal(ours, smallest[scipys])


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """80 scans of a 16-ring drive along KITTI 00 with 16 movers, run with the mover filters and without."""
    root = tmp_path_factory.mktemp("run_movers")
    log = generate_kitti_drive(shared_data("trajectories", "kitti_gt", "00.txt.xz"), root / "log", rings=16,
                               max_scans=80, movers=16)
    off = with_updates(PipelineConfig(), {"odometry": {"drop_movers": False, "movers_delay": 0},  # as before
                                          "mapping": {"split_movers": False}})
    on = with_updates(PipelineConfig(), {"odometry": {"drop_movers": True}})
    _, on_files = run_log(log, root / "on", config=on)
    _, off_files = run_log(log, root / "off", config=off)
    return log, on_files, off_files


def test_run_writes_what_moved_to_map_dynamic_and_keeps_it_out_of_map(runs):
    log, on, off = runs
    assert "map_dynamic.ply" in on and "map_dynamic.ply" not in off
    dynamic = read_ply_points(on["map_dynamic.ply"])
    assert len(dynamic) > 100
    # map_dynamic.ply holds the movers: the share of its points whose nearest scan point (scans at
    # the run's poses) is labelled moving is far above that of the map; map.ply keeps fewer of them
    from scipy.spatial import cKDTree

    run_poses = read_trajectory(on["poses_tum.txt"]).poses  # the map's frame
    world, moving = [], []
    for k, points, labels, _ in labelled_scans(log):
        world.append(points[::2] @ run_poses[k][:3, :3].T + run_poses[k][:3, 3])
        moving.append((labels[::2] & 0xFFFF) >= 252)
    tree, moving = cKDTree(np.vstack(world)), np.concatenate(moving)

    def mover_share(cloud: np.ndarray) -> float:
        return float(moving[tree.query(cloud)[1]].mean())

    share_dynamic = mover_share(dynamic)
    share_on, share_off = mover_share(read_ply_points(on["map.ply"])), mover_share(read_ply_points(off["map.ply"]))
    assert share_dynamic > 0.4 and share_dynamic > 10 * share_on, (share_dynamic, share_on)
    assert share_on < 0.5 * share_off, (share_on, share_off)
    # map.ply: far fewer mover voxels than without the filter, the static ones kept as well
    s_on = evaluate_map_file(on["map.ply"], log, poses=on["poses_tum.txt"], voxel=0.2, radius=0.3)
    s_off = evaluate_map_file(off["map.ply"], log, poses=off["poses_tum.txt"], voxel=0.2, radius=0.3)
    assert s_on["DA"] > s_off["DA"] + 0.4, (s_on, s_off)
    assert s_on["SA"] > s_off["SA"] - 0.03, (s_on, s_off)


def test_odometry_that_keeps_movers_out_is_not_worse(runs):
    log, on, off = runs
    truth = read_trajectory(log / "groundtruth_tum.txt")
    e_on = ate(read_trajectory(on["odometry_tum.txt"]), truth)["rmse"]
    e_off = ate(read_trajectory(off["odometry_tum.txt"]), truth)["rmse"]
    assert e_on <= 1.05 * e_off, (e_on, e_off)


def test_non_ground_follows_sloped_and_bending_ground():
    """Ground tilted 4 % in the sensor frame (a change of grade under the vehicle, a banked road)
    with a car 12 m ahead: the plane fitted to the low points takes none of the ground for an
    obstacle (one height for the whole scan took 21 % of it), the car above the band is tested.
    With ``cell`` the ground also bends where the grade changes again 20 m ahead."""
    from submapslam.mapping.moving_points import non_ground

    rng = np.random.default_rng(0)
    xy = rng.uniform(-45.0, 45.0, size=(40000, 2))
    x = xy[:, 0]
    tilted = -1.73 + 0.04 * x + rng.normal(0.0, 0.03, len(x))
    car = np.column_stack([rng.uniform(10.0, 14.5, 600), rng.uniform(-1.0, 1.0, 600), rng.uniform(-1.5, -0.2, 600)])
    car[:, 2] += 0.04 * car[:, 0]
    pts = np.vstack([np.column_stack([xy, tilted]), car])
    flags = non_ground(pts, 0.3)
    assert flags[: len(xy)].mean() < 0.005
    assert flags[len(xy):][car[:, 2] - 0.04 * car[:, 0] > -1.2].mean() > 0.9
    bend = -1.73 + np.where(x > 20.0, 0.04 * (x - 20.0), 0.0) + rng.normal(0.0, 0.03, len(x))
    bent = np.column_stack([xy, bend])
    assert non_ground(bent, 0.3).mean() > 0.02  # the plane alone: the far climb looks like obstacles
    assert non_ground(bent, 0.3, cell=5.0).mean() < 0.005


def test_evidence_with_the_reach_cull_counts_what_each_scan_alone_counts(monkeypatch):
    """Points beyond ``max_range`` of every scan are left out before the scans are asked
    (``ViewStack._within_reach``): the counts stay those of asking every scan about every point,
    with and without an ``allowed`` filter, the points near and far mixed."""
    params = MoverParams(max_range=15.0)
    views = ViewStack(4, params)
    for k, x in enumerate((0.0, 4.0, 8.0, 12.0)):
        T = np.eye(4)
        T[0, 3] = x
        views.add(k, T, cast(box=k % 2 == 0))
    rng = np.random.default_rng(3)
    points = np.concatenate([cast(box=True)[::3] + [6.0, 0.0, 0.0],  # near every scan
                             rng.uniform([-40.0, -10.0, -1.0], [40.0, 10.0, 1.0], (4000, 3))])  # many beyond reach
    slots = views.slots(0, 3)
    culled = views._within_reach(points, slots)
    assert 0 < len(culled) < len(points)

    def allowed(k, idx):
        return (idx + k) % 3 != 0

    with_cull = [views.evidence(points, slots), views.evidence(points, slots, allowed)]
    monkeypatch.setattr(ViewStack, "_within_reach", lambda self, pts, s: np.arange(len(pts)))
    without = [views.evidence(points, slots), views.evidence(points, slots, allowed)]
    for a, b in zip(with_cull, without):
        for counts_a, counts_b in zip(a, b):
            assert np.array_equal(counts_a, counts_b)
    assert without[0][1].sum() > 0 and without[0][0].max() == 4  # free votes cast; every scan tested each point


def test_normals_from_kept_voxel_sums_are_those_of_the_cloud():
    from submapslam.mapping.local_normals import VoxelSums, local_normals

    rng = np.random.default_rng(5)
    ground = np.column_stack([rng.uniform(-10, 10, (5000, 2)), rng.normal(0.0, 0.01, 5000)])
    wall = np.column_stack([rng.uniform(-10, 10, 3000), np.full(3000, 4.0), rng.uniform(0, 3, 3000)])
    cloud = np.concatenate([ground, wall]) + [100.0, -50.0, 3.0]
    sums = VoxelSums(cloud, 0.4)
    for query in (cloud[::37], cloud[::5] + 0.05, np.zeros((0, 3))):
        assert np.array_equal(local_normals(sums, query, 0.4, flatness=0.2),
                              local_normals(cloud, query, 0.4, flatness=0.2))
    normals = local_normals(sums, cloud[:5000:50], 0.4, flatness=0.2)
    assert (np.abs(normals[:, 2]) > 0.99).mean() > 0.8  # the ground's normal is up (beside the wall: none)
    with pytest.raises(ValueError):
        local_normals(sums, cloud[:10], 0.2)
