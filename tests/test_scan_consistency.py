"""Loop-pair misfit: a log's own scans judge a trajectory where the robot came back."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from submapslam.evaluation.derived_relations import derive_relations
from submapslam.evaluation.metrics import ate, relations_error, worst_pose_times
from submapslam.evaluation.scan_consistency import (
    loop_pair_check,
    loop_pair_comparison,
    loop_pairs,
    pair_misfit,
    scan_matched_relations,
)
from submapslam.geometry import se2_to_matrix
from submapslam.io.scan_lookup import scans_at
from submapslam.io.trajectory import carmen_reference_trajectory
from submapslam.trajectory import Trajectory

from .conftest import shared_data


def _room_points() -> np.ndarray:
    """Walls of a 10 x 6 m room with a pillar, every 2 cm: ``(N, 2)`` [m], world frame."""
    s = np.arange(0.0, 1.0, 0.002)
    walls = [np.c_[10 * s - 5, np.full_like(s, -3)], np.c_[10 * s - 5, np.full_like(s, 3)],
             np.c_[np.full_like(s, -5), 6 * s - 3], np.c_[np.full_like(s, 5), 6 * s - 3],
             np.c_[0.5 * s + 1, np.full_like(s, 0.5)], np.c_[np.full_like(s, 1), 0.5 * s]]
    return np.vstack(walls)


def _two_passes(shift_second: float = 0.0) -> tuple[Trajectory, Trajectory, dict[float, np.ndarray]]:
    """The true path (two laps of a small square, 40 s each) and an estimate whose second lap is
    shifted by ``shift_second`` m in x; scans: the room seen from each true pose (robot frame)."""
    corners = [(-2, -1.5, 0.0), (2, -1.5, np.pi / 2), (2, 1.5, np.pi), (-2, 1.5, -np.pi / 2)]
    world = _room_points()
    stamps, true, est, scans = [], [], [], {}
    for lap in range(2):
        for k, (x, y, yaw) in enumerate(corners):
            t = 40.0 * lap + 10.0 * k
            T = se2_to_matrix(x, y, yaw)
            local = (world - T[:2, 3]) @ T[:2, :2]  # world -> robot frame
            scans[t] = np.c_[local, np.zeros(len(local))]
            stamps.append(t)
            true.append(T)
            est.append(se2_to_matrix(x + (shift_second if lap else 0.0), y, yaw))
    ts = np.array(stamps)
    return Trajectory(ts, np.array(true)), Trajectory(ts, np.array(est)), scans


def test_loop_pairs_are_near_on_different_passes() -> None:
    truth, _, _ = _two_passes()
    pairs = loop_pairs(truth, radius_m=0.5, max_turn_deg=30.0, min_dt=30.0)
    # each corner with itself one lap later, nothing within one lap (10 s apart) or across corners
    assert pairs.shape == (4, 2)
    np.testing.assert_allclose(pairs[:, 1] - pairs[:, 0], 40.0)
    assert len(loop_pairs(truth, radius_m=0.5, max_turn_deg=30.0, min_dt=50.0)) == 0


def test_misfit_measures_the_offset_between_passes() -> None:
    truth, _, scans = _two_passes()
    pairs = loop_pairs(truth, radius_m=0.5, min_dt=30.0)
    np.testing.assert_array_less(pair_misfit(truth, scans, pairs), 0.005)  # the 2 cm sampling floor
    for shift in (0.1, 0.3):
        _, shifted, _ = _two_passes(shift)
        misfit = pair_misfit(shifted, scans, pairs)
        # the walls across x part by the shift, those along x slide on themselves: the median lies between
        assert np.all((misfit > 0.3 * shift) & (misfit <= shift + 0.005)), misfit


def test_the_pairs_at_the_worst_poses_are_compared_apart() -> None:
    """One corner of the estimate's second lap off by 0.3 m: that pose has the largest error, and the
    comparison at the worst poses holds just its pair, where the scans side with the reference."""
    truth, _, scans = _two_passes()
    poses = truth.poses.copy()
    poses[5] = se2_to_matrix(0.3, 0.0, 0.0) @ poses[5]
    estimate = Trajectory(truth.timestamps, poses)
    figures = ate(estimate, truth)
    worst = worst_pose_times(figures, share=0.1)
    assert worst.tolist() == [truth.timestamps[5]]  # 10 % of 8 poses: the one moved
    m = loop_pair_comparison(estimate, truth, lambda times: scans, worst_at=worst)
    assert m["compared"] == 4 and m["estimate_worse"] == 1 and m["reference_worse"] == 0
    w = m["at_worst"]
    assert w["compared"] == 1 and w["estimate_worse"] == 1 and w["reference_worse"] == 0
    assert w["estimate_median_m"] > 0.09 and w["reference_median_m"] < 0.005
    assert "at_worst" not in loop_pair_comparison(estimate, truth, lambda times: scans)
    assert loop_pair_comparison(estimate, truth, lambda times: scans, worst_at=np.array([5.0]))["at_worst"] is None


def test_missing_pose_or_scan_gives_nan() -> None:
    truth, _, scans = _two_passes()
    pairs = np.array([[0.0, 40.0], [0.0, 41.5], [7.0, 40.0]])
    misfit = pair_misfit(truth, scans, pairs)
    assert np.isfinite(misfit[0]) and np.isnan(misfit[1]) and np.isnan(misfit[2])


def _write_scans(folder, stamps, scans_xy) -> None:
    """A folder log of planar scans (KITTI ``scans/NNNNNN.bin``, ``times.txt``, ``meta.yaml``)."""
    (folder / "scans").mkdir(parents=True)
    for k, xy in enumerate(scans_xy):
        np.c_[xy, np.zeros((len(xy), 2))].astype(np.float32).tofile(folder / "scans" / f"{k:06d}.bin")
    (folder / "times.txt").write_text("".join(f"{t:.6f}\n" for t in stamps))
    (folder / "meta.yaml").write_text("planar: true\n")


def test_scan_matched_relations_recover_the_truth_and_drop_corridors(tmp_path) -> None:
    """A room seen from three poses: relations measured by matching the scans land on the true
    relative poses although the reference is 3-4 cm / 0.5-0.8 deg off; in a featureless corridor
    the scans cannot fix the pose along it, and its relation is dropped as ambiguous."""
    room = _room_points()
    corridor = np.vstack([np.c_[np.linspace(-20, 20, 2000), np.full(2000, y)] for y in (-1.0, 1.0)])
    truth = [se2_to_matrix(-2.0, -1.5, 0.1), se2_to_matrix(-1.5, -1.4, 0.2), se2_to_matrix(-1.0, -1.2, 0.35)]
    stamps = np.array([0.0, 1.0, 2.0])
    for name, world, poses in (("room", room, truth),
                               ("corridor", corridor, [se2_to_matrix(x, 0.0, 0.0) for x in (0.0, 0.4, 0.8)])):
        scans = [(world - T[:2, 3]) @ T[:2, :2] for T in poses]
        scans = [xy[np.linalg.norm(xy, axis=1) < 15.0] for xy in scans]
        _write_scans(tmp_path / name, stamps, scans)
        noisy = [T @ se2_to_matrix(0.03 * (k % 2), -0.04 * (k > 0), np.deg2rad(0.5 + 0.3 * k)) for k, T in enumerate(poses)]
        reference = Trajectory(stamps, np.array(noisy))
        derived = derive_relations(reference)
        assert len(derived) == 2
        if name == "room":
            matched, counts = scan_matched_relations(reference, derived, functools.partial(scans_at, tmp_path / name))
            assert counts["matched"] == 2 and len(matched) == 2
            exact = relations_error(Trajectory(stamps, np.array(poses)), matched)
            assert exact["trans_mean"] < 1e-3 and exact["rot_mean_deg"] < 0.02
            assert relations_error(reference, matched)["trans_mean"] > 0.02  # the reference is scored on them
        else:
            with pytest.raises(Exception, match="none of the 2 relations.*'ambiguous': 2"):
                scan_matched_relations(reference, derived, functools.partial(scans_at, tmp_path / name))


def test_real_corrected_log_against_a_bent_copy() -> None:
    """MIT CSAIL's corrected log: its loop pairs fit within a few cm; the same log with its second half
    turned by 2 deg about its middle pose (a bent map) parts them where the halves meet."""
    raw = shared_data("carmen", "mit-csail.clf.bz2")
    ref = carmen_reference_trajectory(shared_data("carmen", "corrected", "mit-csail-corrected.log.gz"), raw)
    pairs = loop_pairs(ref)
    assert len(pairs) > 40
    scans = scans_at(raw, pairs.ravel())
    good = pair_misfit(ref, scans, pairs)
    assert np.count_nonzero(np.isfinite(good)) == len(pairs)
    half = len(ref) // 2
    pivot = ref.poses[half]
    bend = pivot @ se2_to_matrix(0.0, 0.0, np.deg2rad(2.0)) @ np.linalg.inv(pivot)
    bent_poses = ref.poses.copy()
    bent_poses[half:] = bend @ ref.poses[half:]
    bent = pair_misfit(Trajectory(ref.timestamps, bent_poses), scans, pairs)
    across = (pairs[:, 0] < ref.timestamps[half]) & (pairs[:, 1] >= ref.timestamps[half])
    assert across.sum() > 10
    assert np.median(good) < 0.06
    assert np.median(bent[across] - good[across]) > 0.1
    np.testing.assert_allclose(bent[~across], good[~across], atol=1e-9)  # pairs within one half: unchanged


def test_no_scan_at_the_times_or_a_3d_log_is_one_clear_error(tmp_path) -> None:
    raw = shared_data("carmen", "mit-csail.clf.bz2")
    with pytest.raises(Exception, match="no scan of .* within"):
        scans_at(raw, [1.0, 2.0])
    from datasets_synth import generate

    cloud = generate("outdoor", tmp_path / "3d", seed=0, laps=1, max_scans=3)
    with pytest.raises(Exception, match="holds 3D scans.*2D laser log"):
        scans_at(cloud, [0.0])


def test_eval_cli_scores_both_trajectories_on_the_log_scans(tmp_path) -> None:
    """``eval EST REF --scans LOG``: the corrected log against itself scores alike on every pair; a
    reference that never comes back is one clear line."""
    import json

    from typer.testing import CliRunner

    from submapslam.cli import app

    raw = shared_data("carmen", "mit-csail.clf.bz2")
    corrected = shared_data("carmen", "corrected", "mit-csail-corrected.log.gz")
    from submapslam.io.trajectory import write_tum

    est = tmp_path / "corrected_tum.txt"
    write_tum(est, carmen_reference_trajectory(corrected, raw))
    runner = CliRunner()
    r = runner.invoke(app, ["eval", str(est), str(corrected), "--raw-log", str(raw), "--scans", str(raw),
                            "--json", str(tmp_path / "e.json")])
    assert r.exit_code == 0, r.output
    assert "loop-pair misfit" in r.output
    m = json.loads((tmp_path / "e.json").read_text())["loop_pair_misfit"]
    assert m["compared"] > 40 and m["estimate_median_m"] == pytest.approx(m["reference_median_m"], abs=1e-6)
    assert m["reference_median_m"] < 0.06
    assert m["estimate_worse"] == m["reference_worse"] == 0
    # the same trajectory: its "worst" poses are any; where a compared pair touches them, the same misfit
    worst = m["at_worst"]
    assert m["worst_share"] == 0.1 and (worst is None) == ("% largest errors" not in r.output)
    if worst is not None:
        assert worst["estimate_median_m"] == pytest.approx(worst["reference_median_m"], abs=1e-6)
    r = runner.invoke(app, ["eval", str(est), str(corrected), "--raw-log", str(raw), "--scans", str(raw),
                            "--derive-relations", "--match-relations", "--json", str(tmp_path / "m.json")])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "m.json").read_text())
    assert doc["relations_matching"]["matched"] == doc["relations"]["n"] > 100
    assert doc["relations"]["trans_mean"] == pytest.approx(doc["reference_relations"]["trans_mean"], abs=1e-5)
    r = runner.invoke(app, ["eval", str(est), str(corrected), "--raw-log", str(raw), "--match-relations"])
    assert r.exit_code == 1 and "needs the log's scans" in r.output.strip().splitlines()[-1]
    lap = tmp_path / "lap"
    assert runner.invoke(app, ["synth", "rectangle", "--out", str(lap), "--laps", "1", "--max-scans", "60"]).exit_code == 0
    gt = str(lap / "groundtruth_tum.txt")
    r = runner.invoke(app, ["eval", gt, gt, "--scans", str(lap)])
    assert r.exit_code == 1 and "Traceback" not in r.output
    assert "no loop pairs" in r.output.strip().splitlines()[-1]


def test_the_report_checks_a_planar_run_against_its_reference_on_the_log_scans() -> None:
    """``report --ref`` gets the loop-pair misfit of a 2D run and its reference; a 3D run (whose
    scans are clouds) and a run whose log is not at hand get none."""
    from types import SimpleNamespace

    from submapslam.api import _scan_check

    raw = shared_data("carmen", "mit-csail.clf.bz2")
    ref = carmen_reference_trajectory(shared_data("carmen", "corrected", "mit-csail-corrected.log.gz"), raw)
    record = SimpleNamespace(summary={"planar": True}, poses=ref, provenance={"path": str(raw)})
    check = _scan_check(record, ref, None)  # the log input.json names
    assert check is not None and check["compared"] > 40 and check["estimate_worse"] == check["reference_worse"] == 0
    assert _scan_check(SimpleNamespace(**{**vars(record), "summary": {"planar": False}}), ref, raw) is None
    assert _scan_check(SimpleNamespace(**{**vars(record), "provenance": {"path": "/nowhere/log.clf"}}), ref, None) is None


def test_the_report_says_which_trajectory_the_scans_side_with_at_the_worst_poses() -> None:
    """The report's scan check names the misfit at the run's largest errors when there is one."""
    from submapslam.evaluation.html_report import _scan_check as scan_check_html

    truth, _, scans = _two_passes()
    poses = truth.poses.copy()
    poses[5] = se2_to_matrix(0.3, 0.0, 0.0) @ poses[5]
    estimate = Trajectory(truth.timestamps, poses)
    m = loop_pair_check(estimate, truth, lambda times: scans, ate(estimate, truth))
    assert m["worst_share"] == 0.1 and m["at_worst"]["compared"] == 1
    html = scan_check_html(m, "truth.txt")
    assert "Where this run is farthest from the reference (its 10 % largest errors, 1 pairs)" in html
    assert "1 / 0 pairs are worse under each" in html
    assert "farthest" not in scan_check_html({**m, "at_worst": None}, "truth.txt")
