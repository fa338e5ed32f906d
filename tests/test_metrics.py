import numpy as np
import pytest

from submapslam.errors import SubmapSlamError
from submapslam.evaluation.metrics import (
    associate,
    ate,
    kitti_segment_error,
    relations_error,
    rpe,
    umeyama,
)
from submapslam.geometry import se2_to_matrix, se3_exp
from submapslam.trajectory import Relations, Trajectory


def line(n=50, step=1.0, t0=0.0):
    poses = np.array([se2_to_matrix(k * step, 0.0, 0.0) for k in range(n)])
    return Trajectory(t0 + np.arange(n, dtype=float), poses)


def square(n=40):
    poses = []
    for k in range(n):
        a = 2 * np.pi * k / n
        poses.append(se2_to_matrix(10 * np.cos(a), 10 * np.sin(a), a + np.pi / 2))
    return Trajectory(np.arange(n, dtype=float), np.array(poses))


def test_identical_trajectories_have_zero_error():
    t = square()
    assert ate(t, t)["rmse"] == pytest.approx(0.0, abs=1e-9)
    assert rpe(t, t)["rmse"] == pytest.approx(0.0, abs=1e-9)


def test_rigid_offset_removed_by_se3_alignment_but_not_by_none():
    ref = square()
    T = se3_exp([3.0, -2.0, 0.5, 0.1, 0.2, 0.3])
    est = Trajectory(ref.timestamps, T @ ref.poses)
    assert ate(est, ref, align="se3")["rmse"] == pytest.approx(0.0, abs=1e-6)
    # without alignment every position error is |T p - p|; check against a hand computation
    expected = np.linalg.norm((T @ ref.poses)[:, :3, 3] - ref.positions, axis=1)
    assert ate(est, ref, align="none")["rmse"] == pytest.approx(np.sqrt(np.mean(expected**2)))


def test_sim3_recovers_scale():
    ref = square()
    est = Trajectory(ref.timestamps, ref.poses.copy())
    est.poses[:, :3, 3] *= 0.5
    a = ate(est, ref, align="sim3")
    assert a["scale"] == pytest.approx(2.0, rel=1e-6) and a["rmse"] == pytest.approx(0.0, abs=1e-6)
    assert ate(est, ref, align="se3")["rmse"] > 1.0
    T, s = umeyama(est.positions, ref.positions, with_scale=True)
    assert s == pytest.approx(2.0)


def test_rpe_sees_one_jump():
    ref = line()
    est = Trajectory(ref.timestamps, ref.poses.copy())
    est.poses[25:, 1, 3] += 0.3  # a 0.3 m sideways jump between frames 24 and 25
    r = rpe(est, ref, delta=1)
    assert r["max"] == pytest.approx(0.3, abs=1e-9)
    assert r["n"] == 49 and r["median"] == pytest.approx(0.0, abs=1e-9)


def test_kitti_segment_error_on_a_stretched_line():
    ref = line(201, 1.0)
    est = Trajectory(ref.timestamps, ref.poses.copy())
    est.poses[:, 0, 3] *= 1.02  # 2 % too long
    seg = kitti_segment_error(est, ref, lengths=(50.0, 100.0))
    assert seg["trans_percent"] == pytest.approx(2.0, rel=1e-6)


def test_relations_metric():
    ref = line(10)
    rel = Relations(np.array([0.0, 2.0]), np.array([1.0, 5.0]),
                    np.array([se2_to_matrix(1.0, 0, 0), se2_to_matrix(3.0, 0.4, 0)]))
    r = relations_error(ref, rel)
    assert r["n"] == 2
    assert r["trans_mean"] == pytest.approx(0.2) and r["trans_std"] == pytest.approx(0.2)


def test_association_tolerance_and_failure():
    a = line(10)
    b = line(10, t0=0.005)
    i_e, i_r = associate(a, b, max_diff=0.01)
    assert len(i_e) == 10
    with pytest.raises(SubmapSlamError, match="no timestamps match"):
        associate(a, line(10, t0=100.0))
