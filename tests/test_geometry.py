import numpy as np
import pytest

from submapslam import geometry as g


def random_pose(rng):
    T = np.eye(4)
    T[:3, :3] = g.so3_exp(rng.normal(size=3))
    T[:3, 3] = rng.normal(size=3) * 5
    return T


def test_inverse_and_relative():
    rng = np.random.default_rng(1)
    A, B = random_pose(rng), random_pose(rng)
    np.testing.assert_allclose(g.inverse(A) @ A, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(A @ g.relative(A, B), B, atol=1e-12)
    stack = np.stack([A, B])
    np.testing.assert_allclose(g.inverse(stack)[1], g.inverse(B), atol=1e-12)


def test_quaternion_round_trip_and_sign():
    rng = np.random.default_rng(2)
    for _ in range(50):
        R = g.so3_exp(rng.normal(size=3) * 2)
        q = g.matrix_to_quat(R)
        assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(g.quat_to_matrix(q), R, atol=1e-9)
    # 90 deg about z: q = (0, 0, sin45, cos45)
    np.testing.assert_allclose(g.matrix_to_quat(g.se2_to_matrix(0, 0, np.pi / 2)[:3, :3]),
                               [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)


def test_so3_log_exp_including_near_pi():
    for w in ([0.1, -0.2, 0.3], [0, 0, np.pi - 1e-7], [1e-10, 0, 0]):
        np.testing.assert_allclose(g.so3_exp(g.so3_log(g.so3_exp(w))), g.so3_exp(w), atol=1e-6)


def test_se2_helpers():
    T = g.se2_to_matrix(1.0, -2.0, 3.0)
    np.testing.assert_allclose(g.matrix_to_se2(T), [1.0, -2.0, 3.0])
    stack = g.se2_array_to_matrices([[1.0, -2.0, 3.0], [0, 0, 0]])
    np.testing.assert_allclose(stack[0], T)
    assert g.is_planar(stack)
    assert not g.is_planar(g.se3_exp([0, 0, 0, 0.1, 0, 0]))
    assert g.wrap_angle(3 * np.pi) == pytest.approx(-np.pi)


def test_transform_points():
    T = g.se2_to_matrix(1.0, 0.0, np.pi / 2)
    np.testing.assert_allclose(g.transform_points(T, [[1.0, 0.0, 0.0]]), [[1.0, 1.0, 0.0]], atol=1e-12)


def test_blend_poses_follows_the_geodesic():
    from submapslam.geometry import blend_poses, rotation_angle, so3_exp

    A = np.eye(4)
    B = np.eye(4)
    B[:3, :3] = so3_exp(np.array([0.0, 0.0, 1.0]))
    B[:3, 3] = [2.0, 0.0, 4.0]
    assert np.allclose(blend_poses(A, B, 0.0), A) and np.allclose(blend_poses(A, B, 1.0), B)
    half = blend_poses(A, B, 0.5)
    assert np.isclose(rotation_angle(half), 0.5) and np.allclose(half[:3, 3], [1.0, 0.0, 2.0])
