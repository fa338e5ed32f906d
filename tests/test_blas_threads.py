"""A run keeps BLAS to one thread while it works, and gives the caller's setting back after."""

from __future__ import annotations

import numpy as np
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
