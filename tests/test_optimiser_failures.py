"""No optimiser failure loses the run: singular edges are regularised, an indeterminate graph is
solved again regularised, and a failure that cannot be recovered ends the run with its results
written, as after a Ctrl-C, and one line."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from datasets_synth import generate
from submapslam import graph_builder
from submapslam.api import run_log
from submapslam.backend.pose_graph import MIN_INFORMATION, PoseGraph, regularised_information
from submapslam.cli import app
from submapslam.config import BackendConfig
from submapslam.errors import OptimisationError
from submapslam.io.trajectory import read_tum

from .cli_errors import assert_one_error_line


def _step(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def test_a_singular_or_non_finite_information_is_floored_not_fatal():
    floored = regularised_information(np.diag([1e4, 1e4, 1e4, 1e4, 1e4, 0.0]))
    assert np.linalg.eigvalsh(floored).min() == pytest.approx(MIN_INFORMATION)
    assert np.allclose(floored[:5, :5], np.diag([1e4] * 5))
    assert np.allclose(regularised_information(np.full((6, 6), np.nan)), np.eye(6) * MIN_INFORMATION)
    graph = PoseGraph(BackendConfig())
    graph.add_node(0, np.eye(4), np.eye(6) * 1e6)
    graph.add_node(1, _step(1.0))
    graph.add_between(0, 1, _step(1.0), np.zeros((6, 6)), "odometry")  # sees nothing at all
    graph.update()
    assert np.allclose(graph.pose(1), _step(1.0))
    sigma = np.sqrt(np.diag(graph.all_marginal_covariances()[1]))
    assert np.all(np.isfinite(sigma)) and np.all(sigma < 101.0)
    assert graph.recoveries == []


def test_an_indeterminate_graph_is_solved_again_regularised():
    graph = PoseGraph(BackendConfig())
    graph.add_node(0, np.eye(4), np.eye(6) * 1e6)
    graph.add_node(1, _step(1.0))  # no factor touches node 1: GTSAM's solve is indeterminate
    graph.add_node(2, _step(2.0))
    graph.add_between(1, 2, _step(1.0), np.eye(6) * 1e4, "odometry")
    graph.update()
    assert graph.recoveries and "indeterminate" in graph.recoveries[0].lower()
    assert np.allclose(graph.pose(2), _step(2.0), atol=1e-6)
    graph.optimize_batch()
    assert np.isfinite(graph.all_marginal_covariances()[2]).all()


@pytest.fixture(scope="module")
def rectangle_log(tmp_path_factory):
    return generate("rectangle", tmp_path_factory.mktemp("rect") / "log", seed=3, laps=1, max_scans=160)


def test_a_submap_whose_odometry_edge_is_singular_does_not_stop_the_run(rectangle_log, tmp_path, monkeypatch):
    original = graph_builder.odometry_information
    calls = []

    def singular_third(*args, **kwargs):
        calls.append(1)
        return np.zeros((6, 6)) if len(calls) == 3 else original(*args, **kwargs)

    monkeypatch.setattr(graph_builder, "odometry_information", singular_third)
    result, paths = run_log(rectangle_log, tmp_path / "out", config=_no_registration_covariance(tmp_path))
    assert len(calls) >= 3 and result.failure is None and not result.interrupted
    assert np.isfinite(result.poses).all() and np.isfinite(result.submap_covariances).all()
    assert len(read_tum(paths["poses_tum.txt"])) == result.n_scans == 160


def _no_registration_covariance(tmp_path):
    path = tmp_path / "config.yaml"
    path.write_text("backend:\n  odometry_registration_covariance: false\n")
    return path


def test_a_failure_that_cannot_be_recovered_keeps_the_results_and_says_so_in_one_line(rectangle_log, tmp_path,
                                                                                         monkeypatch):
    original = PoseGraph.update
    calls = []

    def failing_from_the_second(self, *args, **kwargs):
        calls.append(1)
        if len(calls) >= 2:
            raise OptimisationError("the pose graph cannot be solved, even regularised: provoked")
        return original(self, *args, **kwargs)

    monkeypatch.setattr(PoseGraph, "update", failing_from_the_second)
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["run", str(rectangle_log), "--out", str(out)])
    assert_one_error_line(res, "cannot be solved", "results cover the first")
    poses = read_tum(out / "poses_tum.txt")
    assert 0 < len(poses) < 160 and np.isfinite(poses.poses).all()
    summary = (out / "summary.json").read_text()
    assert '"interrupted": true' in summary and "provoked" in summary
