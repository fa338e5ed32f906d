"""CARMEN records besides FLASER: ROBOTLASER1 (own laser and robot poses), RAWLASER1..4 with ODOM,
the choice between kinds, and skipping damaged records."""

import itertools
import math

import numpy as np
import pytest

from submapslam.errors import ConfigError, InputError
from submapslam.io.compression import open_text
from submapslam.io.registry import open_log


def robotlaser_line(ranges, robot=(1.0, 2.0, 0.5), laser_offset=(0.2, 0.0, 0.0), ts=100.0, start=-math.pi / 2,
                    res=math.pi / 180, remissions=True, turn_axis=True, tag="ROBOTLASER1", max_range=50.0):
    """A ROBOTLASER line whose laser sits at ``laser_offset`` (x, y, theta) on the robot."""
    x, y, t = robot
    ox, oy, ot = laser_offset
    lx, ly, lt = x + math.cos(t) * ox - math.sin(t) * oy, y + math.sin(t) * ox + math.cos(t) * oy, t + ot
    r = " ".join(f"{v:.3f}" for v in ranges)
    rem = f"{len(ranges)} " + " ".join("0.5" for _ in ranges) + " " if remissions else ""
    tail = "0.3 0.1 0.5 0.5" + (" 0.0" if turn_axis else "")  # tv rv forward side [turn_axis]
    return (f"{tag} 0 {start:.6f} 3.141593 {res:.8f} {max_range} 0.01 0 {len(ranges)} {r} {rem}"
            f"{lx:.6f} {ly:.6f} {lt:.6f} {x:.6f} {y:.6f} {t:.6f} {tail} {ts:.6f} host {ts - 99:.6f}\n")


def rawlaser_line(ranges, ts, tag="RAWLASER1", start=-math.pi / 2, res=math.pi / 180):
    r = " ".join(f"{v:.3f}" for v in ranges)
    return f"{tag} 0 {start:.6f} 3.141593 {res:.8f} 50.0 0.01 0 {len(ranges)} {r} 0 {ts:.6f} host {ts - 99:.6f}\n"


def odom_line(x, y, t, ts):
    return f"ODOM {x:.6f} {y:.6f} {t:.6f} 0.0 0.0 0.0 {ts:.6f} host {ts - 99:.6f}\n"


def flaser_line(ranges, pose=(1.0, 2.0, 0.5), ts=100.0):
    r = " ".join(f"{v:.2f}" for v in ranges)
    x, y, t = pose
    return f"FLASER {len(ranges)} {r} {x} {y} {t} {x} {y} {t} {ts:.6f} host {ts - 99:.6f}\n"


def write(path, lines):
    path.write_text("# CARMEN log\nPARAM robot_frontlaser_offset 0.2 nohost 0\n" + "".join(lines))
    return path


@pytest.mark.parametrize("remissions,turn_axis", [(True, True), (False, False), (True, False)])
def test_robotlaser1_points_are_in_the_base_frame_and_the_robot_pose_is_the_odometry(tmp_path, remissions, turn_axis):
    ranges = np.full(181, 2.0)
    ranges[3] = 50.0  # at the record's maximum range: no return
    path = write(tmp_path / "r.clf", [robotlaser_line(ranges, remissions=remissions, turn_axis=turn_axis, ts=100.5),
                                      robotlaser_line(ranges, robot=(1.5, 2.0, 0.5), ts=100.6,
                                                      remissions=remissions, turn_axis=turn_axis)])
    reader = open_log(path)
    scans = list(reader)
    assert len(scans) == 2 and reader.log_info["laser_record"] == "ROBOTLASER1"
    s = scans[0]
    assert s.timestamp == pytest.approx(100.5) and s.planar
    assert s.points.shape == (180, 3)
    # the laser is 0.2 m ahead of the base: the beam straight ahead (index 90) ends at x = 2.2
    ahead = s.points[np.argmin(np.abs(s.points[:, 1]))]
    np.testing.assert_allclose(ahead, [2.2, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(s.points - [0.2, 0.0, 0.0], axis=1), 2.0, atol=1e-6)
    np.testing.assert_allclose(s.odometry[:2, 3], [1.0, 2.0])
    assert math.atan2(s.odometry[1, 0], s.odometry[0, 0]) == pytest.approx(0.5)
    np.testing.assert_allclose(scans[1].odometry[:2, 3], [1.5, 2.0])


def test_robotlaser1_uses_its_start_angle_and_resolution(tmp_path):
    path = write(tmp_path / "r.clf", [robotlaser_line([1.0, 1.0, 1.0], start=-0.5, res=0.25, laser_offset=(0, 0, 0))])
    (scan,) = list(open_log(path))
    np.testing.assert_allclose(np.arctan2(scan.points[:, 1], scan.points[:, 0]), [-0.5, -0.25, 0.0], atol=1e-6)


def test_rawlaser_odometry_is_interpolated_from_odom_lines(tmp_path):
    lines = [odom_line(0.0, 0.0, 0.0, 10.0), rawlaser_line([2.0] * 5, 10.5), rawlaser_line([2.0] * 5, 10.9),
             odom_line(1.0, 0.0, 0.2, 11.0), rawlaser_line([2.0] * 5, 11.5)]
    reader = open_log(write(tmp_path / "raw.log", lines))
    scans = list(reader)
    assert reader.log_info["laser_record"] == "RAWLASER1"
    assert [s.index for s in scans] == [0, 1, 2] and [s.timestamp for s in scans] == [10.5, 10.9, 11.5]
    np.testing.assert_allclose(scans[0].odometry[:2, 3], [0.5, 0.0], atol=1e-9)
    np.testing.assert_allclose(scans[1].odometry[:2, 3], [0.9, 0.0], atol=1e-9)
    assert math.atan2(scans[1].odometry[1, 0], scans[1].odometry[0, 0]) == pytest.approx(0.18)
    np.testing.assert_allclose(scans[2].odometry[:2, 3], [1.0, 0.0], atol=1e-9)  # after the last ODOM: held
    # stamps out of line order (as loggers write them): the pose is found by time
    lines = [odom_line(0.0, 0, 0, 10.0), odom_line(2.0, 0, 0, 12.0), rawlaser_line([2.0] * 5, 11.5),
             odom_line(1.0, 0, 0, 11.0), rawlaser_line([2.0] * 5, 10.5), odom_line(3.0, 0, 0, 13.0)]
    scans = list(open_log(write(tmp_path / "late.log", lines)))
    assert [s.timestamp for s in scans] == [11.5, 10.5]
    np.testing.assert_allclose([s.odometry[0, 3] for s in scans], [1.5, 0.5], atol=1e-9)
    # no ODOM lines at all: no odometry, the scans still come
    (scan,) = list(open_log(write(tmp_path / "bare.log", [rawlaser_line([2.0] * 5, 3.0)])))
    assert scan.odometry is None and len(scan.points) == 5


def test_a_log_with_several_kinds_reads_flaser_unless_told(tmp_path):
    lines = []
    for k in range(3):
        lines += [robotlaser_line([3.0] * 181, ts=100 + k), flaser_line([2.0] * 181, ts=100 + k + 0.01),
                  rawlaser_line([4.0] * 181, 100 + k + 0.02, tag="RAWLASER2")]
    path = write(tmp_path / "mixed.clf", lines)
    reader = open_log(path)
    assert reader.log_info["laser_record"] == "FLASER"
    assert np.linalg.norm(next(iter(reader)).points[0]) == pytest.approx(2.0)
    for laser, dist in (("robotlaser1", 3.0), ("RAWLASER2", 4.0), ("flaser", 2.0)):
        reader = open_log(path, "carmen", laser=laser)
        scans = list(reader)
        assert len(scans) == 3 and reader.log_info["laser_record"] == laser.upper()
        laser_on_base = [0.2, 0.0, 0.0] if laser == "robotlaser1" else [0.0, 0.0, 0.0]
        assert np.linalg.norm(scans[0].points[0] - laser_on_base) == pytest.approx(dist)
    with pytest.raises(InputError, match="no RAWLASER3 lines.*it holds FLASER, ROBOTLASER1, RAWLASER2"):
        list(open_log(path, "carmen", laser="rawlaser3"))
    with pytest.raises(ConfigError, match="unknown CARMEN laser 'laser9'"):
        open_log(path, "carmen", laser="laser9")


def test_a_robotlaser_only_log_no_longer_ends_in_no_flaser(tmp_path):
    path = write(tmp_path / "fr.log", [robotlaser_line([2.0] * 361, ts=100 + 0.1 * k, res=math.pi / 360)
                                       for k in range(4)])
    assert len(list(open_log(path))) == 4


@pytest.mark.parametrize("make,damage", [
    (lambda: robotlaser_line([2.0] * 10), lambda ln: ln[: len(ln) // 2] + "\n"),
    (lambda: robotlaser_line([2.0] * 10), lambda ln: ln.replace(" 100.000000 host", " nan host")),
    (lambda: rawlaser_line([2.0] * 10, 100.0), lambda ln: ln.replace(" 10 ", " 12 ", 1)),
    (lambda: flaser_line([2.0] * 10), lambda ln: ln.replace("2.00", "2.x0", 1)),
])
def test_damaged_records_stop_with_the_line_or_are_skipped_and_counted(tmp_path, make, damage):
    good = make()
    bad = damage(good)
    path = write(tmp_path / "d.clf", [good, bad, good, bad, good])
    with pytest.raises(InputError, match=r"d\.clf:4: "):  # two header lines: the first damaged record is line 4
        list(open_log(path))
    reader = open_log(path, skip_bad=True)
    scans = list(reader)
    assert len(scans) == 3 and [s.index for s in scans] == [0, 1, 2]
    assert reader.log_info["skipped_records"] == 2 and reader.log_info["skipped_record_lines"] == [4, 6]
    for s in scans:
        assert np.isfinite(s.points).all()


def test_a_folder_given_as_carmen_says_so(tmp_path):
    with pytest.raises(InputError, match="is a folder, not a CARMEN log file"):
        open_log(tmp_path, "carmen")


def _rewrite_tool():

    from .conftest import load_tool

    return load_tool("carmen_rewrite_records")


@pytest.mark.parametrize("name", ["intel.clf.bz2", "fr079.clf.bz2"])
def test_real_scans_rewritten_as_robotlaser1_and_rawlaser1_read_the_same(tmp_path, name):
    """No log in ../shared/data holds these records: the first real FLASER scans of Intel (180
    beams) and FR079 (360) are rewritten (tools/carmen_rewrite_records.py) as ROBOTLASER1 (laser
    0.1 m ahead of the base) and as RAWLASER1 + ODOM, and must give the FLASER reading's points
    and odometry (also where Intel's ipc timestamps run backwards, scans 148-156: the ODOM pose
    is found by time, not by line)."""
    from .conftest import shared_data

    src = shared_data("carmen", name)
    tool = _rewrite_tool()
    head = tmp_path / "head.clf"
    head.write_text("".join(itertools.islice(open_text(src), 700)))
    assert tool.main([str(head), str(tmp_path / "r.clf.gz"), "--record", "robotlaser1", "--laser-offset", "0.1"]) == 0
    assert tool.main([str(head), str(tmp_path / "w.clf"), "--record", "rawlaser1"]) == 0
    reference = list(open_log(head))
    robot_reader, raw_reader = open_log(tmp_path / "r.clf.gz"), open_log(tmp_path / "w.clf")
    robot_scans, raw_scans = list(robot_reader), list(raw_reader)
    assert robot_reader.log_info["laser_record"] == "ROBOTLASER1" and raw_reader.log_info["laser_record"] == "RAWLASER1"
    assert len(reference) > 150 and len(reference) == len(robot_scans) == len(raw_scans)
    if name.startswith("intel"):  # the slice holds the stamps that run backwards
        assert np.any(np.diff([s.timestamp for s in reference]) < 0)
    for f, r, w in zip(reference, robot_scans, raw_scans):
        assert r.timestamp == f.timestamp and w.timestamp == f.timestamp
        np.testing.assert_allclose(r.odometry, f.odometry, atol=1e-6)
        np.testing.assert_allclose(w.odometry, f.odometry, atol=1e-6)
        np.testing.assert_allclose(w.points, f.points, atol=1e-6)
        np.testing.assert_allclose(r.points - [0.1, 0.0, 0.0], f.points, atol=1e-5)


def test_robotlaser1_logs_are_trajectories_too(tmp_path):
    """eval/compare read a ROBOTLASER1-only log (e.g. a corrected Freiburg log) as the robot poses."""
    from submapslam.io.trajectory import read_carmen_trajectory, read_trajectory

    lines = [robotlaser_line([2.0] * 5, robot=(0.5 * k, 1.0, 0.1 * k), ts=100.0 + k) for k in range(4)]
    path = write(tmp_path / "corrected.log", lines)
    traj = read_trajectory(path)
    np.testing.assert_allclose(traj.timestamps, 100.0 + np.arange(4))
    np.testing.assert_allclose(traj.poses[:, 0, 3], 0.5 * np.arange(4), atol=1e-6)
    np.testing.assert_allclose(read_carmen_trajectory(path, "logger").timestamps, 1.0 + np.arange(4))
    # where a log holds both, the FLASER poses are the trajectory
    both = write(tmp_path / "both.log", lines + [flaser_line([2.0] * 5, pose=(9.0, 9.0, 0.0), ts=200.0)])
    assert read_trajectory(both).poses[:, 0, 3].tolist() == [9.0]
