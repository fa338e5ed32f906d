"""tools/bench_calibration.py's scoring on samples whose answer is known (no pipeline runs)."""

from __future__ import annotations

import json

import numpy as np

from .conftest import load_tool


def _bench():
    return load_tool("bench_calibration")


def test_scores_and_rescales_samples(tmp_path, capsys):
    """3D samples drawn from N(0, C) with C = 4 x the covariance on record: mean (e/sigma)^2 ~4 per
    axis, few inside the 95 % bound; rescored with the scale 4 they are calibrated."""
    bench = _bench()
    rng = np.random.default_rng(0)
    n = 4000
    cov = np.diag([1e-4, 2e-4, 3e-4, 0.01, 0.02, 0.03])
    errs = rng.normal(size=(n, 6)) * np.sqrt(4 * np.diag(cov))
    s = bench.summarise(errs, np.repeat(cov[None], n, axis=0), planar=False)
    assert all(3.7 < v["mean_z2"] < 4.3 for v in s["axes"].values())
    assert s["nees_full"]["dof"] == 6 and 22 < s["nees_full"]["mean"] < 26
    assert s["nees_xy"]["in95"] < 0.7
    path = tmp_path / "s.json"
    path.write_text(json.dumps({"samples": {"w anchors": {"errors": errs.tolist(),
                                                          "covariances": np.repeat(cov[None], n, 0).tolist()}}}))
    assert bench.main(["--rescore", str(path), "--scale", "4", "4", "4", "4", "4", "4"]) == 0
    out = capsys.readouterr().out
    fitted = [float(x) for x in out.split("fitted variance scale (GTSAM order)")[1].split("\n")[0].split()]
    np.testing.assert_allclose(fitted, 4.0, rtol=0.08)
    row = [line for line in out.splitlines() if line.startswith("| w anchors (rescaled)")][0]
    assert "x 0.9" in row or "x 1.0" in row
    assert bench.seed_range("3:6") == [3, 4, 5] and bench.seed_range("1,4") == [1, 4]


def test_a_finished_runs_anchors_are_the_submaps_first_scans(tmp_path):
    bench = _bench()
    (tmp_path / "submaps.csv").write_text("id,first_scan,last_scan\n0,0,14\n1,14,28\n2,28,40\n")
    assert bench._anchor_rows(tmp_path / "submaps.csv", [1, 2, 14, 15, 28, 39]) == [2, 4]
    assert bench._anchor_rows(tmp_path / "none.csv", [1, 2]) == []
