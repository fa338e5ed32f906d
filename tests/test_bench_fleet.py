"""tools/bench_fleet.py: cutting a log into sessions (CARMEN and cloud folders, one reversed)."""

from __future__ import annotations

import numpy as np

from datasets_synth import generate
from submapslam import open_log

from .conftest import load_tool


def _bench():
    return load_tool("bench_fleet")


def test_pieces_hold_every_scan_once_each_from_its_own_origin(tmp_path):
    bench = _bench()
    log = generate("rectangle", tmp_path / "log", seed=0, laps=1, size=(20.0, 12.0), max_scans=40)
    whole = list(open_log(log / "log.clf"))
    pieces = bench.split_carmen(log / "log.clf", [15, 30], tmp_path / "carmen")
    parts = [list(open_log(p)) for p in pieces]
    assert [len(p) for p in parts] == [15, 15, 10]
    assert np.array_equal(np.concatenate([[s.timestamp for s in p] for p in parts]), [s.timestamp for s in whole])
    assert np.allclose(parts[1][0].points, whole[15].points)

    folders = bench.split_folder(log, [25], tmp_path / "folder", reverse_last=True)
    first, last = (list(open_log(f)) for f in folders)
    assert len(first) == 25 and len(last) == 15
    # the last piece drives backwards: its first scan is the log's last, with its own timestamp
    # (the CARMEN log rounds ranges to mm; the folder keeps them)
    assert np.allclose(last[0].points, whole[-1].points, atol=2e-3) and last[0].timestamp == whole[-1].timestamp
    assert np.allclose(last[-1].points, whole[25].points, atol=2e-3)
    rows = (folders[1] / "odometry_tum.txt").read_text().splitlines()
    assert len(rows) == 15 and float(rows[0].split()[0]) == whole[-1].timestamp  # each scan's own odometry
