"""Relations derived from a reference trajectory: pairs close in time and pairs across loops."""

import numpy as np
import pytest

from submapslam.errors import SubmapSlamError
from submapslam.evaluation.derived_relations import count_loop_relations, derive_relations
from submapslam.evaluation.metrics import relations_error
from submapslam.geometry import se2_to_matrix
from submapslam.trajectory import Trajectory


def _square_laps(laps: int = 2, side: float = 10.0, step: float = 0.5) -> Trajectory:
    """A robot driving ``laps`` times around a square, one pose per ``step`` metres, 1 s apart."""
    poses = []
    for _ in range(laps):
        for k in range(4):
            yaw = k * np.pi / 2
            start = [(0, 0), (side, 0), (side, side), (0, side)][k]
            for d in np.arange(0.0, side, step):
                poses.append(se2_to_matrix(start[0] + d * np.cos(yaw), start[1] + d * np.sin(yaw), yaw))
    return Trajectory(np.arange(len(poses), dtype=float), np.array(poses))


def test_local_and_loop_relations_are_the_reference_relative_poses():
    ref = _square_laps()
    rel = derive_relations(ref, loop_min_dt=30.0, loop_radius_m=0.3)
    n = len(ref)
    assert len(rel) - count_loop_relations(rel) == n - 1  # every pose with the next one
    loops = np.abs(rel.t_b - rel.t_a) >= 30.0
    assert count_loop_relations(rel) == n // 2  # each pose of lap 1 with itself on lap 2
    np.testing.assert_allclose(rel.t_b[loops] - rel.t_a[loops], n // 2)
    np.testing.assert_allclose(rel.T_a_b[loops], np.broadcast_to(np.eye(4), (n // 2, 4, 4)), atol=1e-9)
    np.testing.assert_allclose(rel.T_a_b[0], se2_to_matrix(0.5, 0.0, 0.0), atol=1e-12)
    exact = relations_error(ref, rel)
    assert exact["trans_mean"] < 1e-9 and exact["rot_mean_deg"] < 1e-6


def test_relations_error_sees_a_drifting_estimate_and_a_wrong_loop():
    ref = _square_laps()
    rel = derive_relations(ref, loop_min_dt=30.0, loop_radius_m=0.3)
    n = len(ref)
    drift = np.array([se2_to_matrix(0.0, 0.0, np.deg2rad(0.05) * k) for k in range(n)])
    est = Trajectory(ref.timestamps, drift @ ref.poses)  # the world turns 0.05 deg per pose
    err = relations_error(est, rel)
    assert err["rot_mean_deg"] > 0.3  # the loop relations see the accumulated 4-deg turn
    local = derive_relations(ref, loop_min_dt=1e9)  # no pairs across loops
    assert count_loop_relations(local) == 0
    assert relations_error(est, local)["rot_mean_deg"] == pytest.approx(0.05, abs=1e-6)


def test_min_dt_thins_the_local_pairs_and_one_pose_is_an_error():
    ref = _square_laps(laps=1)
    rel = derive_relations(ref, local_min_dt=4.0)
    np.testing.assert_allclose(rel.t_b - rel.t_a, 4.0)
    with pytest.raises(SubmapSlamError, match="at least two"):
        derive_relations(ref.subset(np.array([0])))
