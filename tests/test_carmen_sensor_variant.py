"""tools/carmen_sensor_variant.py: a real CARMEN log as a scanner with fewer beams, a shorter range or
noisier ranges, or a robot with miscalibrated wheels, would have recorded it (the robustness rows of
BENCHMARKS.md)."""

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


def test_range_noise_moves_the_returns_along_their_beams_and_keeps_the_no_returns(tool, tmp_path):
    """3 cm of noise: each point stays on its beam, moved about 3 cm along it; the scanner's
    no-return reading stays a no-return; the same seed writes the same file."""
    src = shared_data("carmen", "intel.clf.bz2")
    whole, noisy, again = tmp_path / "whole.clf", tmp_path / "noisy.clf", tmp_path / "again.clf"
    tool.write_variant(src, noisy, range_noise=0.03, seed=3, max_lines=LINES)
    tool.write_variant(src, again, range_noise=0.03, seed=3, max_lines=LINES)
    assert noisy.read_bytes() == again.read_bytes()
    _head(src, whole, LINES)
    moved = []
    for a, b in zip(_scans(whole), _scans(noisy)):
        assert len(a.points) == len(b.points) and len(a.no_returns) == len(b.no_returns)
        ra, rb = np.linalg.norm(a.points[:, :2], axis=1), np.linalg.norm(b.points[:, :2], axis=1)
        ua, ub = a.points[:, :2] / ra[:, None], b.points[:, :2] / rb[:, None]
        assert np.allclose(ua, ub, atol=1e-6)  # the same beam directions
        moved.append(rb - ra)
    moved = np.concatenate(moved)
    assert 0.025 < moved.std() < 0.035 and abs(moved.mean()) < 0.003


def test_miscalibrated_wheels_scale_every_step_of_the_recorded_poses(tool, tmp_path):
    """Travel x 0.97 and turn x 1.05: each scan's odometry step, taken in the previous pose's frame,
    is the original step scaled so; the first pose is kept."""
    from submapslam.geometry import matrix_to_se2

    src = shared_data("carmen", "intel.clf.bz2")
    whole, worn = tmp_path / "whole.clf", tmp_path / "worn.clf"
    tool.write_variant(src, worn, odometry_scale=0.97, odometry_turn_scale=1.05, max_lines=LINES)
    _head(src, whole, LINES)
    a, b = _scans(whole), _scans(worn)
    assert np.allclose(a[0].odometry, b[0].odometry, atol=1e-5)
    turned = 0.0
    for k in range(1, len(a)):
        da = matrix_to_se2(np.linalg.inv(a[k - 1].odometry) @ a[k].odometry)
        db = matrix_to_se2(np.linalg.inv(b[k - 1].odometry) @ b[k].odometry)
        assert np.allclose(db[:2], 0.97 * da[:2], atol=2e-5)
        assert abs(db[2] - 1.05 * da[2]) < 2e-5
        turned += abs(da[2])
    assert turned > 1.0  # the robot turns in these scans: the turn scale is tested


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
    assert tool.main([str(log), str(tmp_path / "x.clf")]) == 1  # no option: one clear line, no file
    assert not (tmp_path / "x.clf").exists()
    assert tool.main([str(log), str(tmp_path / "x.clf"), "--range-noise", "-0.01"]) == 1
    assert tool.main([str(log), str(tmp_path / "x.clf"), "--odometry-scale", "0"]) == 1
    assert not (tmp_path / "x.clf").exists()


def _head(src, dst, n):
    """The first ``n`` lines of a compressed log as a plain file."""
    from submapslam.io.compression import open_text

    with open_text(src) as lines, open(dst, "w") as out:
        for _, line in zip(range(n), lines):
            out.write(line)
