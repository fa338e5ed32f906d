"""`compare` names each estimate after its run folder: two `poses_tum.txt` never collide."""

import json

import numpy as np
from typer.testing import CliRunner

from submapslam.cli import app
from submapslam.geometry import se2_to_matrix
from submapslam.io.trajectory import Trajectory, write_tum
from submapslam.io.trajectory_names import trajectory_labels, trajectory_stem

from .cli_errors import assert_one_error_line

runner = CliRunner()


def _circle(path, noise, seed):
    rng = np.random.default_rng(seed)
    t = np.arange(200) * 0.1
    a = t / t[-1] * 2 * np.pi
    poses = np.array([se2_to_matrix(10 * np.cos(x) + rng.normal(0, noise), 10 * np.sin(x) + rng.normal(0, noise), x)
                      for x in a])
    path.parent.mkdir(parents=True, exist_ok=True)
    write_tum(path, Trajectory(t, poses))
    return path


def test_two_poses_files_from_two_runs_both_get_a_row(tmp_path):
    ref = _circle(tmp_path / "truth_tum.txt", 0.0, 0)
    a = _circle(tmp_path / "runA" / "poses_tum.txt", 0.05, 1)
    b = _circle(tmp_path / "runB" / "poses_tum.txt", 0.30, 2)
    odo = _circle(tmp_path / "runA" / "odometry_tum.txt", 0.60, 3)
    out = tmp_path / "cmp"
    r = runner.invoke(app, ["compare", str(ref), str(a), str(b), str(odo), "--out", str(out)])
    assert r.exit_code == 0, r.output
    rows = json.loads((out / "report.json").read_text())
    assert list(rows) == ["runA/poses", "runB/poses", "runA/odometry"]
    # each row is its own file's figures, not the last one written under a shared name
    assert rows["runA/poses"]["ate_rmse"] < rows["runB/poses"]["ate_rmse"] < rows["runA/odometry"]["ate_rmse"]
    # and the page: one sortable table row per estimate, named the same, with the same ATE
    html = (out / "report.html").read_text()
    body = html.split('<table id="compare" class="sortable">')[1].split("</table>")[0]
    for name, row in rows.items():
        assert f'<td class="t">{name}</td><td>{row["ate_rmse"]:.4g}</td>' in body
    assert "<th>ATE RMSE [m]</th>" in body and "reference: truth_tum.txt" in html
    assert body.count("<tr ") == 3


def test_labels_are_unique_and_readable(tmp_path):
    assert trajectory_stem(tmp_path / "poses_tum.txt") == "poses"
    assert trajectory_stem(tmp_path / "intel-corrected.log.gz") == "intel-corrected"
    same_folder_name = [tmp_path / "x" / "run" / "poses_tum.txt", tmp_path / "y" / "run" / "poses_tum.txt"]
    assert trajectory_labels(same_folder_name) == ["x/run/poses", "y/run/poses"]
    twice = tmp_path / "run" / "poses_tum.txt"
    assert trajectory_labels([twice, twice]) == ["run/poses", "run/poses#2"]


def test_repeated_labels_are_an_error(tmp_path):
    ref = _circle(tmp_path / "truth_tum.txt", 0.0, 0)
    a = _circle(tmp_path / "runA" / "poses_tum.txt", 0.05, 1)
    r = runner.invoke(app, ["compare", str(ref), str(a), str(a), "--out", str(tmp_path / "c"),
                            "--label", "mine", "--label", "mine"])
    assert_one_error_line(r, "mine")
