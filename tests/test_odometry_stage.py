"""Registration in a child process: the same poses (and, for 2D lasers, odometry checks) as in
this process, its memory counted, a dead child reported in one line, and a caller's script never
re-run by it."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from datasets_synth import generate
from submapslam import odometry_stage
from submapslam.config import OdometryConfig
from submapslam.errors import SubmapSlamError
from submapslam.geometry import se2_to_matrix
from submapslam.io.registry import open_log
from submapslam.odometry_stage import InlineOdometry, OdometryProcess, start_odometry
from submapslam.scan import Scan

from .planar_scenes import wall_points
from .test_odometry_wheels import ROOM

CLI = [sys.executable, "-m", "submapslam"]


@pytest.fixture(scope="module")
def outdoor_log(tmp_path_factory):
    return generate("outdoor", tmp_path_factory.mktemp("odo") / "log", seed=3, laps=1, blocks=(1, 1), max_scans=40)


def test_child_process_registers_exactly_as_this_process(outdoor_log):
    scans = list(open_log(outdoor_log))
    inline, child = InlineOdometry(OdometryConfig(), False), OdometryProcess(OdometryConfig(), False)
    try:
        for scan in scans:  # all queued before the first answer: the child works ahead
            child.submit(scan)
        for scan in scans:
            inline.submit(scan)
            a, b = inline.result(), child.result()
            assert np.array_equal(a.pose, b.pose)
            assert np.array_equal(a.frame, b.frame) and np.array_equal(a.frame_down, b.frame_down)
        assert (child.voxel_size, child.frame_voxel) == (inline.voxel_size, inline.frame_voxel)
        moved = np.linalg.norm(a.pose[:3, 3])
        assert moved > 5.0  # the scans really were registered along the drive
    finally:
        child.close()
    assert child.peak_memory_mb > 20  # the child's own high-water mark, reported on close
    assert child._process.poll() is not None  # and it has ended


def test_the_child_runs_ahead_of_a_caller_that_is_busy(outdoor_log):
    """The child's answers are taken as they come: it registers every scan queued while this
    process does not ask (40 3D frames, megabytes: far more than a pipe's buffer holds)."""
    scans = list(open_log(outdoor_log))
    child = OdometryProcess(OdometryConfig(), False)
    try:
        for scan in scans:
            child.submit(scan)
        deadline = time.monotonic() + 120.0
        while child.ready < len(scans) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert child.ready == len(scans)
        assert sum(child.result().frame.nbytes for _ in scans) > 1_000_000
    finally:
        child.close()


def test_a_dead_child_is_one_clear_error(outdoor_log):
    scan = next(iter(open_log(outdoor_log)))
    child = OdometryProcess(OdometryConfig(), False)
    try:
        child._process.kill()
        child.submit(scan)
        with pytest.raises(SubmapSlamError, match="odometry process ended unexpectedly"):
            child.result()
    finally:
        child.close()


def test_a_child_whose_answers_break_while_it_runs_is_stopped_with_one_clear_error(outdoor_log, monkeypatch):
    """The answer stream breaks but the child lives on (waiting for scans): the caller gets the
    same one-line error after a short wait, and the child is stopped, not left running."""
    import submapslam.child_process as child_process
    import submapslam.odometry_stage as stage

    def broken(stream):
        raise EOFError("the stream broke")

    monkeypatch.setattr(stage, "_END_WAIT_S", 0.5)
    monkeypatch.setattr(child_process, "receive", broken)  # the reader's stream breaks; the child itself runs on
    scan = next(iter(open_log(outdoor_log)))
    child = OdometryProcess(OdometryConfig(), False)
    try:
        assert child._process.poll() is None
        child.submit(scan)
        with pytest.raises(SubmapSlamError, match="odometry process ended unexpectedly"):
            child.result()
        assert child._process.poll() is not None
    finally:
        child.close()


def test_planar_child_reports_the_same_poses_and_checks():
    """A planar run in a child process: the same refined poses as in this process, and the
    odometry checks (summary.json's ``odometry_checks``) come back when the child ends."""
    scans, wheel = [], None
    for k in range(24):  # turning 12 deg a scan, the wheel pose updated every 4th scan only
        xyt = np.array([0.01 * k, -1.5, np.deg2rad(12.0) * k])
        wheel = xyt if k % 4 == 0 else wheel
        pts = wall_points(ROOM, xyt, max_range=12.0)
        scans.append(Scan(k, 0.1 * k, np.c_[pts, np.zeros(len(pts))], odometry=se2_to_matrix(*wheel), planar=True))
    inline, child = InlineOdometry(OdometryConfig(), True), OdometryProcess(OdometryConfig(), True)
    try:
        for scan in scans:
            child.submit(scan)
        for scan in scans:
            inline.submit(scan)
            a, b = inline.result(), child.result()
            assert np.array_equal(a.pose, b.pose) and np.array_equal(a.xyt, b.xyt)
        assert child.checks() == {}  # not known while the child runs
    finally:
        child.close()
    assert child.checks() == inline.checks() and inline.checks()["wheel_overruled"] > 0


def test_default_stage_is_a_child_for_3d_and_for_2d_with_a_core_to_spare(monkeypatch):
    for cores, planar, kind in ((2, True, OdometryProcess), (1, True, InlineOdometry), (1, False, OdometryProcess)):
        monkeypatch.setattr(odometry_stage, "usable_cores", lambda cores=cores: cores)
        stage = start_odometry(OdometryConfig(), planar)
        try:
            assert isinstance(stage, kind)
        finally:
            stage.close()
    stage = start_odometry(OdometryConfig(separate_process=False), False)
    assert isinstance(stage, InlineOdometry)


def test_run_counts_the_child_in_its_peak_and_does_not_rerun_the_callers_script(outdoor_log, tmp_path):
    # a script without the `if __name__ == "__main__"` guard: a multiprocessing spawn would
    # import it again in the child; the odometry process must not
    script = tmp_path / "user_script.py"
    marker = tmp_path / "started.txt"
    script.write_text(
        "import pathlib\n"
        f"m = pathlib.Path({str(marker)!r}); m.write_text(m.read_text() + 'x' if m.exists() else 'x')\n"
        "from submapslam.api import run_log\n"
        f"run_log({str(outdoor_log)!r}, {str(tmp_path / 'out')!r})\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert marker.read_text() == "x"
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    by_process = summary["peak_memory_mb_by_process"]
    assert by_process["odometry"] > 20 and by_process["main"] >= by_process["main_when_odometry_ended"] > 20
    # the child ends before the maps are fused: the peak of both is bounded by the larger of the
    # main process's peak and its peak when the child ended plus the child's
    bound = max(by_process["main"], by_process["main_when_odometry_ended"] + by_process["odometry"],
                by_process.get("main_while_grids", 0) + by_process.get("grids", 0))  # the map fusion's child
    assert summary["peak_memory_mb"] == pytest.approx(bound, abs=0.11)
    # registration kept in this process (a 2D run on one core, or asked for): nothing to add
    config = tmp_path / "inline.yaml"
    config.write_text("odometry:\n  separate_process: false\n")
    planar = subprocess.run([*CLI, "run", str(generate("rectangle", tmp_path / "r", laps=1, max_scans=30)),
                             "--out", str(tmp_path / "out2"), "--config", str(config)],
                            capture_output=True, text=True, timeout=300)
    assert planar.returncode == 0, planar.stderr
    planar_peaks = json.loads((tmp_path / "out2" / "summary.json").read_text())["peak_memory_mb_by_process"]
    assert planar_peaks["odometry"] == 0 and planar_peaks["main_when_odometry_ended"] == 0 < planar_peaks["main"]
