"""tools/bench_regression.py: KISS-ICP's figures and the ratios beside each row, and the table."""

from __future__ import annotations

import pytest

from .conftest import load_tool


def _row(**kw) -> dict:
    return {"name": "intel", "kind": "real 2D", "scans": 10, "ate_m": 0.05, "odometry_ate_m": 0.5, "closures": 3,
            "false_closures": None, "wall_s": 30.0, "peak_rss_mib": 240.0, **kw}


def test_ratios_to_kiss_icp_are_submapslam_over_the_peer():
    bench = load_tool("bench_regression")
    row = bench.with_peer(_row(), {"ate_m": 0.8, "wall_s": 25.0, "peak_rss_mib": 80.0})
    assert row["kiss_icp_ate_m"] == 0.8
    assert row["wall_ratio"] == pytest.approx(1.2) and row["memory_ratio"] == pytest.approx(3.0)
    assert bench.with_peer(_row(), None) == _row()  # --no-peers: the row as it was
    failed = bench.with_peer(_row(), {"error": "exit code 1"})
    assert failed["kiss_icp_error"] == "exit code 1" and "wall_ratio" not in failed


def test_the_table_has_the_peer_columns_and_says_what_failed():
    bench = load_tool("bench_regression")
    rows = [bench.with_peer(_row(), {"ate_m": 0.8, "wall_s": 25.0, "peak_rss_mib": 80.0}),
            bench.with_peer(_row(name="fr079"), {"error": "exit code 1"}), _row(name="csail"),
            {"name": "mb", "kind": "real 3D", "error": "exit code 2"}]
    lines = bench.markdown(rows).splitlines()
    assert lines[0].count("|") == lines[1].count("|") == 12
    assert all(line.count("|") == 12 for line in lines[2:])
    assert "| 0.8000 | 1.20 | 3.00 |" in lines[2]
    assert "failed: exit code 1" in lines[3] and "| — | — | — |" in lines[4] and "failed: exit code 2" in lines[5]
