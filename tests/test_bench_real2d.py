"""tools/bench_real2d.py on a tiny CARMEN log: the child's figures and the markdown table."""

import json

import pytest

from .conftest import load_tool
from .test_no_returns import _write_log


@pytest.fixture(scope="module")
def bench():
    return load_tool("bench_real2d")


def test_child_measures_a_log_against_its_corrected_log_and_the_table_shows_it(bench, tmp_path):
    log = tmp_path / "room.clf"
    _write_log(log)  # its FLASER poses are the truth: the log is its own "corrected" log
    result_json = tmp_path / "room.json"
    bench.child(log, log, tmp_path / "out", None, result_json)
    doc = json.loads(result_json.read_text())
    assert doc["scans"] == 60 and doc["reference_poses"] == 60
    assert doc["ate"] < 0.05 and doc["relations"] >= 59  # every pose with the next (no loops in 60 scans)
    assert doc["relations_error"]["trans_mean"] < 0.05
    assert doc["consistency"]["disagrees_with_odometry"] is False
    doc.update(name="intel", numeric="avx2", wall_s=1.5, peak_rss_mib=200.0)
    md = bench.table([doc])
    head, rule, row = md.splitlines()
    assert head.count("|") == rule.count("|") == row.count("|")
    assert "| intel | avx2 | 60 | 1.5 | 200 |" in row and "0.0229 m / 0.453°" in row


def test_a_numeric_variant_reaches_the_child_as_its_environment(bench, tmp_path, monkeypatch):
    """``--numeric sse``: the child runs with numpy's SIMD kernels and OpenBLAS's core type held
    back (and ``native`` without the variables, even when the parent has them)."""
    import subprocess
    import sys

    seen, popen = {}, subprocess.Popen

    def child(cmd, env):  # stands in for the log's child: writes what it was given
        script = ("import json, os, sys; json.dump({'env': {k: os.environ.get(k) for k in "
                  "('NPY_DISABLE_CPU_FEATURES', 'OPENBLAS_CORETYPE')}}, open(sys.argv[1], 'w'))")
        seen["cmd"] = cmd
        return popen([sys.executable, "-c", script, cmd[-1]], env=env)

    monkeypatch.setattr(bench.subprocess, "Popen", child)
    monkeypatch.setenv("OPENBLAS_CORETYPE", "Prescott")
    doc = bench.run_child("intel", tmp_path, tmp_path, None, "sse")
    assert doc["numeric"] == "sse" and seen["cmd"][-1].endswith("intel-sse.json")
    assert doc["env"] == bench.NUMERIC["sse"] and "X86_V3" in doc["env"]["NPY_DISABLE_CPU_FEATURES"]
    doc = bench.run_child("intel", tmp_path, tmp_path, None, "native")
    assert doc["env"] == {"NPY_DISABLE_CPU_FEATURES": None, "OPENBLAS_CORETYPE": None}
