"""eval says how it paired the poses when that is doubtful: KITTI files of different lengths,
a corrected CARMEN reference given without its raw log."""

import json

import numpy as np
from typer.testing import CliRunner

from submapslam.cli import app
from submapslam.geometry import se2_to_matrix
from submapslam.io.trajectory import Trajectory, write_kitti, write_tum

from .cli_errors import assert_one_error_line

runner = CliRunner()


def square_path(n):
    return np.array([se2_to_matrix(0.1 * k, 0.02 * k * k / n, 0.01 * k) for k in range(n)])


def test_kitti_files_of_different_lengths_are_not_paired_silently(tmp_path):
    write_kitti(tmp_path / "ref.txt", square_path(40))
    write_kitti(tmp_path / "est.txt", square_path(25))
    out = tmp_path / "e.json"
    r = runner.invoke(app, ["eval", str(tmp_path / "est.txt"), str(tmp_path / "ref.txt"), "--json", str(out)])
    assert r.exit_code == 0, r.output
    (warning,) = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert warning.startswith("warning: est.txt has 25 poses and ref.txt 40") and "first 25 are compared" in warning
    assert json.loads(out.read_text())["warnings"] == [warning.removeprefix("warning: ")]
    # equal lengths: nothing to say
    write_kitti(tmp_path / "est.txt", square_path(40))
    r = runner.invoke(app, ["eval", str(tmp_path / "est.txt"), str(tmp_path / "ref.txt")])
    assert r.exit_code == 0 and r.stderr.strip() == ""


def test_a_corrected_carmen_reference_without_raw_log_suggests_it(tmp_path):
    """Corrected logs are stamped with the raw log's logger time (seconds since the logger
    started); an estimate carries the raw log's ipc time (unix time)."""
    poses = square_path(30)
    lines = ["# corrected\n"]
    for k, T in enumerate(poses):
        x, y, yaw = T[0, 3], T[1, 3], np.arctan2(T[1, 0], T[0, 0])
        ranges = " ".join(["2.0"] * 5)
        lines.append(f"FLASER 5 {ranges} {x} {y} {yaw} {x} {y} {yaw} {30.0 + 0.1 * k:.6f} host {30.0 + 0.1 * k:.6f}\n")
    ref = tmp_path / "corrected.log"
    ref.write_text("".join(lines))
    write_tum(tmp_path / "est.txt", Trajectory(976052857.0 + 0.1 * np.arange(30), poses))
    r = runner.invoke(app, ["eval", str(tmp_path / "est.txt"), str(ref)])
    assert_one_error_line(r, "no timestamps match", "corrected.log is a corrected log", "--raw-log")
    # a few stamps overlap by chance: the figures come with the same suggestion as a warning
    write_tum(tmp_path / "est.txt", Trajectory(np.r_[30.0 + 0.1 * np.arange(5), 976052857.0 + 0.1 * np.arange(25)],
                                                poses))
    r = runner.invoke(app, ["eval", str(tmp_path / "est.txt"), str(ref)])
    assert r.exit_code == 0, r.output
    (warning,) = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert warning.startswith("warning: only 5 of the 30 reference poses match") and "--raw-log" in warning
