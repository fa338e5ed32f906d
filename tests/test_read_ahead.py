"""The background scan reader: the same scans in order, errors where they happened, and no more
points held ahead than its budget."""

from __future__ import annotations

import time

import numpy as np
import pytest

from submapslam.pipeline import ReadAhead
from submapslam.scan import Scan


def _scans(count: int, points: int, produced: list[int]):
    for k in range(count):
        produced.append(k)
        yield Scan(index=k, timestamp=float(k), points=np.zeros((points, 3)))


def _wait_for(produced: list[int], count: int, timeout: float = 30.0) -> None:
    """Let the reader thread read ``count`` scans (however loaded the machine), then a little more
    time to read past them if it would."""
    deadline = time.monotonic() + timeout
    while len(produced) < count and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.3)


def test_the_same_scans_in_order():
    produced: list[int] = []
    with ReadAhead(_scans(30, 10, produced), depth=4) as scans:
        assert [s.index for s in scans] == list(range(30))


def test_small_scans_are_read_depth_ahead():
    produced: list[int] = []
    with ReadAhead(_scans(30, 10, produced), depth=4) as scans:
        next(scans)
        _wait_for(produced, 1 + 4)
        assert len(produced) >= 1 + 4  # the queue is full: the budget does not hold small scans back


def test_large_scans_are_held_ahead_only_within_the_byte_budget():
    produced: list[int] = []
    scan_bytes = 1000 * 3 * 8
    with ReadAhead(_scans(30, 1000, produced), depth=8, max_bytes=2 * scan_bytes) as scans:
        next(scans)
        _wait_for(produced, 1 + 2 + 1)
        # taken 1, queued 2 (the budget), 1 read and waiting for room; 8 queued without the budget
        assert len(produced) == 1 + 2 + 1
        assert [s.index for s in scans] == list(range(1, 30))


def test_one_scan_larger_than_the_budget_still_passes():
    produced: list[int] = []
    with ReadAhead(_scans(5, 1000, produced), depth=8, max_bytes=10) as scans:
        assert [s.index for s in scans] == list(range(5))


def test_a_reader_error_comes_out_where_it_happened():
    def failing():
        yield Scan(index=0, timestamp=0.0, points=np.zeros((5, 3)))
        raise ValueError("broken record")

    with ReadAhead(failing()) as scans:
        assert next(scans).index == 0
        with pytest.raises(ValueError, match="broken record"):
            next(scans)
