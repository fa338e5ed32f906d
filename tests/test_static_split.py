"""The submap mover split keeps a static street whole (thin and overhanging things on a 16-ring
sensor) and still takes out a car that drove off."""

from __future__ import annotations

import dataclasses

import numpy as np

from submapslam.mapping.moving_points import SPLIT_PARAMS, MoverParams, SubmapMovers

# boxes (lo, hi) [m] in the world frame, ground at z = 0
BUILDING = (np.array([-5.0, 8.0, 0.0]), np.array([40.0, 14.0, 7.0]))
EAVE = (np.array([-5.0, 6.8, 6.6]), np.array([40.0, 8.0, 7.0]))  # a thin roof overhang beams pass under
POLES = [(np.array([x, -4.2, 0.0]), np.array([x + 0.2, -4.0, 6.0])) for x in (6.0, 14.0, 22.0)]
CANOPY = (np.array([10.0, -7.5, 3.0]), np.array([13.5, -4.5, 5.0]))  # a tree crown over the pavement
TRUNK = (np.array([11.6, -6.1, 0.0]), np.array([11.9, -5.8, 3.0]))
PARKED = (np.array([16.0, 4.0, 0.2]), np.array([20.5, 5.8, 1.6]))
STATIC = [BUILDING, EAVE, *POLES, CANOPY, TRUNK, PARKED]
CAR = (np.array([24.0, -2.5, 0.2]), np.array([28.5, -0.7, 1.6]))  # in the opposite lane, then gone
MOUNT = 1.73
HILL = 30.0  # [m] x where the road starts to climb (``grade``)


def _rays() -> np.ndarray:
    """Unit directions ``(R, 3)`` of a 16-ring, 0.4-degree spinning LiDAR (sensor frame)."""
    el, az = np.meshgrid(np.deg2rad(np.linspace(-15.0, 15.0, 16)), np.deg2rad(np.arange(-180.0, 180.0, 0.4)))
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)


def _cast(origin: np.ndarray, boxes: list, rng: np.random.Generator, grade: float = 0.0) -> np.ndarray:
    """Sensor-frame returns ``(N, 3)`` (sensor level, axes as the world's) of the ground and ``boxes``, 4 cm noise.
    The ground is z = 0, with ``grade``: z = grade * (x - HILL) for x > HILL (a road climbing ahead)."""
    d = _rays()
    t = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        flat = -origin[2] / d[:, 2]
        t = np.where((flat > 0) & ((origin[0] + flat * d[:, 0] <= HILL) | (grade == 0.0)), flat, t)
        if grade:
            slope = (grade * (origin[0] - HILL) - origin[2]) / (d[:, 2] - grade * d[:, 0])
            t = np.where((slope > 0) & (origin[0] + slope * d[:, 0] > HILL), np.minimum(t, slope), t)
    with np.errstate(divide="ignore", invalid="ignore"):
        for lo, hi in boxes:
            t0, t1 = (lo - origin) / d, (hi - origin) / d
            near = np.nanmax(np.minimum(t0, t1), axis=1)
            far = np.nanmin(np.maximum(t0, t1), axis=1)
            t = np.where((near <= far) & (near > 0), np.minimum(t, near), t)
    keep = t < 60.0
    r = t[keep] + rng.normal(0.0, 0.04, int(keep.sum()))
    return d[keep] * r[:, None]


def _split_drive(car_until: int, grade: float = 0.0, params: MoverParams = SPLIT_PARAMS) -> tuple[np.ndarray, np.ndarray]:
    """Drive 24 m along y = 0 (36 scans, 2 submaps of 18); ``CAR`` stands in the scans before
    ``car_until``; the road ahead climbs by ``grade`` beyond ``HILL``. Returns every submap point
    (world frame) and which of them went to the dynamic cloud."""
    rng = np.random.default_rng(0)
    movers = SubmapMovers(params=params)
    poses, clouds = [], []
    for k in range(36):
        T = np.eye(4)
        T[:3, 3] = [0.7 * k, 0.0, MOUNT]
        pts = _cast(T[:3, 3], STATIC + ([CAR] if k < car_until else []), rng, grade)
        movers.add(k, T, pts[::2], pts)
        poses.append(T)
        clouds.append(pts[::2] + T[:3, 3])
    points, moved, earlier = [], [], None
    for ids in (list(range(0, 18)), list(range(17, 36))):
        evidence = movers.take(ids)
        T_anchor = poses[ids[0]]
        cloud = np.vstack([clouds[k] for k in ids]) - T_anchor[:3, 3]  # anchor frame
        out = movers.split(evidence, T_anchor, cloud)
        if earlier is not None:  # the earlier submap loses what the new one's scans saw through
            e_T, e_cloud, e_out = earlier
            rest = np.flatnonzero(~e_out)
            e_out[rest] = movers.seen_through_later(evidence, e_T, e_cloud[rest])
        earlier = (T_anchor, cloud, out)
        points.append(cloud + T_anchor[:3, 3])
        moved.append(out)
    return np.vstack(points), np.concatenate(moved)


def _inside(points: np.ndarray, box: tuple) -> np.ndarray:
    return np.all((points >= box[0] - 0.1) & (points <= box[1] + 0.1), axis=1)


def test_a_static_street_with_poles_a_canopy_and_eaves_keeps_its_points():
    points, moved = _split_drive(car_until=0)
    assert len(points) > 100_000
    assert moved.mean() <= 0.005, {name: int(moved[_inside(points, box)].sum()) for name, box in
                                   (("poles", POLES[1]), ("canopy", CANOPY), ("eave", EAVE), ("parked", PARKED))}


def test_the_same_street_still_loses_a_car_that_drove_off():
    points, moved = _split_drive(car_until=10)
    car = _inside(points, CAR)
    assert car.sum() > 100
    assert moved[car].mean() > 0.8, moved[car].mean()
    assert moved[~car].mean() <= 0.005


def test_a_return_within_the_radius_blocks_a_free_vote():
    """RangeImage.returns_near: a voxel 0.2 m beside a pole's return is near it, 1 m beside is not."""
    from submapslam.mapping.dynamic_removal import RangeImage

    pole = np.column_stack([np.full(20, 10.0), np.zeros(20), np.linspace(-1.0, 1.0, 20)])
    image = RangeImage(pole, 0.5, 0.4)
    centres = np.array([[10.0, 0.2, 0.0], [10.0, 1.0, 0.0], [9.8, 0.0, 0.3]])
    assert image.returns_near(centres, 0.3).tolist() == [True, False, True]


def test_a_road_climbing_ahead_keeps_its_ground():
    """The hill beyond the scan's own ground plane is tested, and the beams graze it: a beam that
    passes a ground voxel ends on the same road metres on, which is no sign that the voxel is
    free (the split's incidence margin; without it 19 % of the hill went)."""
    points, moved = _split_drive(car_until=0, grade=0.05)
    far = points[:, 0] > HILL + 5.0
    assert far.sum() > 1000
    assert moved.mean() <= 0.005, (moved.mean(), moved[far].mean())


def test_the_floor_of_a_column_is_the_lowest_point_beside_it():
    """column_floor: on a road climbing 10 %, the floor under a point is the road within a cell of
    it; under a car whose own columns hold no road, it is the road beside the car."""
    from submapslam.mapping.moving_points import column_floor

    xy = np.stack(np.meshgrid(np.arange(0.0, 20.0, 0.25), np.arange(-5.0, 5.0, 0.25)), -1).reshape(-1, 2)
    under_car = (np.abs(xy[:, 0] - 10.0) < 2.0) & (np.abs(xy[:, 1]) < 0.9)
    road = np.column_stack([xy[~under_car], 0.1 * xy[~under_car, 0]])
    car = np.column_stack([xy[under_car], 0.1 * xy[under_car, 0] + 0.5])  # its underside, 0.5 m up
    floor = column_floor(np.vstack([road, car]), np.array([[5.1, 0.1, 9.0], [10.1, 0.1, 1.5]]), 1.0)
    assert abs(floor[0] - 0.4) < 0.11  # the road's lowest point within a cell of x = 5.1
    assert abs(floor[1] - 0.8) < 0.11  # the road beside the car, not the car (1.5 m)
    assert column_floor(road, np.array([[100.0, 0.0, 0.0]]), 1.0)[0] == -np.inf  # no point near


def test_with_the_floor_rule_a_steep_road_keeps_its_ground_and_the_car_still_goes():
    """A road climbing 15 % ahead, the split with ``floor_cell`` 1 m (off by default: see BENCHMARKS):
    what a beam sees through within 0.4 m of the submap's own floor casts no free vote, so the hill
    keeps its points (without the rule 0.5 % of it goes); a car (1.4 m tall) still leaves."""
    floor = dataclasses.replace(SPLIT_PARAMS, floor_cell=1.0)
    points, moved = _split_drive(car_until=0, grade=0.15, params=floor)
    far = points[:, 0] > HILL + 5.0
    assert far.sum() > 1000
    assert moved.mean() <= 0.001 and moved[far].mean() <= 0.001, (moved.mean(), moved[far].mean())
    points, moved = _split_drive(car_until=10, grade=0.15, params=floor)
    car = _inside(points, CAR)
    assert moved[car].mean() > 0.8 and moved[~car].mean() <= 0.005


def test_a_steep_road_keeps_its_ground_at_the_defaults_and_the_car_still_goes():
    """A road climbing 20 % ahead: beams skim over the slope and land on it metres on. Only beams
    at or below a voxel's height count (``pass_above`` 0), so none of the hill goes (with beams
    on either side counting, 2.3 % of it went) and the car that drove off still does."""
    points, moved = _split_drive(car_until=0, grade=0.2)
    far = points[:, 0] > HILL + 5.0
    assert far.sum() > 1000
    assert moved.mean() <= 0.001 and moved[far].mean() <= 0.001, (moved.mean(), moved[far].mean())
    points, moved = _split_drive(car_until=10, grade=0.2)
    car = _inside(points, CAR)
    assert moved[car].mean() > 0.8 and moved[~car].mean() <= 0.001


def test_a_beam_over_a_point_is_not_a_beam_through_it():
    """RangeImage.passes with ``above`` 0: a beam 0.1 m under a voxel that ends 20 m beyond sees
    through it; one 0.1 m over it (over a roof, along the ground) does not, unless either side counts."""
    from submapslam.mapping.dynamic_removal import RangeImage

    def margin(r: np.ndarray) -> np.ndarray:
        return np.full(len(r), 0.5)

    for rise, free_one_sided in ((-0.1, True), (0.1, False)):
        beam = np.array([[40.0, 0.0, 40.0 * np.tan(rise / 20.0)]])  # passes the voxel at (20, 0, 0) by ``rise``
        image = RangeImage(beam, 0.5, 0.4)
        voxel = np.array([[20.0, 0.0, 0.0]])
        assert image.passes(voxel, 0.3, margin)[1].tolist() == [True]
        assert image.passes(voxel, 0.3, margin, above=0.0)[1].tolist() == [free_one_sided]


def _later_test_of_a_car(distance: float, params: MoverParams = SPLIT_PARAMS, step: float = -0.5) -> float:
    """Share of an earlier submap's car ``distance`` [m] ahead of it that goes when the new
    submap's scans, driving ``step`` [m] a scan along x (away from it when negative), see through
    where it stood (a wall 12 m beyond)."""
    rng = np.random.default_rng(1)
    car = (np.array([distance, -3.5, 0.2]), np.array([distance + 4.5, -1.7, 1.6]))
    wall = (np.array([distance + 12.0, -30.0, 0.0]), np.array([distance + 13.0, 30.0, 10.0]))
    origins = [np.array([step * k, 0.0, MOUNT]) for k in range(6)]
    seen = np.vstack([_cast(o, [car, wall], rng) + o for o in origins[:2]])  # anchor = world frame
    earlier = seen[_inside(seen, car)]
    movers = SubmapMovers(params=params)
    for k, origin in enumerate(origins):  # the new submap: the car has gone
        T = np.eye(4)
        T[:3, 3] = origin
        scan = _cast(origin, [wall], rng)
        movers.add(k, T, scan[::2], scan)
    return float(movers.seen_through_later(movers.take(list(range(6))), np.eye(4), earlier).mean())


def test_later_scans_test_earlier_submaps_within_their_range_only():
    """An earlier submap's points get evidence from the new submap's scans within
    ``later_max_range`` (30 m) only: beyond, the odometry's tilt drift between two submaps moves a
    passing beam by a decimetre or more. A car that left 15 m away goes; 40 m away it stays (it
    went with evidence from up to 50 m)."""
    assert _later_test_of_a_car(15.0) == 1.0
    assert _later_test_of_a_car(40.0) == 0.0
    assert _later_test_of_a_car(40.0, dataclasses.replace(SPLIT_PARAMS, later_max_range=50.0)) == 1.0


def test_a_forward_looking_sensor_counts_beams_on_either_side():
    """Scans nearing a car that left pass a little above the earlier hits on its side: the
    one-sided window keeps the car, the narrow sensor's settings (both sides, 0.25 m) take it."""
    from submapslam.mapping.moving_points import NARROW_SPLIT_PARAMS

    assert _later_test_of_a_car(15.0, SPLIT_PARAMS, step=0.5) == 0.0
    assert _later_test_of_a_car(15.0, NARROW_SPLIT_PARAMS, step=0.5) > 0.9


def _submaps_result(kept: list, moved: list, reach: float = 20.0):
    """A 3D result of submaps k = 0, 1, ..., each anchor (and its one scan) k m along x:
    ``kept[k]`` / ``moved[k]`` the anchor-frame points submap k kept / split off."""
    from submapslam.config import PipelineConfig
    from submapslam.result import SlamResult

    cfg = PipelineConfig()
    cfg.mapping.write_grid = False
    cfg.mapping.moved_verdict_range = reach
    n = len(kept)
    anchors = np.tile(np.eye(4), (n, 1, 1))
    anchors[:, 0, 3] = np.arange(n)

    def cloud(p: list) -> np.ndarray:
        return np.asarray(p, dtype=np.float64).reshape(-1, 3)

    return SlamResult(
        timestamps=np.zeros(n), poses=anchors.copy(), odometry_poses=anchors.copy(), submap_poses=anchors,
        submap_covariances=np.tile(np.eye(6), (n, 1, 1)), submap_points=[cloud(p) for p in kept],
        submap_scan_indices=[[k] for k in range(n)], submap_scan_poses=[np.eye(4)[None] for _ in range(n)],
        submap_scan_points=[[] for _ in range(n)], edges=[], loops=[], planar=False, config=cfg,
        map_voxel_size=0.4, submap_dynamic_points=[cloud(p) for p in moved])


def test_map_and_dynamic_cloud_share_no_voxel():
    """A voxel one submap's split took out far from its own path while another submap kept it
    stays in map.ply and is not reported in map_dynamic.ply; a voxel no submap kept is reported
    (fails when the dynamic cloud is every submap's split-off points, as before)."""
    from submapslam.mapping.global_map import build_map_outputs

    wall = [[30.05, 0.05, 1.05], [30.05, 0.45, 1.05]]  # world = submap 0's frame; 30 m from its scan
    held = [29.1, 0.1, 1.1]  # submap 1 (1 m on): world (30.1, 0.1, 1.1), 29 m from its path
    gone = [39.1, 0.1, 1.1]  # world (40.1, 0.1, 1.1): nobody kept it
    maps = build_map_outputs(_submaps_result([wall, []], [[], [held, gone]]))
    assert len(maps.points) == 2 and maps.left_points == 0
    np.testing.assert_allclose(maps.dynamic_points, [[40.1, 0.1, 1.1]], atol=1e-5)
    assert maps.moved_points_in_map == 1


def test_a_voxel_leaves_the_map_when_near_verdicts_of_moved_match_those_that_kept_it():
    """A car one submap kept and another, 5 m from it, took out as moved leaves the map for the
    dynamic cloud, in either order; kept by two submaps and moved by one it stays; with the rule
    off (range 0), or the car beyond the range, any submap's keeping wins (each fails when the
    map is the plain union of what the submaps kept, or when the counts are not compared)."""
    from submapslam.mapping.global_map import build_map_outputs

    car = [[5.05, 0.05, 1.05], [5.05, 0.45, 1.05]]  # world = submap 0's frame
    car_from_1 = [[4.1, 0.1, 1.1]]  # the first car voxel, in submap 1's frame (1 m on)
    left = build_map_outputs(_submaps_result([car, []], [[], car_from_1]))
    np.testing.assert_allclose(left.points, [car[1]], atol=1e-5)
    np.testing.assert_allclose(left.dynamic_points, [[5.1, 0.1, 1.1]], atol=1e-5)
    assert left.left_points == 1 and left.moved_points_in_map == 0
    first_moved = build_map_outputs(_submaps_result([[], car_from_1], [car, []]))  # kept later: the same count
    assert len(first_moved.points) == 0 and len(first_moved.dynamic_points) == 2
    car_from_2 = [[3.1, 0.1, 1.1]]  # the same voxel from submap 2 (2 m on), which keeps it too
    outvoted = build_map_outputs(_submaps_result([car, [], car_from_2], [[], car_from_1, []]))
    assert len(outvoted.points) == 2 and len(outvoted.dynamic_points) == 0 and outvoted.left_points == 0
    for reach in (0.0, 3.0):
        kept = build_map_outputs(_submaps_result([car, []], [[], car_from_1], reach=reach))
        assert len(kept.points) == 2 and len(kept.dynamic_points) == 0 and kept.moved_points_in_map == 1
