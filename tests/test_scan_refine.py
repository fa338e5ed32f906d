"""Scan-level refinement after the submap solve: scans the odometry misplaced inside their submap
are pulled back by their matches against the other submaps."""

from functools import lru_cache

import numpy as np

from submapslam.config import ScanRefineConfig
from submapslam.registration.scan_to_submap import match_scans
from submapslam.scan_refine import _between, _compose, refine_scans

from .planar_scenes import wall_points

# a 12 x 6 m room with a pillar, a recess and a slanted corner: every scan constrains x, y and yaw
ROOM = [(0, -3, 12, -3), (12, -3, 12, 3), (12, 3, 0, 3), (0, 3, 0, -3),
        (4.0, 1.8, 4.6, 1.8), (4.6, 1.8, 4.6, 2.4), (4.6, 2.4, 4.0, 2.4), (4.0, 2.4, 4.0, 1.8),
        (8.0, -3.0, 8.0, -2.2), (8.0, -2.2, 9.0, -2.2), (9.0, -2.2, 9.0, -3.0), (10.5, 3.0, 12.0, 1.5)]
STEP = 15  # scans per submap (the last one shared with the next submap, as SubmapBuilder does)
BURST = range(20, 25)  # the scans the odometry misplaced (inside submap 1)


@lru_cache(maxsize=1)
def _scene():
    truth = np.array([[1.0 + 0.2 * k, 0.3 * np.sin(0.3 * k), 0.05 * np.cos(0.2 * k)] for k in range(46)])
    scans = [wall_points(ROOM, p, beams=181) for p in truth]
    # a burst of bad registrations: the odometry turns scans 20-24 by 1.5 deg about scan 20 (and
    # slides them 3 cm), then registers scan 25 right again
    glitch = np.array([0.03, -0.02, np.deg2rad(1.5)])
    pivot = truth[20]
    G = _compose(_compose(pivot, glitch), _between(pivot, np.zeros(3)))  # the glitch about scan 20
    odom = np.array([_compose(G, p) if k in BURST else p for k, p in enumerate(truth)])
    submaps = [list(range(a, min(a + STEP, len(truth) - 1) + 1)) for a in range(0, len(truth) - 1, STEP)]
    # the submap solve placed every anchor right (loops); scans inside a submap follow the odometry
    world = odom.copy()
    for idx in submaps:
        a = idx[0]
        for i in idx[1:]:
            world[i] = _compose(truth[a], _between(odom[a], odom[i]))
    clouds = []
    for idx in submaps:
        a = idx[0]
        parts = []
        for i in idx:
            rel = _between(odom[a], odom[i])
            c, s = np.cos(rel[2]), np.sin(rel[2])
            parts.append(scans[i] @ np.array([[c, s], [-s, c]]) + rel[:2])
        clouds.append(np.concatenate(parts))
    return truth, odom, world, submaps, clouds, scans


def _errors(poses_xyt, truth):
    d = _between(truth, poses_xyt)
    return np.hypot(d[:, 0], d[:, 1]), np.abs(np.rad2deg(d[:, 2]))


def test_scans_misplaced_by_the_odometry_are_pulled_back_by_the_other_submaps():
    truth, odom, world, submaps, clouds, scans = _scene()
    t0, r0 = _errors(world, truth)
    misplaced = np.array(BURST)
    assert t0[misplaced].mean() > 0.025 and r0[misplaced].min() > 1.49
    cfg = ScanRefineConfig(keyframe_step_m=0.15)
    refined = refine_scans(odom, world, submaps, clouds, scans, cfg)
    assert refined.stats["keyframes"] == len(truth) and refined.stats["matches_kept"] > 40
    xyt = np.stack([refined.poses[:, 0, 3], refined.poses[:, 1, 3],
                    np.arctan2(refined.poses[:, 1, 0], refined.poses[:, 0, 0])], axis=1)
    t1, r1 = _errors(xyt, truth)
    # the matches pull the burst back in translation (2-3.6 cm -> 0.3-1.5 cm); in rotation the
    # odometry between keyframes (sigma 0.1 deg) is trusted over a match (floor 1 deg), so it
    # comes back only a little (1.5 -> 1.2-1.3 deg)
    assert t1[misplaced].mean() < 0.4 * t0[misplaced].mean() and t1[misplaced].max() < 0.02
    assert r1[misplaced].max() < 1.4
    others = np.setdiff1d(np.arange(len(truth)), misplaced)
    assert t1[others].max() < 0.01 and r1[others].max() < 0.2  # nothing else was pushed away


def test_a_batch_of_scans_is_registered_to_its_cloud():
    truth, odom, world, submaps, clouds, scans = _scene()
    # scans 3..8 against the cloud of submap 0 (exact: no glitch before scan 20), from guesses off
    # by a few cm and a degree
    from scipy.spatial import cKDTree

    from submapslam.registration.point_to_line import line_normals

    cloud = clouds[0]
    normals = line_normals(cloud, cKDTree(cloud))
    idx = list(range(3, 9))
    rng = np.random.default_rng(1)
    in_cloud = _between(truth[0], truth[idx])  # the scans' true poses in the anchor frame of submap 0
    guesses = in_cloud + rng.uniform(-1, 1, (len(idx), 3)) * [0.08, 0.08, np.deg2rad(1.5)]
    res = match_scans(cloud, normals, [scans[i] for i in idx], guesses)
    d = _between(in_cloud, res.xyt)
    assert np.hypot(d[:, 0], d[:, 1]).max() < 0.005 and np.abs(np.rad2deg(d[:, 2])).max() < 0.05
    assert (res.fitness > 0.9).all() and (res.inlier_rmse < 0.005).all()


def test_a_scan_in_a_corridor_is_uncertain_along_the_corridor_in_its_own_frame():
    """The information is about the scan pose perturbed in the scan's frame (a Pose2
    between-factor's tangent): a scan turned 90 deg in a corridor along the cloud's x is uncertain
    along its own y."""
    from scipy.spatial import cKDTree

    from submapslam.registration.point_to_line import line_normals

    x = np.arange(-10.0, 10.0, 0.05)
    cloud = np.vstack([np.c_[x, np.full_like(x, -1.5)], np.c_[x, np.full_like(x, 1.5)]])
    pose = np.array([[0.3, 0.2, np.pi / 2]])  # the scan in the cloud's frame
    # the cloud's points (as poses with yaw 0) in the scan's frame, the 12 m of corridor around it
    scan = _between(pose, np.c_[cloud, np.zeros(len(cloud))])[np.abs(cloud[:, 0] - 0.3) < 6, :2]
    res = match_scans(cloud, line_normals(cloud, cKDTree(cloud)), [scan], pose)
    info = res.information[0]
    assert info[0, 0] > 0 and info[1, 1] < 1e-3 * info[0, 0]


def test_anchors_where_the_solve_bent_the_odometry_are_held_loosely():
    """Five anchors 2 m apart; the submap solve moved the last two 0.2 m sideways and turned the
    last one 1 deg: the anchors on either side of each bend get sigmas of 0.2 m / 1 deg, the rest
    the floor."""
    from submapslam.config import ScanRefineConfig
    from submapslam.scan_refine import anchor_sigmas

    odom = np.array([[2.0 * k, 0.0, 0.0] for k in range(5)])
    world = odom.copy()
    world[3:, 1] += 0.2
    world[4, 2] += np.deg2rad(1.0)
    cfg = ScanRefineConfig()
    sigma_m, sigma_rad = anchor_sigmas(odom, world, cfg)
    np.testing.assert_allclose(sigma_m, [0.01, 0.01, 0.2, 0.2, 0.01], atol=1e-9)
    np.testing.assert_allclose(np.rad2deg(sigma_rad), [cfg.anchor_sigma_deg] * 3 + [1.0, 1.0], atol=1e-9)
    flat, _ = anchor_sigmas(odom, world, ScanRefineConfig(anchor_bend_factor=0.0))
    np.testing.assert_allclose(flat, 0.01)


def test_a_noisy_scanners_submaps_keep_their_walls_for_the_matches():
    """The same room seen with 3 cm of range noise: with the wall noise the odometry measured
    allowed for in the submaps' line test, more keyframe-to-submap matches are kept (49-55 ->
    56-57 over four noise seeds); without it the noisy submaps lose wall points."""
    from submapslam.registration.wall_noise import WallNoise

    truth, odom, world, submaps, _, scans = _scene()
    rng = np.random.default_rng(1)
    noisy = [s * (1.0 + rng.normal(0.0, 0.03, len(s)) / np.hypot(s[:, 0], s[:, 1]))[:, None] for s in scans]
    noise = WallNoise()
    for s in noisy:
        noise.add(s)
    assert 0.015 < noise.sigma_m < 0.03
    clouds = []
    for idx in submaps:
        parts = []
        for i in idx:
            rel = _between(odom[idx[0]], odom[i])
            c, s = np.cos(rel[2]), np.sin(rel[2])
            parts.append(noisy[i] @ np.array([[c, s], [-s, c]]) + rel[:2])
        clouds.append(np.concatenate(parts))
    cfg = ScanRefineConfig(keyframe_step_m=0.15)
    kept = [refine_scans(odom, world, submaps, clouds, noisy, cfg, wall_noise_m=w).stats["matches_kept"]
            for w in (0.0, noise.sigma_m)]
    assert kept[1] > kept[0]
