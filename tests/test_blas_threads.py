"""A run keeps BLAS to one thread while it works, and gives the caller's setting back after; the
command line's process allocates from one malloc arena."""

from __future__ import annotations

import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from datasets_synth import generate
from submapslam.config import PipelineConfig
from submapslam.io.registry import open_log
from submapslam.observer import RunObserver
from submapslam.pipeline import run
from submapslam.process_stats import single_threaded_blas


def _blas_threads() -> set[int]:
    return {pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"}


def test_single_threaded_blas_limits_and_restores():
    with threadpool_limits(limits=2, user_api="blas"):
        callers = _blas_threads()  # {2} where the machine has two cores
        with single_threaded_blas():
            assert _blas_threads() == {1}
            assert float(np.ones((300, 3)).T @ np.ones(300) @ np.ones(3)) == 900.0  # still computes
        assert _blas_threads() == callers


class _Watch(RunObserver):
    def __init__(self) -> None:
        self.seen: list[set[int]] = []

    def on_scan(self, index, timestamp, T_odom_base, points) -> None:
        if index % 10 == 0:
            self.seen.append(_blas_threads())


def test_a_run_works_with_one_blas_thread_and_restores_the_callers(tmp_path):
    log = generate("rectangle", tmp_path / "log", laps=1, max_scans=30)
    watch = _Watch()
    with threadpool_limits(limits=2, user_api="blas"):
        callers = _blas_threads()
        result = run(open_log(log), PipelineConfig(), observer=watch)
        assert _blas_threads() == callers  # the caller's limit is back
    assert len(result.poses) == 30 and watch.seen and all(s == {1} for s in watch.seen)


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt(M_ARENA_MAX) is glibc's")
def test_the_command_line_asks_glibc_for_one_malloc_arena():
    # in a process of its own: the setting is process-wide and permanent
    code = "from submapslam.process_stats import one_malloc_arena; print(one_malloc_arena())"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == "True", done.stderr
    source = (Path(__file__).resolve().parents[1] / "submapslam" / "cli" / "__init__.py").read_text()
    assert "one_malloc_arena()" in source.split("def main()")[1]  # the entry point sets it before the app runs
