"""tools/edges_vs_reference.py: a run's graph edges whitened against a reference trajectory."""

import csv

import numpy as np
import pytest

from datasets_synth import generate
from submapslam.api import run_log
from submapslam.io.trajectory import Trajectory, read_tum

from .conftest import load_tool


@pytest.fixture(scope="module")
def tool():
    return load_tool("edges_vs_reference")


def test_edges_agree_with_the_truth_and_a_bent_reference_shows(tool, tmp_path):
    """A synthetic rectangle, two laps, against its ground truth: odometry and loop edges both
    found and within a few sigmas. Shifting the reference by 0.5 m from one anchor on makes the
    odometry edge into that anchor a 0.5 m outlier and leaves the edges before it as they were."""
    log = generate("rectangle", tmp_path / "log", seed=0, laps=2)
    run_log(log, tmp_path / "run")
    truth = read_tum(log / "groundtruth_tum.txt")
    edges = tool.edge_errors(tmp_path / "run", truth)
    assert edges["odometry"] and edges["loop"]
    for kind in ("odometry", "loop"):
        figures = tool.summarize(edges[kind])
        assert figures["edges"] == len(edges[kind]) and figures["chi2_median"] < 7.81
        assert figures["median_error_m"] < 0.05
    assert tool.summarize([])["edges"] == 0

    with open(tmp_path / "run" / "submaps.csv", newline="") as f:
        first_scan = [int(r["first_scan"]) for r in csv.DictReader(f)]
    anchor = len(first_scan) // 2
    poses = truth.poses.copy()
    poses[first_scan[anchor]:, 0, 3] += 0.5
    bent = tool.edge_errors(tmp_path / "run", Trajectory(truth.timestamps, poses))
    jump = next(e for e in bent["odometry"] if e["j"] == anchor)
    assert jump["error_m"] == pytest.approx(0.5, abs=0.05) and jump["chi2"] > 7.81
    before = [e["chi2"] for e in edges["odometry"] if e["j"] < anchor]
    np.testing.assert_allclose([e["chi2"] for e in bent["odometry"] if e["j"] < anchor], before)


def test_a_folder_without_a_run_is_one_line_not_a_traceback(tool, tmp_path, capsys):
    empty = tmp_path / "empty.clf"
    empty.write_text("")
    assert tool.main([str(tmp_path / "nothing"), str(empty), str(empty)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("edges_vs_reference: "), err
