import bz2
import gzip
import itertools

import numpy as np
import pytest

from submapslam.errors import InputError, UnknownFormatError
from submapslam.io.carmen import beam_angles
from submapslam.io.registry import available_formats, open_log

from .conftest import shared_data


def carmen_line(ranges, pose=(1.0, 2.0, 0.5), ts=100.0):
    r = " ".join(f"{v:.2f}" for v in ranges)
    x, y, t = pose
    return f"FLASER {len(ranges)} {r} {x} {y} {t} {x} {y} {t} {ts:.6f} host {ts - 99:.6f}\n"


def write_log(path, lines, opener=open):
    with opener(path, "wt") as fh:
        fh.write("# CARMEN log\nPARAM robot_frontlaser_offset 0.0 nohost 0\n")
        fh.write("ODOM 0 0 0 0 0 0 99.0 host 0.0\n")
        fh.writelines(lines)


def test_beam_angles_follow_the_carmen_convention():
    a = beam_angles(180)
    assert a[0] == pytest.approx(-np.pi / 2) and a[1] - a[0] == pytest.approx(np.deg2rad(1.0))
    a = beam_angles(361)
    assert a[0] == pytest.approx(-np.pi / 2) and a[-1] == pytest.approx(np.pi / 2)
    assert beam_angles(180, rear=True)[0] == pytest.approx(np.pi / 2)


@pytest.mark.parametrize("suffix,opener", [(".clf", open), (".clf.gz", gzip.open), (".log.bz2", bz2.open)])
def test_carmen_points_pose_and_timestamp(tmp_path, suffix, opener):
    path = tmp_path / f"a{suffix}"
    ranges = np.full(181, 2.0)
    ranges[5] = 81.9  # no return
    write_log(path, [carmen_line(ranges, ts=100.5), carmen_line(ranges, (2.0, 2.0, 0.0), ts=100.6)], opener)
    scans = list(open_log(path))
    assert len(scans) == 2
    s = scans[0]
    assert s.planar and s.timestamp == pytest.approx(100.5)
    assert s.points.shape == (180, 3)  # the 81.9 m reading is dropped
    np.testing.assert_allclose(np.linalg.norm(s.points, axis=1), 2.0)
    np.testing.assert_allclose(s.points[:, 2], 0.0)
    # first beam points to the right (-90 deg)
    np.testing.assert_allclose(s.points[0], [0.0, -2.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(s.odometry[:2, 3], [1.0, 2.0])
    assert s.odometry[0, 0] == pytest.approx(np.cos(0.5))


def test_truncated_carmen_log_names_file_and_line(tmp_path):
    path = tmp_path / "trunc.clf"
    good = carmen_line(np.full(180, 3.0))
    write_log(path, [good, good, good[: len(good) // 2] + "\n"])
    it = iter(open_log(path))
    assert len(list(itertools.islice(it, 2))) == 2  # scans before the damage are delivered
    with pytest.raises(InputError, match=r"trunc\.clf:6: FLASER line is truncated"):
        next(it)


def test_garbled_carmen_line(tmp_path):
    path = tmp_path / "garbled.clf"
    line = carmen_line(np.full(180, 3.0)).replace("3.00", "3.x0", 1)
    write_log(path, [line])
    with pytest.raises(InputError, match=r"garbled\.clf:4: FLASER line has a non-numeric field"):
        list(open_log(path))
    path.write_text("\x00\x01binary junk here\n")
    with pytest.raises(InputError, match="binary data, not a text CARMEN log"):
        list(open_log(path, "carmen"))


def test_unknown_and_forced_format(tmp_path):
    p = tmp_path / "thing.xyz"
    p.write_text("hello world\n")
    with pytest.raises(UnknownFormatError, match="cannot tell the log format"):
        open_log(p)
    with pytest.raises(UnknownFormatError, match="unknown format 'nope'"):
        open_log(p, "nope")
    with pytest.raises(InputError, match="no such file"):
        open_log(tmp_path / "missing.clf")
    assert {"carmen", "cloud_folder"} <= set(available_formats())


def test_real_intel_log_head():
    path = shared_data("carmen", "intel.clf.bz2")
    scans = list(itertools.islice(open_log(path), 50))
    assert len(scans) == 50
    assert all(s.points.shape[1] == 3 and 100 <= len(s.points) <= 180 for s in scans)
    assert scans[0].timestamp == pytest.approx(976052857.337530, abs=1e-6)
    # real logs jitter a little (ipc timestamps are not strictly monotonic), but move forward
    assert np.mean(np.diff([s.timestamp for s in scans]) > 0) > 0.9


def write_bin(path, pts):
    rec = np.zeros((len(pts), 4), np.float32)
    rec[:, :3] = pts
    rec.tofile(path)


def test_kitti_bin_folder_with_times_and_odometry(tmp_path):
    (tmp_path / "velodyne").mkdir()
    rng = np.random.default_rng(0)
    clouds = [rng.normal(size=(100, 3)) for _ in range(3)]
    for k, c in enumerate(clouds):
        write_bin(tmp_path / "velodyne" / f"{k:06d}.bin", c)
    (tmp_path / "times.txt").write_text("0.0\n0.1\n0.2\n")
    (tmp_path / "odometry_tum.txt").write_text(
        "0.0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n0.2 2 0 0 0 0 0 1\n")
    scans = list(open_log(tmp_path))
    assert [s.timestamp for s in scans] == [0.0, 0.1, 0.2]
    np.testing.assert_allclose(scans[1].points, clouds[1], atol=1e-6)
    np.testing.assert_allclose(scans[2].odometry[:3, 3], [2, 0, 0])
    assert not scans[0].planar


def test_cloud_folder_mounting_moves_points_into_the_base_frame(tmp_path):
    (tmp_path / "velodyne").mkdir()
    cloud = np.random.default_rng(1).normal(size=(50, 3))
    write_bin(tmp_path / "velodyne" / "000000.bin", cloud)
    c, s = float(np.cos(0.5)), float(np.sin(0.5))
    T = [[c, -s, 0, 0.4], [s, c, 0, 0.0], [0, 0, 1, 1.2], [0, 0, 0, 1]]
    (tmp_path / "meta.yaml").write_text(f"T_base_sensor: {T}\n")
    scan = next(iter(open_log(tmp_path)))
    np.testing.assert_allclose(scan.points, cloud @ np.array(T)[:3, :3].T + [0.4, 0.0, 1.2], atol=1e-6)
    (tmp_path / "meta.yaml").write_text("T_base_sensor: [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n")
    with pytest.raises(InputError, match=r"meta\.yaml: T_base_sensor is not a rigid transform"):
        open_log(tmp_path)


def test_bad_bin_size_and_short_times(tmp_path):
    (tmp_path / "000000.bin").write_bytes(b"\x00" * 10)
    with pytest.raises(InputError, match="not a whole number"):
        list(open_log(tmp_path))
    (tmp_path / "000000.bin").write_bytes(b"\x00" * 16)
    (tmp_path / "000001.bin").write_bytes(b"\x00" * 16)
    (tmp_path / "times.txt").write_text("0.0\n")
    with pytest.raises(InputError, match="1 timestamps for 2 scans"):
        open_log(tmp_path)


def test_empty_folder_is_unknown(tmp_path):
    with pytest.raises(UnknownFormatError):
        open_log(tmp_path)


def test_real_mulran_pcd_folder():
    folder = shared_data("lidar3d", "mulran_kaist03")
    reader = open_log(folder)
    assert len(reader) == 21
    scan = next(iter(reader))
    assert 30_000 < len(scan.points) < 45_000
    assert np.isfinite(scan.points).all()
    assert scan.timestamp > 1e9  # unix time from times.txt.xz


def test_carmen_laser_choice_is_checked(tmp_path):
    from submapslam.errors import ConfigError
    from submapslam.io.carmen import CarmenReader

    path = tmp_path / "two.clf"
    front = carmen_line(np.full(180, 2.0), ts=100.5)
    write_log(path, [front, front.replace("FLASER", "RLASER").replace(" 2.00 ", " 3.00 ", 1)])
    for laser in ("Front", "back", ""):
        with pytest.raises(ConfigError) as err:
            CarmenReader(path, laser=laser)
        assert str(err.value) == (f"unknown CARMEN laser {laser!r}: use one of front, rear, flaser, robotlaser1, "
                                  "rawlaser1, rlaser, robotlaser2, rawlaser2, rawlaser3, rawlaser4")
    with pytest.raises(ConfigError, match="unknown CARMEN laser 'Front'"):
        open_log(path, "carmen", laser="Front")
    # the two known lasers read their own lines: the rear one starts at +90 degrees
    (rear,) = list(open_log(path, "carmen", laser="rear"))
    np.testing.assert_allclose(rear.points[0], [0.0, 3.0, 0.0], atol=1e-9)
    (front_scan,) = list(open_log(path, "carmen", laser="front"))
    np.testing.assert_allclose(front_scan.points[0], [0.0, -2.0, 0.0], atol=1e-9)


def test_carmen_trajectory_timestamp_choice_is_checked(tmp_path):
    from submapslam.errors import ConfigError
    from submapslam.io.trajectory import read_carmen_trajectory

    path = tmp_path / "a.clf"
    write_log(path, [carmen_line(np.full(180, 2.0), ts=100.5)])
    assert read_carmen_trajectory(path, "logger").timestamps[0] == pytest.approx(1.5)
    assert read_carmen_trajectory(path).timestamps[0] == pytest.approx(100.5)
    with pytest.raises(ConfigError) as err:
        read_carmen_trajectory(path, "IPC")
    assert str(err.value) == "unknown CARMEN timestamp 'IPC': use ipc or logger"


def _ply_bytes(fields: list[tuple[str, str, str]], records: np.ndarray, order: str = "binary_little_endian") -> bytes:
    head = ["ply", f"format {order} 1.0", f"element vertex {len(records)}"]
    head += [f"property {ply_type} {name}" for name, ply_type, _ in fields] + ["end_header"]
    return ("\n".join(head) + "\n").encode() + records.tobytes()


@pytest.mark.parametrize("order, endian", [("binary_little_endian", "<"), ("binary_big_endian", ">")])
def test_binary_ply_fast_path_reads_what_open3d_reads(tmp_path, order, endian):
    from submapslam._deps import open3d
    from submapslam.io.cloud_folder import read_cloud

    rng = np.random.default_rng(5)
    fields = [("x", "float", "f4"), ("y", "float", "f4"), ("z", "float", "f4"), ("intensity", "float", "f4"),
              ("ring", "ushort", "u2"), ("time", "float", "f4")]
    dtype = np.dtype([(name, endian + code) for name, _, code in fields])
    records = np.zeros(500, dtype=dtype)
    for name in ("x", "y", "z", "intensity", "time"):
        records[name] = rng.normal(size=500) * 20
    records["ring"] = rng.integers(0, 16, 500)
    path = tmp_path / "scan.ply"
    path.write_bytes(_ply_bytes(fields, records, order))
    points, times = read_cloud(path)
    assert points.dtype == np.float64 and points.shape == (500, 3)
    assert np.array_equal(points[:, 0], records["x"].astype(np.float64))
    assert np.array_equal(times, records["time"].astype(np.float64))
    if order == "binary_little_endian":  # what the open3d reader gives for the same file
        pcd = open3d().t.io.read_point_cloud(str(path))
        assert np.array_equal(points, pcd.point.positions.numpy().astype(np.float64))
    # double coordinates, no time field
    doubles = np.zeros(7, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
    doubles["x"] = np.arange(7) * 0.1
    path.write_bytes(_ply_bytes([("x", "double", "f8"), ("y", "double", "f8"), ("z", "double", "f8")], doubles))
    points, times = read_cloud(path)
    assert times is None and np.array_equal(points[:, 0], doubles["x"])


def test_ply_the_fast_path_does_not_describe_goes_to_open3d(tmp_path):
    from submapslam.io.cloud_folder import read_cloud
    from submapslam.io.ply import vertex_dtype

    ascii_ply = b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n" \
                b"end_header\n1 2 3\n4 5 6\n"
    assert vertex_dtype(ascii_ply) is None
    path = tmp_path / "a.ply"
    path.write_bytes(ascii_ply)
    points, _ = read_cloud(path)
    assert np.array_equal(points, [[1, 2, 3], [4, 5, 6]])
    with_faces = b"ply\nformat binary_little_endian 1.0\nelement face 1\nproperty list uchar int vertex_indices\n" \
                 b"element vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    assert vertex_dtype(with_faces) is None  # another element first: its size is not known here
    listed = b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n" \
             b"property float z\nproperty list uchar int idx\nend_header\n"
    assert vertex_dtype(listed) is None


def test_binary_pcd_fast_path_reads_what_open3d_reads(tmp_path):
    """A binary PCD (x y z, intensity, a uint16 ring, a 3-count field, per-point time) read with
    numpy gives open3d's points; an ASCII body and a body of the wrong size go to open3d."""
    from submapslam._deps import open3d
    from submapslam.io.cloud_folder import read_cloud
    from submapslam.io.pcd import read_pcd_records

    rng = np.random.default_rng(7)
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("ring", "<u2"),
                      ("rgb", "<u1", (3,)), ("t", "<f8")])
    records = np.zeros(300, dtype=dtype)
    for name in ("x", "y", "z", "intensity", "t"):
        records[name] = rng.normal(size=300) * 20
    records["ring"] = rng.integers(0, 16, 300)
    head = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity ring rgb t\nSIZE 4 4 4 4 2 1 8\n"
            "TYPE F F F F U U F\nCOUNT 1 1 1 1 1 3 1\nWIDTH 300\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
            "POINTS 300\nDATA binary\n")
    path = tmp_path / "scan.pcd"
    path.write_bytes(head.encode() + records.tobytes())
    assert read_pcd_records(path) is not None
    points, times = read_cloud(path)
    assert points.dtype == np.float64 and points.shape == (300, 3)
    assert np.array_equal(times, records["t"])
    plain = tmp_path / "plain.pcd"  # open3d's own reading of the x/y/z part
    xyz = np.zeros(300, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    for name in "xyz":
        xyz[name] = records[name]
    plain.write_bytes((b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 300\n"
                       b"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 300\nDATA binary\n") + xyz.tobytes())
    o3d_points = open3d().t.io.read_point_cloud(str(plain)).point.positions.numpy().astype(np.float64)
    assert np.array_equal(points, o3d_points) and np.array_equal(read_cloud(plain)[0], o3d_points)
    ascii_pcd = tmp_path / "a.pcd"
    ascii_pcd.write_text("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\n"
                         "HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n1 2 3\n4 5 6\n")
    assert read_pcd_records(ascii_pcd) is None
    assert np.array_equal(read_cloud(ascii_pcd)[0], [[1, 2, 3], [4, 5, 6]])
    short = tmp_path / "short.pcd"  # one record missing: not read here (check_cloud_file or open3d decide)
    short.write_bytes(head.encode() + records[:-1].tobytes())
    assert read_pcd_records(short) is None
