"""Point-to-line refinement of planar odometry against recent scans."""

import numpy as np

from submapslam.planar_refine import RecentScanMap


def _wall_points(segments, pose_xyt, max_range=8.0, beams=361):
    """Ray-cast a 180-degree planar scan of wall ``segments`` from ``pose_xyt``; points in the sensor frame."""
    x, y, th = pose_xyt
    pts = []
    for a in np.linspace(-np.pi / 2, np.pi / 2, beams):
        d = np.array([np.cos(th + a), np.sin(th + a)])
        best = np.inf
        for x0, y0, x1, y1 in segments:
            e = np.array([x1 - x0, y1 - y0])
            M = np.array([d, -e]).T
            if abs(np.linalg.det(M)) < 1e-12:
                continue
            t, u = np.linalg.solve(M, np.array([x0 - x, y0 - y]))
            if t > 0 and 0 <= u <= 1:
                best = min(best, t)
        if best < max_range:
            pts.append([best * np.cos(a), best * np.sin(a)])
    return np.array(pts)


# a corridor along x (walls at y = +-1.5) with a side recess and a pillar face: constrained in x too
ROOM = [(-20, -1.5, 3, -1.5), (3, -1.5, 3, -3), (3, -3, 5, -3), (5, -3, 5, -1.5), (5, -1.5, 40, -1.5),
        (-20, 1.5, 8, 1.5), (8, 1.5, 8, 1.0), (8, 1.0, 8.4, 1.0), (8.4, 1.0, 8.4, 1.5), (8.4, 1.5, 40, 1.5)]
CORRIDOR = [(-20, -1.5, 40, -1.5), (-20, 1.5, 40, 1.5)]  # nothing along x


def _build(segments, upto):
    m = RecentScanMap(window=30, rebuild_every=1)
    for k in range(upto):
        pose = np.array([0.1 * k, 0.0, 0.0])
        m.add(_wall_points(segments, pose), pose)
    return m


def test_refinement_recovers_the_pose_from_a_perturbed_guess():
    m = _build(ROOM, 20)
    truth = np.array([2.0, 0.0, 0.0])
    scan = _wall_points(ROOM, truth)
    guess = truth + [0.08, -0.05, np.deg2rad(1.5)]
    refined, used = m.refine(scan, guess)
    assert used > 100
    assert np.linalg.norm(refined[:2] - truth[:2]) < 0.005 and abs(refined[2]) < np.deg2rad(0.1)


def test_a_plain_corridor_leaves_its_axis_to_the_prior():
    m = _build(CORRIDOR, 20)
    truth = np.array([2.0, 0.0, 0.0])
    scan = _wall_points(CORRIDOR, truth)
    prior = truth + [0.03, 0.0, 0.0]          # wheel odometry says 3 cm further
    guess = truth + [-0.2, 0.06, 0.01]        # the ICP result slid back along the corridor
    refined, _ = m.refine(scan, guess, prior_xyt=prior)
    assert abs(refined[0] - prior[0]) < 0.01   # along the axis: the prior decides
    assert abs(refined[1]) < 0.005 and abs(refined[2]) < np.deg2rad(0.1)  # across it: the walls do


def test_without_a_map_the_guess_is_returned():
    m = RecentScanMap()
    guess = np.array([1.0, 2.0, 0.3])
    refined, used = m.refine(np.random.default_rng(0).normal(size=(50, 2)), guess)
    assert used == 0 and np.array_equal(refined, guess)
