"""Point-to-line refinement of planar odometry against recent scans."""

import numpy as np

from submapslam.registration.point_to_line import RecentScanMap

from .planar_scenes import wall_points

# a corridor along x (walls at y = +-1.5) with a side recess and a pillar face: constrained in x too
ROOM = [(-20, -1.5, 3, -1.5), (3, -1.5, 3, -3), (3, -3, 5, -3), (5, -3, 5, -1.5), (5, -1.5, 40, -1.5),
        (-20, 1.5, 8, 1.5), (8, 1.5, 8, 1.0), (8, 1.0, 8.4, 1.0), (8.4, 1.0, 8.4, 1.5), (8.4, 1.5, 40, 1.5)]
CORRIDOR = [(-20, -1.5, 40, -1.5), (-20, 1.5, 40, 1.5)]  # nothing along x


def _build(segments, upto):
    m = RecentScanMap(window=30, rebuild_every=1)
    for k in range(upto):
        pose = np.array([0.1 * k, 0.0, 0.0])
        m.add(wall_points(segments, pose), pose)
    return m


def test_refinement_recovers_the_pose_from_a_perturbed_guess():
    m = _build(ROOM, 20)
    truth = np.array([2.0, 0.0, 0.0])
    scan = wall_points(ROOM, truth)
    guess = truth + [0.08, -0.05, np.deg2rad(1.5)]
    refined, used = m.refine(scan, guess)
    assert used > 100
    assert np.linalg.norm(refined[:2] - truth[:2]) < 0.005 and abs(refined[2]) < np.deg2rad(0.1)


def test_a_plain_corridor_leaves_its_axis_to_the_prior():
    m = _build(CORRIDOR, 20)
    truth = np.array([2.0, 0.0, 0.0])
    scan = wall_points(CORRIDOR, truth)
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


def test_submap_matching_ends_point_to_line_where_sparse_samples_bias_point_to_point():
    """Two views of a room seen with a 1-degree laser and 6 m reach: walls end at the sensor's reach,
    where the last samples differ between the views. The match must land on the truth."""
    from submapslam.geometry import se2_to_matrix
    from submapslam.registration.planar import match_planar

    rooms = ROOM + [(0, -1.5, 0, -6), (12, 1.5, 12, 5)]
    a, b = np.array([0.0, 0.0, 0.0]), np.array([1.3, 0.05, np.deg2rad(2.0)])
    target, source = (wall_points(rooms, pose, max_range=6.0, beams=181) for pose in (a, b))
    target, source = np.c_[target, np.zeros(len(target))], np.c_[source, np.zeros(len(source))]
    guess = se2_to_matrix(1.3 + 0.1, 0.05 - 0.05, np.deg2rad(1.0))
    m = match_planar(source, target, initial_guess=guess, refine_only=True, inlier_distance=0.2)
    assert np.linalg.norm(m.xyt[:2] - b[:2]) < 0.01 and abs(m.xyt[2] - b[2]) < np.deg2rad(0.2)


def test_refinement_removes_the_odometry_lag_of_a_short_range_laser(tmp_path):
    """1-degree laser, 10 m reach: point-to-point KISS-ICP lags; the refined odometry drifts far less."""
    from datasets_synth import generate
    from submapslam.api import run_log
    from submapslam.config import config_from_dict
    from submapslam.evaluation.metrics import ate
    from submapslam.io.trajectory import Trajectory, read_tum

    log = generate("rectangle", tmp_path / "log", seed=0, laps=1,
                   sensor_options={"beams": 181, "range_noise": 0.03, "max_range": 10.0})
    gt = read_tum(log / "groundtruth_tum.txt")
    errors = {}
    for refine in (False, True):
        cfg = config_from_dict({"odometry": {"planar_point_to_line": refine}})
        result, _ = run_log(log, None, config=cfg, loops=False)
        errors[refine] = ate(Trajectory(result.timestamps, result.odometry_poses), gt)["rmse"]
    assert errors[True] < 0.6 * errors[False]


def test_the_first_scan_registered_again_against_the_scans_after_it():
    """The start's refit (``odometry.startup_refit_scans``): scans 1..20 sit where they truly are
    in the frame of a first scan whose own pose came out 0.3 deg and 3 cm off; registered against
    them, the first scan goes back where it belongs, and a refit without enough matches says so."""
    from submapslam.registration.point_to_line import refit_first_scan

    truths = np.array([[0.1 * k, 0.02 * np.sin(k / 4), np.deg2rad(0.2 * k)] for k in range(21)])
    frames = [wall_points(ROOM, t) for t in truths]
    start = truths.copy()
    start[0] += [0.03, -0.02, np.deg2rad(0.3)]
    refit = refit_first_scan(frames, start)
    assert refit is not None
    assert np.linalg.norm(refit[:2] - truths[0, :2]) < 0.003 and abs(refit[2] - truths[0, 2]) < np.deg2rad(0.02)
    assert refit_first_scan([frames[0][:30], *frames[1:]], start) is None  # 30 points: fewer than 50 matches


def _registered(xyt, points):
    """A planar scan as the odometry stage returns it: pose from ``xyt``, points in its frame."""
    from submapslam.geometry import se2_to_matrix
    from submapslam.odometry_stage import Registered

    frame = np.column_stack([points, np.zeros(len(points))])
    return Registered(se2_to_matrix(*xyt), frame, frame, np.asarray(xyt, dtype=np.float64))


def test_the_start_frame_holds_the_first_scans_and_rebases_the_rest_only_when_believable():
    """:class:`StartFrame`: nothing passes until the refit's window is full; then every held scan
    passes in order, the first at its own pose and the others moved by one rigid correction; later
    scans move by the same correction. A first scan whose refit would move it by more than the cap
    (here its odometry pose is 0.15 m off across the corridor) leaves the frame alone, and a log that ends before the
    window is full passes its scans as registered."""
    from submapslam.geometry import inverse, matrix_to_se2
    from submapslam.start_frame import MAX_TURN_RAD, StartFrame

    truths = np.array([[0.1 * k, 0.02 * np.sin(k / 4), np.deg2rad(0.2 * k)] for k in range(25)])
    scans = [_registered(t, wall_points(ROOM, t)) for t in truths]

    def shifted(offset):  # the first scan's odometry pose off by ``offset``, the others true
        first = _registered(truths[0] + offset, wall_points(ROOM, truths[0]))
        return [first, *scans[1:]]

    start = StartFrame(20)
    log = shifted([0.03, -0.02, np.deg2rad(0.3)])
    assert all(start.add(k, r) == [] for k, r in enumerate(log[:20]))
    released = start.add(20, log[20])
    assert [k for k, _ in released] == list(range(21))
    assert released[0][1] is log[0]
    correction = start.correction
    moved = matrix_to_se2(correction)
    assert abs(moved[2]) < MAX_TURN_RAD and abs(moved[2] - np.deg2rad(0.3)) < np.deg2rad(0.03)
    for k, r in released[1:]:
        np.testing.assert_allclose(r.pose, correction @ log[k].pose, atol=1e-12)
        np.testing.assert_allclose(r.xyt, matrix_to_se2(r.pose), atol=1e-12)
    (k, later), = start.add(21, log[21])
    assert k == 21 and np.allclose(inverse(later.pose) @ released[20][1].pose, inverse(log[21].pose) @ log[20].pose)

    far = StartFrame(20)
    for k, r in enumerate(shifted([0.0, 0.15, 0.0])[:21]):
        far.add(k, r)
    assert far.correction is None

    short = StartFrame(20)
    for k, r in enumerate(log[:5]):
        short.add(k, r)
    assert [r is log[k] for k, r in short.settle(refit=False)] == [True] * 5
    assert short.settle(refit=False) == [] and StartFrame(0).add(7, log[3]) == [(7, log[3])]
