import numpy as np

from submapslam.backend.pose_graph import PoseGraph, floor_information
from submapslam.config import BackendConfig
from submapslam.geometry import inverse, matrix_to_se2, se2_to_matrix
from submapslam.io.g2o import read_g2o_edges, write_g2o

INFO = np.diag([1e4, 1e4, 1e2, 1e2, 1e2, 1e4])  # planar-ish: tight z/roll/pitch


def square_truth(n_side=5, step=2.0):
    """Poses around a square loop, ``(4 * n_side, 4, 4)``."""
    poses, x, y, th = [], 0.0, 0.0, 0.0
    for _side in range(4):
        for _ in range(n_side):
            poses.append(se2_to_matrix(x, y, th))
            x += step * np.cos(th)
            y += step * np.sin(th)
        th += np.pi / 2
    return np.array(poses)


def build(truth, drift_deg=3.0, loops=(), robust="gnc"):
    g = PoseGraph(BackendConfig(robust_kernel=robust))
    bias = se2_to_matrix(0.0, 0.0, np.deg2rad(drift_deg))
    g.add_node(0, truth[0], np.diag([1e8] * 6))
    for k in range(1, len(truth)):
        meas = inverse(truth[k - 1]) @ truth[k] @ bias  # biased odometry
        g.add_node(k, g.pose(k - 1) @ meas)
        g.add_between(k - 1, k, meas, INFO, "odometry")
        g.update()
    for i, j, T in loops:
        g.add_between(i, j, T, INFO * 10, "loop")
    g.update(extra_iterations=2)
    return g


def position_error(g, truth):
    return max(np.linalg.norm(g.pose(k)[:2, 3] - truth[k][:2, 3]) for k in range(len(truth)))


def test_loop_closure_removes_most_of_the_drift():
    truth = square_truth()
    drifted = build(truth)
    closed = build(truth, loops=[(0, len(truth) - 1, inverse(truth[0]) @ truth[-1])])
    assert position_error(drifted, truth) > 2.0
    assert position_error(closed, truth) < 0.25 * position_error(drifted, truth)
    closed.optimize_batch()
    assert position_error(closed, truth) < 0.25 * position_error(drifted, truth)
    cov = closed.all_marginal_covariances()
    assert set(cov) == set(range(len(truth)))
    assert all(np.all(np.linalg.eigvalsh(c) > 0) for c in cov.values())
    # the far end of the chain is less certain than the anchored start
    assert np.trace(cov[10][3:, 3:]) > np.trace(cov[0][3:, 3:])


def test_gnc_rejects_a_false_loop_and_keeps_the_true_one():
    truth = square_truth()
    good = (0, len(truth) - 1, inverse(truth[0]) @ truth[-1])
    false = (2, 12, se2_to_matrix(0.5, 0.0, 0.0))  # claims two far-apart nodes coincide
    gnc = build(truth, loops=[good, false], robust="gnc")
    plain = build(truth, loops=[good, false], robust="none")
    weights = gnc.optimize_batch()
    assert weights[(2, 12)] < 0.1 and weights[(0, len(truth) - 1)] > 0.9
    plain.optimize_batch()
    assert position_error(gnc, truth) < 0.5
    assert position_error(plain, truth) > 2 * position_error(gnc, truth)


def test_floor_information_caps_confidence():
    info = np.diag([1e12] * 6)
    floored = floor_information(info, 0.05, np.deg2rad(0.5))
    cov = np.linalg.inv(floored)
    assert cov[3, 3] >= 0.05**2 * 0.999 and cov[0, 0] >= np.deg2rad(0.5) ** 2 * 0.999


def test_g2o_round_trip(tmp_path):
    truth = square_truth(2)
    g = build(truth, loops=[(0, 7, inverse(truth[0]) @ truth[7])])
    path = tmp_path / "g.g2o"
    edges = [(e.i, e.j, e.T_i_j, e.information, e.kind) for e in g.edges]
    write_g2o(path, np.array([g.pose(k) for k in range(len(truth))]), edges)
    vertices, read = read_g2o_edges(path)
    assert len(vertices) == len(truth) and len(read) == len(edges)
    for (i, j, T, info, _), (i2, j2, T2, info2) in zip(edges, read):
        assert (i, j) == (i2, j2)
        np.testing.assert_allclose(T2, T, atol=1e-7)
        np.testing.assert_allclose(info2, info, rtol=1e-7)
    np.testing.assert_allclose(matrix_to_se2(vertices[3]), matrix_to_se2(g.pose(3)), atol=1e-7)
    # gtsam reads it too
    import gtsam

    graph, initial = gtsam.readG2o(str(path), True)
    assert initial.size() == len(truth)


def test_cap_covariance_cuts_only_the_directions_beyond_the_caps():
    from submapslam.backend.pose_graph import cap_covariance

    # GTSAM order (rx, ry, rz, tx, ty, tz): a corridor along x (5 m sigma), 1 cm across, 0.1 deg yaw
    sig = np.array([1e-4, 1e-4, np.deg2rad(0.1), 5.0, 0.01, 1e-4])
    capped = cap_covariance(np.diag(sig**2), sigma_m=0.1, sigma_rad=np.deg2rad(20))
    assert np.isclose(np.sqrt(capped[3, 3]), 0.1)                      # the axis is cut to the cap
    assert np.allclose(np.sqrt(np.diag(capped))[[0, 1, 2, 4, 5]], sig[[0, 1, 2, 4, 5]])  # the rest kept
