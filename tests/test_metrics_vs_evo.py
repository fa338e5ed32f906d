"""Our trajectory metrics against evo's (the field's standard) on real trajectories.

The same association (nearest stamp within ``max_diff``), the same Umeyama alignment (SE(3),
Sim(3), none), the same APE statistics and the same RPE over frame pairs (evo with
``all_pairs=True``: every start pose, as ours). Real pairs: the Intel lab's raw odometry
against its corrected (reference) log, and KITTI ground-truth paths against a copy with
drift, noise, a scale error, dropped poses and jittered stamps.

Not compared: RPE in metres (evo takes consecutive segments, or with ``all_pairs`` the pair
whose path length is nearest ``delta`` within a tolerance; ours takes, from every pose, the
first pose at least ``delta`` metres further) and SE(2) alignment (evo has none; on planar
data it equals SE(3), checked on Intel).
"""

import numpy as np
import pytest

from submapslam.evaluation.metrics import associate, ate, rpe
from submapslam.geometry import se3_exp
from submapslam.trajectory import Trajectory

from .conftest import shared_data

evo_metrics = pytest.importorskip("evo.core.metrics", reason="evo is not installed (pip install -e '.[test]')")
from evo.core import sync  # noqa: E402
from evo.core.trajectory import PoseTrajectory3D  # noqa: E402

MAX_DIFF = 0.02
STATS = ("rmse", "mean", "median", "std", "max")


def evo_pair(est: Trajectory, ref: Trajectory) -> tuple[PoseTrajectory3D, PoseTrajectory3D]:
    """evo's associated ``(reference, estimate)``."""
    r = PoseTrajectory3D(poses_se3=list(ref.poses), timestamps=ref.timestamps.copy())
    e = PoseTrajectory3D(poses_se3=list(est.poses), timestamps=est.timestamps.copy())
    return sync.associate_trajectories(r, e, max_diff=MAX_DIFF)


def evo_ape(est: Trajectory, ref: Trajectory, align: str) -> tuple[dict, dict]:
    """evo's APE statistics: translation [m] and rotation angle [deg]."""
    r, e = evo_pair(est, ref)
    if align != "none":
        e.align(r, correct_scale=align == "sim3")
    out = []
    for relation in (evo_metrics.PoseRelation.translation_part, evo_metrics.PoseRelation.rotation_angle_deg):
        ape = evo_metrics.APE(relation)
        ape.process_data((r, e))
        out.append(ape.get_all_statistics() | {"errors": ape.error})
    return out[0], out[1]


def evo_rpe(est: Trajectory, ref: Trajectory, delta: int) -> tuple[dict, dict]:
    """evo's RPE statistics over every pose pair ``delta`` frames apart: translation, rotation [deg]."""
    r, e = evo_pair(est, ref)
    out = []
    for relation in (evo_metrics.PoseRelation.translation_part, evo_metrics.PoseRelation.rotation_angle_deg):
        m = evo_metrics.RPE(relation, delta=delta, delta_unit=evo_metrics.Unit.frames, all_pairs=True)
        m.process_data((r, e))
        out.append(m.get_all_statistics() | {"n": len(m.error)})
    return out[0], out[1]


def check_against_evo(est: Trajectory, ref: Trajectory) -> None:
    # association: the same pose pairs
    i_e, i_r = associate(est, ref, MAX_DIFF)
    r, e = evo_pair(est, ref)
    np.testing.assert_array_equal(ref.timestamps[i_r], r.timestamps)
    np.testing.assert_array_equal(est.timestamps[i_e], e.timestamps)
    for align in ("se3", "sim3", "none"):
        ours = ate(est, ref, align=align, max_diff=MAX_DIFF)
        trans, rot = evo_ape(est, ref, align)
        assert ours["n"] == len(trans["errors"])
        np.testing.assert_allclose(ours["errors"], trans["errors"], rtol=1e-7, atol=1e-9, err_msg=align)
        for k in STATS:
            assert ours[k] == pytest.approx(trans[k], rel=1e-7, abs=1e-9), (align, k)
        assert ours["rotation_rmse_deg"] == pytest.approx(rot["rmse"], rel=1e-6, abs=1e-7), align
    for delta in (1, 10):
        ours = rpe(est, ref, delta=delta, unit="frames", max_diff=MAX_DIFF)
        trans, rot = evo_rpe(est, ref, delta)
        assert ours["n"] == trans["n"]
        for k in STATS:
            assert ours[k] == pytest.approx(trans[k], rel=1e-7, abs=1e-9), (delta, k)
            assert ours[f"rotation_{k}"] == pytest.approx(rot[k], rel=1e-6, abs=1e-7), (delta, k)


def test_intel_raw_odometry_against_the_corrected_log():
    from submapslam.io.trajectory import carmen_reference_trajectory, read_carmen_trajectory

    raw = shared_data("carmen", "intel.clf.bz2")
    ref = carmen_reference_trajectory(shared_data("carmen", "corrected", "intel-corrected.log.gz"), raw)
    odometry = read_carmen_trajectory(raw)
    check_against_evo(odometry, ref)
    a = ate(odometry, ref, max_diff=MAX_DIFF)
    assert a["n"] == len(ref) and a["rmse"] > 1.0  # raw odometry drifts metres: a real test, not zeros
    # planar data: the yaw-only alignment is the SE(3) one
    assert ate(odometry, ref, align="se2", max_diff=MAX_DIFF)["rmse"] == pytest.approx(a["rmse"], rel=1e-9)


@pytest.mark.parametrize("sequence", ["00", "07"])
def test_kitti_ground_truth_against_a_drifting_copy(sequence):
    from submapslam.io.trajectory import read_kitti

    gt = read_kitti(shared_data("trajectories", "kitti_gt", f"{sequence}.txt.xz"))
    # the files' rotations have 6 significant digits, orthonormal only to ~1e-6: projected onto
    # SO(3) first (evo's rotation angle projects, ours reads the trace: they differ by ~1e-6 rad)
    U, _, Vt = np.linalg.svd(gt.poses[:, :3, :3])
    poses = gt.poses.copy()
    poses[:, :3, :3] = U @ Vt
    ref = Trajectory(0.1 * gt.timestamps, poses)  # 10 Hz
    rng = np.random.default_rng(int(sequence))
    drift = np.eye(4)
    poses = []
    for T in ref.poses:  # random-walk drift of the whole frame, white noise per pose
        drift = drift @ se3_exp(rng.normal(0, [0.01, 0.01, 0.005, 2e-4, 2e-4, 5e-4]))
        poses.append(drift @ T @ se3_exp(rng.normal(0, [0.05, 0.05, 0.05, 1e-3, 1e-3, 1e-3])))
    poses = np.array(poses)
    poses[:, :3, 3] *= 1.03                                            # 3 % scale error
    G = se3_exp([100.0, -50.0, 3.0, 0.02, -0.01, 1.2])                 # another world frame
    keep = np.ones(len(ref), dtype=bool)
    keep[::7] = False                                                   # dropped poses
    est = Trajectory(ref.timestamps[keep] + rng.uniform(-0.015, 0.015, keep.sum()), G @ poses[keep])
    check_against_evo(est, ref)
    a_sim3 = ate(est, ref, align="sim3", max_diff=MAX_DIFF)
    assert a_sim3["scale"] == pytest.approx(1 / 1.03, rel=0.02)
    assert a_sim3["rmse"] < ate(est, ref, align="se3", max_diff=MAX_DIFF)["rmse"]
