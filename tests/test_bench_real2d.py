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


def test_a_cut_keeps_every_kth_scan_of_each_laser_and_every_other_line(tmp_path):
    """tools/cut_carmen_log.py: each laser record counted on its own, ODOM lines kept, the reader
    sees a third of the scans with their own times, and an existing file is never overwritten."""
    from submapslam.io.registry import open_log

    log, cut = tmp_path / "room.clf", tmp_path / "room_every3.clf"
    _write_log(log)
    lines = log.read_text().splitlines()
    lines = [x for k, line in enumerate(lines) for x in (line, f"ODOM 0 0 0 0 0 0 {1000 + 0.2 * k:.6f} host 0",
                                                          line.replace("FLASER", "RLASER", 1))]
    log.write_text("\n".join(lines) + "\n")
    tool = load_tool("cut_carmen_log")
    assert tool.cut(log, cut, 3) == (40, 120)  # 20 of 60 front and 20 of 60 rear scans
    kept = cut.read_text().splitlines()
    assert sum(x.startswith("ODOM") for x in kept) == 60
    front = [x for x in kept if x.startswith("FLASER")]
    assert front == [x for x in lines if x.startswith("FLASER")][::3]
    stamps = [scan.timestamp for scan in open_log(cut)]
    assert len(stamps) == 20 and stamps == [s.timestamp for s in open_log(log)][::3]
    with pytest.raises(FileExistsError):
        tool.cut(log, cut, 2)
    assert tool.main([str(log), str(cut), "--every", "2"]) == 1  # one line, the file untouched
    assert cut.read_text().splitlines() == kept


def test_the_bench_runs_a_cut_as_its_own_row(bench, tmp_path, monkeypatch):
    """``--every 2``: the child gets the cut log (written once under OUT/cuts), the row says so."""
    import subprocess
    import sys

    seen, popen = [], subprocess.Popen

    def child(cmd, env):
        seen.append(cmd)
        script = "import json, sys; json.dump({}, open(sys.argv[1], 'w'))"
        return popen([sys.executable, "-c", script, cmd[-1]], env=env)

    data = tmp_path / "carmen"
    data.mkdir()
    _write_log(data / "intel.clf")
    monkeypatch.setattr(bench.subprocess, "Popen", child)
    monkeypatch.setattr(bench, "LOGS", {"intel": ("intel.clf", "intel.clf")})
    doc = bench.run_child("intel", data, tmp_path / "out", None, "native", every=2)
    cut = tmp_path / "out" / "cuts" / "intel-every2.clf"
    assert seen[-1][3] == str(cut) and cut.exists() and doc["name"] == "intel (1 scan in 2)"
    assert sum(line.startswith("FLASER") for line in cut.read_text().splitlines()) == 30


def test_a_sensor_variant_runs_against_the_original_logs_reference(bench, tmp_path, monkeypatch):
    """``--sensor beams2``: the log rewritten once under OUT/variants, run in a child, and scored on
    the corrected log matched to the original log's scans; a variant that is not one: one line."""
    _write_log(tmp_path / "room.clf")  # its own "corrected" log
    monkeypatch.setitem(bench.LOGS, "room", ("room.clf", "room.clf"))
    doc = bench.run_child("room", tmp_path, tmp_path / "out", None, sensor="beams2")
    variant = tmp_path / "out" / "variants" / "room-beams2.clf"
    assert doc["name"] == "room (beams2)" and doc["log_path"] == str(variant)
    assert variant.read_text().split()[1] == "91"  # 181 beams, every other one kept
    assert doc["scans"] == 60 and doc["reference_poses"] == 60 and doc["ate"] < 0.05
    for spec, kwargs in (("beams4", {"every_beam": 4}), ("range20", {"max_range": 20.0}),
                         ("noise3", {"range_noise": 0.03})):
        assert bench.sensor_variant(spec) == kwargs
    with pytest.raises(ValueError, match="use beamsK") as err:
        bench.sensor_variant("beamsX")
    assert "\n" not in str(err.value)
    with pytest.raises(SystemExit, match="room: 181 beams every 3") as stop:  # 60 beams would not keep their angles
        bench.run_child("room", tmp_path, tmp_path / "out", None, sensor="beams3")
    assert "\n" not in str(stop.value) and not (tmp_path / "out" / "variants" / "room-beams3.clf").exists()
