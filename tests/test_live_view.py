"""`run --record` writes a Rerun recording that the SDK reads back; the options fail in one line."""

import json
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from submapslam.cli import app
from submapslam.errors import ConfigError
from submapslam.geometry import se2_to_matrix
from submapslam.result import LoopRecord

from .cli_errors import assert_one_error_line

runner = CliRunner()


def _rerun_or_skip():
    return pytest.importorskip("rerun", reason="rerun-sdk not installed (pip install 'submapslam[view]')")


def _chunks(path):
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    assert [r.application_id for r in reader.recordings()] == ["submapslam"]
    return list(reader.store().stream())


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    out = tmp_path_factory.mktemp("live") / "log"
    r = runner.invoke(app, ["synth", "rectangle", "--out", str(out), "--laps", "1", "--max-scans", "120"])
    assert r.exit_code == 0, r.output
    return out


def test_record_writes_an_rrd_the_sdk_reads_back(small_log, tmp_path):
    _rerun_or_skip()
    rrd, out = tmp_path / "run.rrd", tmp_path / "out"
    r = runner.invoke(app, ["run", str(small_log), "--out", str(out), "--record", str(rrd)])
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "summary.json").read_text())
    chunks = _chunks(rrd)
    paths = {c.entity_path for c in chunks}
    assert {"/world/scan", "/world/trajectory", "/world/anchors", "/world/anchor_path"} <= paths
    assert {f"/world/submaps/{k}" for k in range(summary["submaps"])} <= paths
    scans = sorted({i for c in chunks if c.entity_path == "/world/scan"
                    for i in c.to_record_batch().column("scan").to_pylist()})
    assert scans == list(range(summary["scans"]))  # every scan was streamed, in order
    # the trajectory at the end of the timeline holds one vertex per scan (the chunks of the
    # graph worker's thread and the main thread may come in either order: pick by time)
    sent = [(t, strips[0]) for c in chunks if c.entity_path == "/world/trajectory"
            for batch in [c.to_record_batch()]
            for t, strips in zip(batch.column("scan").to_pylist(), batch.column("LineStrips3D:strips").to_pylist())]
    _, strip = max(sent, key=lambda row: row[0])
    assert len(strip) == summary["scans"]


def test_loops_are_streamed_green_and_red_with_their_reason(tmp_path):
    _rerun_or_skip()
    from submapslam.viz.rerun_view import RerunView

    rrd = tmp_path / "loops.rrd"
    view = RerunView(record=rrd)
    anchors = np.array([se2_to_matrix(4.0 * k, 0.0, 0.0) for k in range(3)])
    view.on_submap(2, anchors, np.zeros((10, 3)), np.eye(4))
    view.on_loop(LoopRecord(0, 2, "spatial", True, 0.9, 0.8, 0.03, "2 adjacent submap(s) confirm"), anchors[0], anchors[2])
    view.on_loop(LoopRecord(1, 2, "descriptor", False, 0.2, 0.2, 0.1, "fitness 0.20 < 0.45"), anchors[1], anchors[2])
    view.close()
    labels = {}
    for c in _chunks(rrd):
        if c.entity_path.startswith("/world/loops/"):
            labels[c.entity_path] = c.to_record_batch().column("LineStrips3D:labels").to_pylist()[-1]
    assert labels == {"/world/loops/accepted": ["0-2: 2 adjacent submap(s) confirm"],
                      "/world/loops/rejected": ["1-2: fitness 0.20 < 0.45"]}


def test_record_options_fail_in_one_line(small_log, tmp_path):
    mine = tmp_path / "notes.rrd"
    mine.write_text("my notes")
    r = runner.invoke(app, ["run", str(small_log), "--out", str(tmp_path / "o"), "--record", str(mine)])
    assert_one_error_line(r, "not a Rerun recording")
    assert mine.read_text() == "my notes" and not (tmp_path / "o").exists()
    r = runner.invoke(app, ["run", str(small_log), "--out", str(tmp_path / "o"), "--record", str(tmp_path / "x.txt")])
    assert_one_error_line(r, "must end in .rrd")


def test_missing_rerun_sdk_is_one_clear_error(monkeypatch, tmp_path):
    from submapslam.viz.rerun_view import RerunView

    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun now raises ImportError
    with pytest.raises(ConfigError, match=r"submapslam\[view\]"):
        RerunView(record=tmp_path / "a.rrd")
