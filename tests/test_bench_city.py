"""tools/bench_city.py: the side-by-side table on a tiny 3D log, and its false-closure counter."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

from datasets_synth import generate
from submapslam.evaluation.metrics import ate
from submapslam.geometry import inverse, se2_to_matrix
from submapslam.io.g2o import write_g2o
from submapslam.io.trajectory import read_tum

from .conftest import load_tool


@pytest.fixture(scope="module")
def bench():
    return load_tool("bench_city")


def _md_row(md: str, label: str) -> list[str]:
    rows = [line for line in md.splitlines() if line.startswith(f"| {label} |")]
    assert len(rows) == 1, f"one row for {label} expected in:\n{md}"
    return [c.strip() for c in rows[0].strip("|").split("|")]


def test_bench_city_tiny_log_submapslam_and_kiss_icp_with_a_missing_peer(tmp_path, bench, monkeypatch):
    log = generate("outdoor", tmp_path / "log", seed=0, laps=1, blocks=(1, 1), max_scans=60,
                   sensor_options={"rings": 16, "columns": 450})
    reaped: dict[int, int] = {}
    real_wait4 = os.wait4

    def spy_wait4(pid, options):
        res = real_wait4(pid, options)
        reaped[res[0]] = res[2].ru_maxrss
        return res

    monkeypatch.setattr(os, "wait4", spy_wait4)
    # KISS-SLAM counts as not installed, whatever this machine has
    real_has = bench._has_module
    monkeypatch.setattr(bench, "_has_module", lambda name: name != "kiss_slam" and real_has(name))
    js, md_path = tmp_path / "bench.json", tmp_path / "bench.md"
    rc = bench.main([str(log), "--tools", "submapslam", "kiss-icp", "kiss-slam", "--out", str(tmp_path / "out"),
                     "--json", str(js), "--markdown", str(md_path), "--no-peer-install",
                     "--peer-venv", str(tmp_path / "no_such_venv")])
    assert rc == 0
    report = json.loads(js.read_text())
    md = md_path.read_text()
    assert md.startswith("```sh\n") and "tools/bench_city.py" in md.splitlines()[1]
    (entry,) = report["logs"]
    assert entry["scans"] == 60
    gt = read_tum(log / "groundtruth_tum.txt")
    length = float(np.linalg.norm(np.diff(gt.positions[:60], axis=0), axis=1).sum())
    assert entry["path_length_m"] == pytest.approx(length, abs=1e-3)

    for tool, label in (("submapslam", "submapslam"), ("kiss-icp", "KISS-ICP")):
        r = entry["tools"][tool]
        assert r["status"] == "ok", r
        for key in ("ate_m", "ate_percent", "odometry_ate_m", "wall_s", "scans_per_s", "peak_rss_mib",
                    "peak_rss_kib", "memory_growth_mib_per_km", "pid"):
            assert key in r, (tool, key)
        # the ATE is the one of the poses it wrote, against the log's ground truth
        out = Path(r["out"])
        expect = ate(read_tum(out / "poses_tum.txt"), gt, align="se3")["rmse"]
        assert math.isfinite(r["ate_m"]) and r["ate_m"] == pytest.approx(expect, rel=1e-9)
        assert r["ate_percent"] == pytest.approx(100 * expect / length, rel=1e-6)
        assert len(read_tum(out / "poses_tum.txt")) == 60
        # peak RSS is the child's own ru_maxrss as wait4 returned it for that pid; submapslam's is at
        # least its peak when its odometry process ended plus that process's (wait4 gives the larger)
        odometry = r.get("odometry_process_peak_kib", 0)
        assert odometry > 0 if tool == "submapslam" else odometry == 0
        both = r.get("main_peak_when_odometry_ended_kib", 0) + odometry
        assert r["peak_rss_kib"] > 0 and r["peak_rss_kib"] == max(reaped[r["pid"]], both)
        assert r["peak_rss_mib"] == pytest.approx(r["peak_rss_kib"] / 1024)
        assert r["wall_s"] > 0 and r["scans_per_s"] == pytest.approx(60 / r["wall_s"])
        row = _md_row(md, label)
        assert len(row) == len(bench.COLUMNS)
        assert row[1] == f"{r['ate_m']:.3f}" and row[8] == f"{r['peak_rss_mib']:.0f}"

    sub = entry["tools"]["submapslam"]
    for key in ("closures_g2o", "closures_loops_csv", "false_closures_g2o", "false_closures_loops_csv"):
        assert isinstance(sub[key], int) and sub[key] >= 0
    icp = entry["tools"]["kiss-icp"]
    assert icp["submapslam_ratio"]["time"] == pytest.approx(sub["wall_s"] / icp["wall_s"])
    assert icp["submapslam_ratio"]["ate"] == pytest.approx(sub["ate_m"] / icp["ate_m"])
    assert icp["points"] > 0 and len(icp["points_digest"]) == 32

    slam = entry["tools"]["kiss-slam"]
    assert slam["status"] == "skipped" and "not installed" in slam["reason"]
    assert _md_row(md, "KISS-SLAM")[1].startswith("skipped: kiss-slam is not installed")


def _out_and_back_ground_truth() -> np.ndarray:
    """100 scans 1 m apart: out along +x on y = 0, back along -x on y = 2."""
    out = [se2_to_matrix(x, 0.0, 0.0) for x in range(50)]
    back = [se2_to_matrix(49.0 - k, 2.0, np.pi) for k in range(50)]
    poses = np.array(out + back)
    poses[:, 2, 3] = 1.7
    return poses


def _write_run(folder: Path, gt: np.ndarray, loops: list[tuple[int, int, np.ndarray]]) -> None:
    """A submapslam-like output: 10 submaps of 10 scans (consecutive ones share a scan)."""
    folder.mkdir()
    firsts = list(range(0, 100, 10))
    anchors = gt[firsts]
    edges = [(k, k + 1, inverse(anchors[k]) @ anchors[k + 1], np.eye(6), "odometry") for k in range(9)]
    edges += [(i, j, T, np.eye(6), "loop") for i, j, T in loops]
    write_g2o(folder / "graph.g2o", anchors, edges)
    lines = ["id,first_scan,last_scan,x,y,z,yaw,sigma_x,sigma_y,sigma_z,sigma_roll,sigma_pitch,sigma_yaw"]
    lines += [f"{k},{f},{min(f + 10, 99)},0,0,0,0,0,0,0,0,0,0" for k, f in enumerate(firsts)]
    (folder / "submaps.csv").write_text("\n".join(lines) + "\n")


def test_false_closure_counter_on_a_written_graph(tmp_path, bench):
    gt = _out_and_back_ground_truth()
    A = gt[list(range(0, 100, 10))]
    true_0_9 = inverse(A[0]) @ A[9]  # anchors (0, 0) and (9, 2): 9.2 m apart, extent 10 m
    wrong_1_8 = inverse(A[1]) @ A[8] @ se2_to_matrix(3.0, 0.0, 0.0)  # 3 m off
    _write_run(tmp_path / "run", gt, [(0, 9, true_0_9), (1, 8, wrong_1_8)])
    fc = bench.false_closures_from_files(tmp_path / "run" / "graph.g2o", tmp_path / "run" / "submaps.csv", gt)
    assert fc["closures"] == 2 and fc["false"] == 1
    assert fc["extent_m"] == pytest.approx(10.0)
    (bad,) = [d for d in fc["details"] if d["false"]]
    assert (bad["i"], bad["j"]) == (1, 8) and bad["trans_err_m"] == pytest.approx(3.0, abs=1e-6)

    # a correct relative pose between submaps whose paths stay more than twice the extent apart
    # is false too, and a rotation off by 3 degrees is
    far_0_4 = inverse(A[0]) @ A[4]  # 40 m apart
    turned = true_0_9 @ se2_to_matrix(0.0, 0.0, np.deg2rad(3.0))
    submaps = bench.read_submaps_csv(tmp_path / "run" / "submaps.csv")
    assert bench.false_closures([(0, 9, true_0_9), (0, 4, far_0_4)], submaps, gt)["false"] == 1
    assert bench.false_closures([(0, 9, turned)], submaps, gt)["false"] == 1
    # what counts is where the paths come closest, not the anchors: out from (0, 0) to (10, 0),
    # and on the way back from (25, 2) to (15, 2): anchors 25 m apart, more than twice the
    # extent (10 m), paths 5.4 m apart at their nearest
    facing = {0: (0, 10), 1: (74, 84)}
    fc = bench.false_closures([(0, 1, inverse(gt[0]) @ gt[74])], facing, gt)
    assert fc["extent_m"] == pytest.approx(10.0) and fc["details"][0]["anchor_distance_m"] > 25
    assert fc["details"][0]["path_distance_m"] == pytest.approx(np.hypot(5.0, 2.0), abs=1e-3)
    assert fc["false"] == 0


def test_memory_growth_is_the_slope_over_the_second_half(bench):
    km = np.linspace(0, 4, 41)
    rss = np.where(km < 2, 300 + 100 * km, 500 + 5 * (km - 2))  # fast start, 5 MiB/km later
    assert bench.memory_growth_per_km(list(zip(km, rss))) == pytest.approx(5.0)
    assert bench.memory_growth_per_km(None) is None and bench.memory_growth_per_km([(1.0, 3.0)]) is None
