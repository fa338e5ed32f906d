"""The label reader and the DynamicMap scores (SA, DA, AA) on constructed cases, and ``eval-map``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from datasets_synth.writer import write_labels
from submapslam.cli import app
from submapslam.errors import InputError
from submapslam.evaluation.dynamic_map import LabelledVoxels, is_dynamic, score_map
from submapslam.geometry import se2_array_to_matrices
from submapslam.io.grid import write_pgm_yaml
from submapslam.io.labels import read_label_file, read_map_points
from submapslam.io.ply import write_ply
from submapslam.io.trajectory import Trajectory, write_tum

from .cli_errors import assert_one_error_line
from .labelled_scenes import write_wall_and_person_log


def test_label_file_round_trip_and_checks(tmp_path):
    labels = np.array([40, 50, 252, 254 | (7 << 16), 10], dtype=np.uint32)
    path = tmp_path / "000000.label"
    write_labels(path, labels)
    assert path.stat().st_size == 4 * len(labels)
    assert np.array_equal(read_label_file(path, expected=5), labels)
    # instance ids in the upper 16 bits do not change the class
    assert is_dynamic(read_label_file(path)).tolist() == [False, False, True, True, False]
    with pytest.raises(InputError, match="5 labels for a scan of 6 points"):
        read_label_file(path, expected=6)
    (tmp_path / "bad.label").write_bytes(b"\x00" * 7)
    with pytest.raises(InputError, match="not a whole number"):
        read_label_file(tmp_path / "bad.label")


def _grid_of_cubes():
    """Static voxels: a 10 x 10 floor patch at z = 0.05; dynamic: a 4 x 4 patch at z = 1.05 (0.1 m voxels)."""
    ij = np.stack(np.meshgrid(np.arange(10), np.arange(10), indexing="ij"), -1).reshape(-1, 2)
    static = np.column_stack([(ij + 0.5) * 0.1, np.full(len(ij), 0.05)])
    ij4 = ij[(ij[:, 0] < 4) & (ij[:, 1] < 4)]
    dynamic = np.column_stack([(ij4 + 0.5) * 0.1, np.full(len(ij4), 1.05)])
    return static, dynamic


def test_scores_count_kept_static_and_removed_dynamic_voxels():
    static, dynamic = _grid_of_cubes()
    truth = LabelledVoxels(0.1)
    truth.add(np.vstack([static, dynamic]), np.r_[np.full(len(static), 40), np.full(len(dynamic), 252)])
    # a map with every static voxel but the first 20, and half of the dynamic ones
    s = score_map(truth, np.vstack([static[20:], dynamic[:8]]), radius=0.05)
    assert (s.static_voxels, s.static_kept) == (100, 80)
    assert (s.dynamic_voxels, s.dynamic_removed) == (16, 8)
    assert s.static_accuracy == pytest.approx(0.8) and s.dynamic_accuracy == pytest.approx(0.5)
    assert s.associated_accuracy == pytest.approx(np.sqrt(0.4))
    # the radius decides what counts as kept: points 0.07 m above the centroids are kept at 0.1 m only
    shifted = static + (0.0, 0.0, 0.07)
    assert score_map(truth, shifted, radius=0.1).static_kept == 100
    assert score_map(truth, shifted, radius=0.05).static_kept == 0


def test_mixed_voxels_are_not_scored_and_scans_accumulate():
    truth = LabelledVoxels(0.1, merge_every=1)
    truth.add(np.array([[0.05, 0.05, 0.05]]), np.array([50]))
    truth.add(np.array([[0.06, 0.04, 0.05], [1.05, 0.05, 0.05]]), np.array([252, 252]))
    centroids, n_static, n_dyn = truth.voxels()
    assert len(centroids) == 2 and truth.points == 3
    s = score_map(truth, np.zeros((0, 3)))
    assert s.mixed_voxels == 1 and s.static_voxels == 0 and s.dynamic_voxels == 1
    assert s.dynamic_accuracy == 1.0 and s.static_accuracy == 1.0  # nothing static to keep


def test_planar_truth_ignores_height():
    truth = LabelledVoxels(0.1, planar=True)
    truth.add(np.array([[0.05, 0.05, 0.0], [0.55, 0.05, 0.0]]), np.array([50, 254]))
    s = score_map(truth, np.array([[0.05, 0.05, 3.0]]), radius=0.05)
    assert (s.static_kept, s.dynamic_removed) == (1, 1)


def test_grid_map_points_are_occupied_cell_centres(tmp_path):
    prob = np.full((4, 6), 0.5)
    prob[1, 2] = 0.9  # row 1 = the second-lowest y
    prob[0, 0] = 0.05
    write_pgm_yaml(tmp_path / "map", prob, np.array([10.0, -2.0]), 0.5)
    points, resolution = read_map_points(tmp_path / "map.yaml")
    assert resolution == 0.5
    assert np.allclose(points, [[10.0 + 2.5 * 0.5, -2.0 + 1.5 * 0.5, 0.0]])
    with pytest.raises(InputError, match="map is a .ply"):
        (tmp_path / "x.txt").write_text("1 2 3\n")
        read_map_points(tmp_path / "x.txt")


@pytest.fixture()
def labelled_log(tmp_path):
    """Two planar-free 3D scans, 1 m apart along x: a static wall seen twice, a person seen in the first."""
    log = tmp_path / "log"
    _, wall, person = write_wall_and_person_log(log)
    return log, wall, person


def test_eval_map_cli_scores_a_cleaned_and_an_uncleaned_map(labelled_log, tmp_path):
    log, wall, person = labelled_log
    write_ply(tmp_path / "clean.ply", wall)
    write_ply(tmp_path / "all.ply", np.vstack([wall, person]))
    runner = CliRunner()
    res = runner.invoke(app, ["eval-map", str(tmp_path / "clean.ply"), str(log), "--json", str(tmp_path / "s.json")])
    assert res.exit_code == 0, res.output
    s = json.loads((tmp_path / "s.json").read_text())
    assert (s["SA"], s["DA"]) == (1.0, 1.0) and s["dynamic_voxels"] == 10 and s["static_voxels"] == 50
    res = runner.invoke(app, ["eval-map", str(tmp_path / "all.ply"), str(log)])
    assert res.exit_code == 0 and "DA 0.0000" in res.output
    # the truth uses the poses: wrong poses move the wall away from the map
    shifted = se2_array_to_matrices(np.array([[0.0, 3.0, 0.0], [1.0, 3.0, 0.0]]))
    write_tum(tmp_path / "wrong.txt", Trajectory(np.array([0.0, 0.1]), shifted))
    res = runner.invoke(app, ["eval-map", str(tmp_path / "clean.ply"), str(log), "--poses", str(tmp_path / "wrong.txt"),
                              "--json", str(tmp_path / "w.json")])
    assert json.loads((tmp_path / "w.json").read_text())["SA"] < 0.5


def test_eval_map_cli_errors_are_one_line(labelled_log, tmp_path):
    log, wall, _ = labelled_log
    write_ply(tmp_path / "m.ply", wall)
    runner = CliRunner()
    assert_one_error_line(runner.invoke(app, ["eval-map", str(tmp_path / "none.ply"), str(log)]), "no such map file")
    write_tum(tmp_path / "one.txt", Trajectory(np.array([0.0]), np.eye(4)[None]))
    assert_one_error_line(runner.invoke(app, ["eval-map", str(tmp_path / "m.ply"), str(log), "--poses",
                                              str(tmp_path / "one.txt")]), "1 poses for 2 scans")
    (log / "labels" / "000001.label").unlink()
    assert_one_error_line(runner.invoke(app, ["eval-map", str(tmp_path / "m.ply"), str(log)]), "no labels for scan")
    (tmp_path / "taken.json").write_text("{}")
    assert_one_error_line(runner.invoke(app, ["eval-map", str(tmp_path / "m.ply"), str(log), "--json",
                                              str(tmp_path / "taken.json")]), "not overwriting")
