"""Checkpoints and ``run --resume`` (issue 12): an interrupted run continued from its checkpoint
ends with the trajectory, loops and graph of the run that was never interrupted."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from typer.testing import CliRunner

from datasets_synth import generate
from submapslam.api import run_log
from submapslam.cli import app
from submapslam.config import PipelineConfig
from submapslam.errors import SubmapSlamError
from submapslam.io.checkpoint import checkpoint_folder, read_checkpoint

from .cli_errors import assert_one_error_line

runner = CliRunner()


def _stop_after(n_scans: int) -> tuple[threading.Event, callable]:
    """A stop event and a progress callback that sets it once ``n_scans`` scans are done."""
    stop = threading.Event()
    return stop, (lambda n: stop.set() if n >= n_scans else None)


def _run_stopped(log, out, config, n_scans):
    """run_log stopped after ``n_scans`` scans, as a first Ctrl-C would stop it."""
    import submapslam.pipeline as pipeline

    stop, on_progress = _stop_after(n_scans)
    real_run = pipeline.run

    def run_with_progress(*args, **kwargs):
        kwargs["progress"] = on_progress
        return real_run(*args, **kwargs)

    pipeline.run = run_with_progress
    try:
        return run_log(log, out, config=config, stop=stop)
    finally:
        pipeline.run = real_run


@pytest.mark.parametrize("world, options, stop_at", [
    ("rectangle", {"size": (16.0, 10.0), "laps": 2}, 0.55),  # the measured odometry noise (2D)
    ("outdoor", {"laps": 1, "max_scans": 170}, 0.6),  # 11 submaps: the measured odometry noise (3D)
])
def test_resume_gives_the_uninterrupted_result(tmp_path, world, options, stop_at):
    log = generate(world, tmp_path / "log", seed=1, **options)
    config = PipelineConfig(checkpoint_every_submaps=2)
    full, _ = run_log(log, tmp_path / "full", config=config)
    assert full.loops_accepted > 0 or world == "outdoor"
    assert not checkpoint_folder(tmp_path / "full").exists()  # a finished run leaves no checkpoint
    cut = int(stop_at * full.n_scans)
    part, paths = _run_stopped(log, tmp_path / "part", config, cut)
    assert part.interrupted and part.n_scans == cut
    assert json.loads(paths["summary.json"].read_text())["interrupted"] is True
    checkpoint, _, started = read_checkpoint(tmp_path / "part")
    assert checkpoint.n_scans == cut and started["log"] == str(log.resolve())
    # the run's re-based start (odometry.startup_refit_scans) is kept, its odometry's own poses beside it
    assert checkpoint.run_frame is not None
    resumed, paths = run_log(None, tmp_path / "part", resume=True)
    assert not resumed.interrupted and resumed.n_scans == full.n_scans
    # the same to rounding: two uninterrupted 3D runs differ in the last bits too (threaded BLAS, TBB)
    np.testing.assert_allclose(resumed.poses, full.poses, rtol=0, atol=1e-9)
    np.testing.assert_allclose(resumed.submap_poses, full.submap_poses, rtol=0, atol=1e-9)
    assert [(lp.i, lp.j, lp.accepted, lp.reason) for lp in resumed.loops] == \
        [(lp.i, lp.j, lp.accepted, lp.reason) for lp in full.loops]
    assert (tmp_path / "part" / "loops.csv").read_bytes() == (tmp_path / "full" / "loops.csv").read_bytes()
    # the reported covariances too (the measured odometry noise comes back from the checkpoint)
    assert full.covariance_model["kind"] == "measured odometry noise"
    assert resumed.covariance_model.get("kind") == full.covariance_model.get("kind")
    np.testing.assert_allclose(resumed.submap_covariances, full.submap_covariances, rtol=1e-6, atol=1e-15)
    assert not checkpoint_folder(tmp_path / "part").exists()


def test_resume_cli_and_its_errors(tmp_path):
    log = generate("rectangle", tmp_path / "log", seed=2, laps=1, max_scans=120, size=(16.0, 10.0))
    assert_one_error_line(runner.invoke(app, ["run", "--resume", str(tmp_path / "nothing")]),
                          "no checkpoint to resume from")
    cfg = tmp_path / "c.yaml"
    cfg.write_text("checkpoint_every_submaps: 1\n")
    _run_stopped(log, tmp_path / "out", PipelineConfig(checkpoint_every_submaps=1), 70)
    r = runner.invoke(app, ["run", "--resume", str(tmp_path / "out"), "--max-scans", "90"])
    assert_one_error_line(r, "--max-scans cannot change a resumed run")
    r = runner.invoke(app, ["run", "--resume", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["scans"] == 120 and summary["interrupted"] is False
    other = generate("rectangle", tmp_path / "other", seed=3, laps=1, max_scans=60, size=(16.0, 10.0))
    _run_stopped(log, tmp_path / "out2", PipelineConfig(checkpoint_every_submaps=1), 50)
    assert_one_error_line(runner.invoke(app, ["run", str(other), "--resume", str(tmp_path / "out2")]),
                          "LOG cannot change a resumed run")
    with pytest.raises(SubmapSlamError, match="was started on"):
        run_log(other, tmp_path / "out2", resume=True)
