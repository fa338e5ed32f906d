import numpy as np
import pytest

from submapslam.errors import ConfigError, SubmapSlamError
from submapslam.evaluation.metrics import (
    Alignment,
    DeltaUnit,
    align,
    associate,
    ate,
    kitti_segment_error,
    relations_error,
    rpe,
    umeyama,
)
from submapslam.evaluation.report import compare_trajectories
from submapslam.geometry import se2_to_matrix, se3_exp
from submapslam.trajectory import Relations, Trajectory

from .cli_errors import assert_one_error_line


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


# ---------------------------------------------------------------------------- option values are checked
def test_unknown_alignment_is_a_config_error_not_se3():
    t = square()
    for call in (lambda: ate(t, t, align="foo"), lambda: align(t, t, "foo")):
        with pytest.raises(ConfigError) as err:
            call()
        assert str(err.value) == "unknown alignment 'foo': use one of se3, sim3, se2, none"
    # the Enum and its strings are the same choice
    assert ate(t, t, align=Alignment.SIM3)["scale"] == ate(t, t, align="sim3")["scale"]
    assert Alignment("se2") is Alignment.SE2


def test_unknown_rpe_unit_and_bad_delta_are_config_errors():
    t = line()
    with pytest.raises(ConfigError) as err:
        rpe(t, t, unit="bogus")
    assert str(err.value) == "unknown RPE unit 'bogus': use one of frames, meters"
    for delta, unit, message in ((0, "frames", "RPE delta in frames must be a whole number >= 1, not 0"),
                                 (1.5, "frames", "RPE delta in frames must be a whole number >= 1, not 1.5"),
                                 (-2.0, "meters", "RPE delta in meters must be > 0, not -2.0")):
        with pytest.raises(ConfigError) as err:
            rpe(t, t, delta=delta, unit=unit)
        assert str(err.value) == message
    # metres still work: 2 m apart on a 1 m-step line is 2 frames
    assert rpe(t, t, delta=2.0, unit=DeltaUnit.METERS)["n"] == rpe(t, t, delta=2)["n"] == 48


def test_compare_report_checks_alignment_before_writing(tmp_path):
    ref = square()
    with pytest.raises(ConfigError, match=r"^unknown alignment 'foo': use one of se3, sim3, se2, none$"):
        compare_trajectories(ref, {"a": ref}, tmp_path / "rep", align="foo")
    assert not (tmp_path / "rep").exists()


def test_compare_report_leaves_segments_empty_only_when_none_fits(tmp_path, monkeypatch):
    import submapslam.evaluation.report as report

    still = Trajectory(np.arange(5, dtype=float), np.tile(np.eye(4), (5, 1, 1)))  # no path: no segment
    rows = compare_trajectories(still, {"a": still}, tmp_path / "rep").rows
    assert np.isnan(rows["a"]["segment_trans_percent"]) and rows["a"]["ate_rmse"] == pytest.approx(0.0)
    # anything else than "no segment fits" is not turned into an empty column

    def broken(*_args, **_kwargs):
        raise ValueError("a bug")

    monkeypatch.setattr(report, "kitti_segment_error", broken)
    with pytest.raises(ValueError, match="a bug"):
        compare_trajectories(square(), {"a": square()}, tmp_path / "rep2")


@pytest.mark.parametrize("command", ["eval", "compare"])
def test_cli_unknown_alignment_is_one_line(tmp_path, command):
    from typer.testing import CliRunner

    from submapslam.cli import app
    from submapslam.io.trajectory import write_tum

    write_tum(tmp_path / "t.txt", square())
    args = ([command, str(tmp_path / "t.txt"), str(tmp_path / "t.txt"), "--align", "foo"]
            + (["--out", str(tmp_path / "rep")] if command == "compare" else []))
    r = CliRunner().invoke(app, args)
    assert_one_error_line(r, "unknown alignment 'foo': use one of se3, sim3, se2, none")
    assert not (tmp_path / "rep").exists()


def test_nearest_stamps_picks_the_nearest_within_the_tolerance():
    from submapslam.trajectory import nearest_stamps

    times = np.array([3.0, 1.0, 2.0])  # any order
    np.testing.assert_array_equal(nearest_stamps(times, [1.01, 2.6, 1.5, 9.0], 0.5), [1, 0, 1, -1])  # tie: earlier
    np.testing.assert_array_equal(nearest_stamps(times, [1.01, 2.6], 0.05), [1, -1])
    np.testing.assert_array_equal(nearest_stamps([5.0], [5.0, 6.0], 0.1), [0, -1])
    np.testing.assert_array_equal(nearest_stamps([], [1.0], 0.1), [-1])
