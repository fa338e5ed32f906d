"""tools/carmen_sensor_variant.py: a real CARMEN log as a scanner with fewer beams or a shorter range
would have recorded it (the robustness rows of BENCHMARKS.md)."""

import numpy as np
import pytest

from submapslam.io.registry import open_log

from .conftest import load_tool, shared_data

LINES = 1200  # Intel's first lines: about 450 scans (the reader finds a no-return value from about 400)


@pytest.fixture(scope="module")
def tool():
    return load_tool("carmen_sensor_variant")


def _scans(path):
    return list(open_log(path))


def test_every_second_beam_keeps_the_kept_beams_where_they_were(tool, tmp_path):
    """Each variant scan holds exactly the original's points of every second beam: the reader's
    layout for 90 beams puts them at the angles they had among 180."""
    src = shared_data("carmen", "intel.clf.bz2")
    whole, half = tmp_path / "whole.clf", tmp_path / "half.clf"
    n = tool.write_variant(src, half, every_beam=2, max_lines=LINES)
    _head(src, whole, LINES)
    original, variant = _scans(whole), _scans(half)
    assert n == len(original) == len(variant) > 100
    for a, b in zip(original, variant):
        assert a.timestamp == b.timestamp
        rows = {tuple(p) for p in np.round(a.points, 9)}
        assert all(tuple(p) in rows for p in np.round(b.points, 9))  # every kept point is an original one
        assert 0.4 * len(a.points) <= len(b.points) <= 0.6 * len(a.points)


def test_a_shorter_range_turns_far_beams_into_no_returns(tool, tmp_path):
    """Ranges beyond 8 m become 8 m, which the reader takes as the scanner's maximum: no point
    beyond it, those beams free space (no-returns), the near points unchanged."""
    src = shared_data("carmen", "intel.clf.bz2")
    whole, short = tmp_path / "whole.clf", tmp_path / "short.clf"
    tool.write_variant(src, short, max_range=8.0, max_lines=LINES)
    _head(src, whole, LINES)
    original, variant = _scans(whole), _scans(short)
    far = sum(int((np.linalg.norm(s.points[:, :2], axis=1) > 8.0).sum()) for s in original)
    assert far > 100  # the test means something: Intel's first scans see beyond 8 m
    for a, b in zip(original, variant):
        assert np.linalg.norm(b.points[:, :2], axis=1).max() < 8.0
        near = a.points[np.linalg.norm(a.points[:, :2], axis=1) < 7.9]
        rows = {tuple(p) for p in np.round(b.points, 9)}
        assert all(tuple(p) in rows for p in np.round(near, 9))
    assert sum(len(s.no_returns) for s in variant) >= far


def test_a_layout_that_would_move_the_beams_and_an_existing_file_are_refused(tool, tmp_path):
    """90 beams every 2nd would be 45, which the reader spreads over 180 deg in 44 steps, not 4 deg
    apart: refused, nothing left behind. An existing DST is never overwritten."""
    log = tmp_path / "ninety.clf"
    ranges = " ".join(["2.0"] * 90)
    log.write_text(f"FLASER 90 {ranges} 0 0 0 0 0 0 1000.0 host 0.0\n")
    dst = tmp_path / "out.clf"
    assert tool.main([str(log), str(dst), "--every-beam", "2"]) == 1
    assert not dst.exists()
    dst.write_text("mine\n")
    assert tool.main([str(log), str(dst), "--max-range", "1"]) == 1
    assert dst.read_text() == "mine\n"
    assert tool.main([str(log), str(tmp_path / "x.clf")]) == 1  # neither option: one clear line, no file
    assert not (tmp_path / "x.clf").exists()


def _head(src, dst, n):
    """The first ``n`` lines of a compressed log as a plain file."""
    from submapslam.io.compression import open_text

    with open_text(src) as lines, open(dst, "w") as out:
        for _, line in zip(range(n), lines):
            out.write(line)
