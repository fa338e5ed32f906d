"""ROS bag reader: round trips through the rosbags writers, message decoding, odometry
interpolation, topic choice, damaged files, and a run on a bag against the same cloud folder."""

import math
import os
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from typer.testing import CliRunner

from datasets_synth import generate
from submapslam.cli import app
from submapslam.errors import InputError
from submapslam.io.registry import open_log
from submapslam.io.rosbag import RosbagReader, laserscan_to_points, pointcloud2_to_points, slerp
from submapslam.io.trajectory import read_tum

from .conftest import load_tool

to_bag = load_tool("cloud_folder_to_bag")

T0 = 1_700_000_000  # header stamps [s]


# ---------------------------------------------------------------------------- bag writing helpers
class BagWriter:
    """Write messages with the rosbags writers: ``.bag`` -> ROS 1, ``.mcap`` -> bare MCAP file,
    anything else -> ROS 2 sqlite3 folder."""

    def __init__(self, path: Path, frame: str = "frame"):
        self.path = path
        self.frame = frame
        self.m = to_bag._Messages(ros1=path.suffix == ".bag")
        self.T = self.m.T
        self.msgs: list[tuple[str, str, int, object]] = []

    def header(self, t):
        return self.m.header(t, self.frame)

    def add(self, topic, msgtype, t, msg):
        # recorded 13 ms after the header stamp: scan times must come from the header, not the bag
        self.msgs.append((topic, msgtype, int(round((t + 0.013) * 1e9)), msg))

    def cloud(self, topic, t, points, times=None, time_type=7):
        rec = np.zeros(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("pad", "<f4"), ("t", "<u4")])
        rec["x"], rec["y"], rec["z"] = points.T
        fields = [self.T["sensor_msgs/msg/PointField"](name=n, offset=4 * k, datatype=7, count=1)
                  for k, n in enumerate("xyz")]
        if times is not None:
            rec["t"] = times
            fields.append(self.T["sensor_msgs/msg/PointField"](name="t", offset=16, datatype=6, count=1))
        msg = self.T["sensor_msgs/msg/PointCloud2"](
            header=self.header(t), height=1, width=len(rec), fields=fields, is_bigendian=False, point_step=20,
            row_step=20 * len(rec), data=np.frombuffer(rec.tobytes(), dtype=np.uint8), is_dense=False)
        self.add(topic, "sensor_msgs/msg/PointCloud2", t, msg)

    def laser(self, topic, t, ranges, angle_min=-math.pi / 2, inc=math.pi / 180, rmin=0.1, rmax=30.0):
        msg = self.T["sensor_msgs/msg/LaserScan"](
            header=self.header(t), angle_min=angle_min, angle_max=angle_min + inc * (len(ranges) - 1),
            angle_increment=inc, time_increment=0.0, scan_time=0.0, range_min=rmin, range_max=rmax,
            ranges=np.asarray(ranges, dtype=np.float32), intensities=np.zeros(0, dtype=np.float32))
        self.add(topic, "sensor_msgs/msg/LaserScan", t, msg)

    def odom(self, topic, t, x, y, yaw, child="base_link"):
        T = np.eye(4)
        T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        T[:2, 3] = x, y
        self.odom_pose(topic, t, T, child)

    def odom_pose(self, topic, t, T, child="base_link"):
        msg = self.m.odometry(t, T)
        msg.child_frame_id = child
        self.add(topic, "nav_msgs/msg/Odometry", t, msg)

    def tf(self, topic, t, parent, child, T):
        self.add(topic, "tf2_msgs/msg/TFMessage", t, self.m.tf(t, parent, child, T))

    def write(self) -> Path:
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        if self.path.suffix == ".bag":
            writer, target = Writer1(self.path), self.path
        elif self.path.suffix == ".mcap":
            target = self.path.with_suffix("")
            writer = Writer2(target, version=9, storage_plugin=StoragePlugin.MCAP)
        else:
            writer, target = Writer2(self.path, version=9), self.path
        with writer:
            conns = {}
            for topic, msgtype, t_ns, msg in self.msgs:
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=self.m.store)
                writer.write(conns[topic], t_ns, self.m.serialize(msg, msgtype))
        if self.path.suffix == ".mcap":
            shutil.move(target / f"{target.name}.mcap", self.path)
            shutil.rmtree(target)
        return self.path


def random_clouds(n_scans, n_points, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.uniform(-20, 20, (n_points, 3)).astype(np.float32) for _ in range(n_scans)]


# ---------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("name", ["a.bag", "a.mcap", "a_ros2"])
def test_pointcloud2_round_trip(tmp_path, name):
    clouds = random_clouds(4, 300)
    clouds[1][7] = np.nan  # dropped
    clouds[2][9, 2] = np.inf  # dropped
    w = BagWriter(tmp_path / name)
    stamps = [T0 + 0.1 * k + 1e-9 * 37 for k in range(4)]
    for k, (t, c) in enumerate(zip(stamps, clouds)):
        w.cloud("/points", t, c, times=np.arange(len(c), dtype=np.uint32) * 1000 + 5000 * k)
    path = w.write()
    reader = open_log(path)
    assert isinstance(reader, RosbagReader) and reader.topic == "/points" and len(reader) == 4
    scans = list(reader)
    assert [s.index for s in scans] == [0, 1, 2, 3]
    for s, t, c in zip(scans, stamps, clouds):
        keep = np.all(np.isfinite(c), axis=1)
        np.testing.assert_array_equal(s.points, c[keep].astype(np.float64))  # float32 values exactly
        assert s.timestamp == pytest.approx(t, abs=5e-7)  # float64 ulp at 1.7e9 s is 2.4e-7
        assert not s.planar and s.odometry is None
        expected_t = np.arange(len(c))[keep] / (len(c) - 1.0)
        np.testing.assert_allclose(s.point_times, expected_t, atol=1e-12)
    assert scans[1].points.shape == (299, 3) and scans[2].points.shape == (299, 3)


def test_pointcloud2_big_endian_float64_padded_rows_without_time():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(2, 3, 3))  # height 2, width 3
    rec = np.zeros((2, 3), dtype=[("i", ">u2"), ("x", ">f8"), ("y", ">f8"), ("z", ">f8")])
    rec["x"], rec["y"], rec["z"] = pts[..., 0], pts[..., 1], pts[..., 2]
    step = rec.dtype.itemsize  # 26
    rows = [rec[r].tobytes() + b"\xee" * 6 for r in range(2)]  # 6 bytes of row padding
    F = SimpleNamespace
    fields = [F(name="intensity", offset=0, datatype=4, count=1)] + [
        F(name=n, offset=2 + 8 * k, datatype=8, count=1) for k, n in enumerate("xyz")]
    msg = F(fields=fields, point_step=step, width=3, height=2, row_step=3 * step + 6, is_bigendian=True,
            data=np.frombuffer(b"".join(rows), dtype=np.uint8))
    points, times = pointcloud2_to_points(msg, Path("x.bag"), "m")
    np.testing.assert_array_equal(points, pts.reshape(-1, 3))
    assert times is None
    msg.data = msg.data[:-20]
    with pytest.raises(InputError, match="data bytes"):
        pointcloud2_to_points(msg, Path("x.bag"), "m")


def test_laserscan_gives_planar_points_without_bad_beams(tmp_path):
    ranges = np.full(181, 2.0)
    ranges[3], ranges[4], ranges[5], ranges[6] = np.nan, np.inf, 0.05, 31.0  # all dropped
    ranges[90] = 5.0  # straight ahead
    w = BagWriter(tmp_path / "l.bag")
    w.laser("/scan", T0, ranges)
    w.laser("/scan", T0 + 0.1, np.full(181, 1.0))
    scans = list(open_log(w.write()))
    s = scans[0]
    assert s.planar and s.points.shape == (177, 3)
    np.testing.assert_array_equal(s.points[:, 2], 0.0)
    np.testing.assert_allclose(s.points[0], [0.0, -2.0, 0.0], atol=1e-6)  # first beam at -90 deg
    assert np.any(np.all(np.abs(s.points - [5.0, 0.0, 0.0]) < 1e-5, axis=1))
    np.testing.assert_allclose(np.linalg.norm(scans[1].points, axis=1), 1.0, rtol=1e-6)
    assert scans[1].timestamp == pytest.approx(T0 + 0.1, abs=5e-7)
    # per-beam times from time_increment
    msg = SimpleNamespace(ranges=np.ones(5, np.float32), angle_min=0.0, angle_increment=0.1, range_min=0.0,
                          range_max=10.0, time_increment=1e-4)
    _, times = laserscan_to_points(msg)
    np.testing.assert_allclose(times, [0, 0.25, 0.5, 0.75, 1.0])


# ---------------------------------------------------------------------------- odometry
def test_odometry_is_interpolated_at_scan_stamps(tmp_path):
    w = BagWriter(tmp_path / "o.mcap")
    w.odom("/odom", T0, 0.0, 0.0, 0.0)
    w.odom("/odom", T0 + 1.0, 2.0, 1.0, math.pi / 2)
    for t in (T0 - 0.5, T0, T0 + 0.25, T0 + 0.5, T0 + 1.5):
        w.laser("/scan", t, np.full(10, 1.0))
    reader = open_log(w.write())
    assert reader.odometry_topic == "/odom"
    odo = [s.odometry for s in reader]
    yaw = [math.atan2(T[1, 0], T[0, 0]) for T in odo]
    np.testing.assert_allclose([T[0, 3] for T in odo], [0.0, 0.0, 0.5, 1.0, 2.0], atol=1e-9)  # clamped ends
    np.testing.assert_allclose([T[1, 3] for T in odo], [0.0, 0.0, 0.25, 0.5, 1.0], atol=1e-9)
    np.testing.assert_allclose(yaw, [0.0, 0.0, math.pi / 8, math.pi / 4, math.pi / 2], atol=1e-9)
    for T in odo:
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert [s.odometry for s in RosbagReader(reader.path, odometry_topic="")] == [None] * 5


def test_slerp_takes_the_short_arc():
    q0 = np.array([0.0, 0.0, math.sin(0.1), math.cos(0.1)])
    q1 = -np.array([0.0, 0.0, math.sin(0.3), math.cos(0.3)])  # same rotation as +q1
    q = slerp(q0, q1, 0.5)
    assert abs(q[3]) == pytest.approx(math.cos(0.2)) and abs(q[2]) == pytest.approx(math.sin(0.2))


# ---------------------------------------------------------------------------- topics and errors
def test_several_scan_topics_need_a_choice(tmp_path):
    w = BagWriter(tmp_path / "two.bag")
    w.cloud("/velodyne_points", T0, random_clouds(1, 20)[0])
    w.laser("/scan", T0 + 0.05, np.full(30, 3.0))
    w.laser("/scan", T0 + 0.15, np.full(30, 3.0))
    path = w.write()
    with pytest.raises(InputError) as err:
        open_log(path)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(str(path))
    assert "/scan (LaserScan, 2 msgs)" in msg and "/velodyne_points (PointCloud2, 1 msgs)" in msg
    assert "pick one" in msg and "--topic" in msg
    scans = list(RosbagReader(path, topic="/scan"))
    assert len(scans) == 2 and all(s.planar for s in scans)
    assert len(list(RosbagReader(path, topic="/velodyne_points"))) == 1
    with pytest.raises(InputError, match=r"no topic '/nope'; scan topics: /scan"):
        RosbagReader(path, topic="/nope")
    # the same choice through open_log (what the CLI's --topic passes on)
    assert open_log(path, topic="/scan", odometry_topic=None).topic == "/scan"
    clf = tmp_path / "a.clf"
    clf.write_text("ODOM 0 0 0 0 0 0 99.0 host 0.0\n")
    with pytest.raises(InputError, match=r"a\.clf: option topic does not apply to carmen logs"):
        open_log(clf, topic="/scan")


def test_bag_without_scan_topics_and_cloud_without_xyz(tmp_path):
    w = BagWriter(tmp_path / "odom_only")
    w.odom("/odom", T0, 0.0, 0.0, 0.0)
    path = w.write()
    assert (path / "metadata.yaml").is_file()
    with pytest.raises(InputError, match=r"odom_only: no sensor_msgs PointCloud2 or LaserScan topic \(topics: /odom \(Odometry"):
        open_log(path)
    w = BagWriter(tmp_path / "noxyz.mcap")
    w.cloud("/points", T0, random_clouds(1, 10)[0])
    msg = w.msgs[0][3]
    msg.fields = [f for f in msg.fields if f.name != "y"]
    with pytest.raises(InputError, match=r"noxyz\.mcap: PointCloud2 /points message 0 has no y field \(fields: x, z\)"):
        list(open_log(w.write()))


def test_corrupt_files_are_one_line_input_errors(tmp_path):
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V2.0\n" + os.urandom(500))
    with pytest.raises(InputError, match=r"junk\.bag: ") as err:
        open_log(junk)
    assert "\n" not in str(err.value)
    mc = tmp_path / "junk.mcap"
    mc.write_bytes(b"not an mcap file at all")
    with pytest.raises(InputError, match=r"junk\.mcap: cannot read"):
        open_log(mc)


@pytest.mark.parametrize("error", [TypeError, KeyError, AssertionError])
@pytest.mark.parametrize("name", ["b.bag", "b.mcap"])
def test_bugs_in_the_decoding_are_not_reported_as_a_damaged_bag(tmp_path, monkeypatch, error, name):
    import submapslam.io.rosbag as rosbag

    w = BagWriter(tmp_path / name)
    w.cloud("/points", T0, random_clouds(1, 10)[0])
    path = w.write()

    def buggy(*_args, **_kwargs):
        raise error("a bug in submapslam")

    monkeypatch.setattr(rosbag, "pointcloud2_to_points", buggy)
    with pytest.raises(error, match="a bug in submapslam"):
        list(open_log(path))


@pytest.mark.parametrize("error", [TypeError, KeyError, AssertionError])
def test_the_same_errors_inside_rosbags_mean_a_damaged_bag(tmp_path, monkeypatch, error):
    # rosbags' readers hit bare asserts, ord() of empty reads and corrupt ids on damaged bytes
    from rosbags.highlevel import AnyReader

    w = BagWriter(tmp_path / "b.mcap")
    w.cloud("/points", T0, random_clouds(1, 10)[0])
    path = w.write()
    reader = open_log(path)

    def damaged(*_args, **_kwargs):
        raise error("corrupt record")

    monkeypatch.setattr(AnyReader, "deserialize", damaged)
    with pytest.raises(InputError) as err:
        list(reader)
    assert str(err.value) == f"{path}: bag breaks off or is damaged after 0 scans on /points (corrupt record)"


def test_truncated_mcap_yields_scans_before_the_damage(tmp_path, caplog):
    clouds = random_clouds(8, 40000)  # 640 kB messages: rosbags closes a 1 MiB chunk every 2 scans
    for c in clouds:
        c[:38000] = np.nan  # dropped by the reader: 2000 points per scan keep the run below fast
    w = BagWriter(tmp_path / "full.mcap")
    for k, c in enumerate(clouds):
        w.odom("/odom", T0 + 0.1 * k, 0.5 * k, 0.0, 0.0)
        w.cloud("/points", T0 + 0.1 * k, c)
    full = w.write()
    cut = tmp_path / "cut.mcap"
    data = full.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    with caplog.at_level("WARNING"):
        reader = open_log(cut)
    assert not [r for r in caplog.records if "summary/footer" in r.getMessage()]  # said once: by the error
    with pytest.raises(TypeError):
        len(reader)
    got = []
    with pytest.raises(InputError, match=r"cut\.mcap: bag breaks off or is damaged after \d+ scans on /points"):
        for s in reader:
            got.append(s)
    assert 2 <= len(got) < 8
    for k, s in enumerate(got):
        np.testing.assert_array_equal(s.points, clouds[k][38000:].astype(np.float64))
        assert s.odometry[0, 3] == pytest.approx(0.5 * k)
    # `run` keeps the scans read before the damage, writes their results and exits 1 with one line
    r = CliRunner().invoke(app, ["run", str(cut), "--out", str(tmp_path / "out"), "--no-loops"])
    assert r.exit_code == 1
    last = r.output.strip().splitlines()[-1]
    assert last.startswith("error:") and "cut.mcap" in last and f"the {len(got)} scans read before it" in last
    assert len(read_tum(tmp_path / "out" / "poses_tum.txt")) == len(got)
    # a ROS 1 bag loses its index at the end: no scans, an actionable message
    w = BagWriter(tmp_path / "full.bag")
    for k, c in enumerate(clouds[:3]):
        w.cloud("/points", T0 + 0.1 * k, c)
    data = w.write().read_bytes()
    (tmp_path / "cut.bag").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"cut\.bag: bag index is missing or damaged.*rosbag reindex"):
        open_log(tmp_path / "cut.bag")


# ---------------------------------------------------------------------------- converter + run
@pytest.fixture(scope="module")
def small_rectangle(tmp_path_factory):
    root = tmp_path_factory.mktemp("rosbag_rect")
    return generate("rectangle", root / "log", seed=0, laps=1, max_scans=100)


def test_converter_writes_laser_scans_and_odometry(small_rectangle, tmp_path):
    ref = list(open_log(small_rectangle))
    out = tmp_path / "rect_ros2"
    assert to_bag.main([str(small_rectangle), str(out), "--storage", "mcap"]) == 0
    assert (out / "metadata.yaml").is_file() and list(out.glob("*.mcap"))
    scans = list(open_log(out))
    assert len(scans) == len(ref) and scans[0].planar
    wheel = read_tum(small_rectangle / "odometry_tum.txt")
    for s, r, T in zip(scans, ref, wheel.poses):
        assert s.timestamp == pytest.approx(r.timestamp, abs=1e-6)
        assert s.points.shape == r.points.shape
        np.testing.assert_allclose(s.points, r.points, atol=1e-5)  # float32 ranges and angles
        np.testing.assert_allclose(s.odometry, T, atol=1e-12)
    assert to_bag.main([str(small_rectangle), str(out)]) == 1  # never overwrites


def test_run_on_a_bag_matches_the_cloud_folder_run(small_rectangle, tmp_path):
    runner = CliRunner()
    bag = to_bag.convert(small_rectangle, tmp_path / "rect.mcap", msg="cloud")
    laser_bag = to_bag.convert(small_rectangle, tmp_path / "rect.bag")
    outs = {}
    for name, log in (("folder", small_rectangle), ("cloud", bag), ("laser", laser_bag)):
        r = runner.invoke(app, ["run", str(log), "--out", str(tmp_path / name)])
        assert r.exit_code == 0, r.output
        outs[name] = read_tum(tmp_path / name / "poses_tum.txt")
    ref = outs["folder"]
    assert len(ref) == 100
    for name in ("cloud", "laser"):
        np.testing.assert_allclose(outs[name].timestamps, ref.timestamps, atol=1e-6)
    # PointCloud2 carries the folder's float32 points exactly (and z = 0 makes it planar)
    assert np.abs(outs["cloud"].poses[:, :3, 3] - ref.poses[:, :3, 3]).max() < 1e-3
    # rotations to 1e-4 (0.006 deg): on one CPU's numeric kernels the two runs part by 1.1e-5 in
    # the matrices' entries, as the positions' 1e-3 m above allows
    np.testing.assert_allclose(outs["cloud"].poses[:, :3, :3], ref.poses[:, :3, :3], atol=1e-4)
    # LaserScan re-derives points from float32 ranges/angles (~1e-6 m); scan matching turns that
    # into millimetres (4 mm measured; how much depends on the CPU's floating point), so this run
    # is held to 2 cm
    assert np.abs(outs["laser"].poses[:, :3, 3] - ref.poses[:, :3, 3]).max() < 2e-2


def test_run_cli_topic_options_pick_the_scan_and_odometry_topics(tmp_path):
    w = BagWriter(tmp_path / "two.bag")
    for k in range(3):
        w.laser("/scan", T0 + 0.1 * k, np.full(30, 3.0))
        w.cloud("/velodyne_points", T0 + 0.1 * k + 0.05, random_clouds(1, 50)[0])
        w.odom("/odom", T0 + 0.1 * k, 0.0, 0.0, 0.0)
    path = w.write()
    r = CliRunner().invoke(app, ["run", str(path), "--out", str(tmp_path / "none"), "--no-loops"])
    assert r.exit_code == 1 and "pick one" in r.output
    r = CliRunner().invoke(app, ["run", str(path), "--out", str(tmp_path / "scan"), "--no-loops",
                                 "--topic", "/scan", "--odometry-topic", "/odom"])
    assert r.exit_code == 0, r.output
    assert len(read_tum(tmp_path / "scan" / "poses_tum.txt")) == 3


# ---------------------------------------------------------------------------- sensor mounting (tf)
def pose(x=0.0, y=0.0, z=0.0, roll=0.0, pitch=0.0, yaw=0.0):
    """``T = Trans(x, y, z) Rz(yaw) Ry(pitch) Rx(roll)``."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    T = np.eye(4)
    T[:3, :3] = (np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
                 @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]]))
    T[:3, 3] = x, y, z
    return T


# a 2D laser 30 deg to the left of the base's x axis and mounted upside down (its scan plane stays
# horizontal), reached through an intermediate frame: base_link -> mount -> lidar
T_BASE_MOUNT = pose(0.3, -0.1, 0.25, yaw=math.radians(30))
T_MOUNT_LIDAR = pose(0.05, 0.02, 0.05, roll=math.pi)
T_BASE_LIDAR = T_BASE_MOUNT @ T_MOUNT_LIDAR


def to_sensor(points_base, T_base_sensor):
    """Planar base-frame points -> the points a level laser mounted at ``T_base_sensor`` measures
    (in its own frame, z = 0 exactly)."""
    p = points_base + [0.0, 0.0, T_base_sensor[2, 3]]  # the scan plane at the mounting height
    p = (p - T_base_sensor[:3, 3]) @ T_base_sensor[:3, :3]
    assert np.abs(p[:, 2]).max() < 1e-9
    p[:, 2] = 0.0
    return p


def mounted_bag(path, folder, n=None, tf_static=True):
    """The cloud-folder log ``folder`` (base frame == scan frame) as a bag whose PointCloud2 scans
    are in the frame of a laser mounted at ``T_BASE_LIDAR``, given by /tf_static as a chain."""
    w = BagWriter(path, frame="lidar")
    if tf_static:  # child before parent, one transform per message: the order must not matter
        w.tf("/tf_static", T0, "mount", "lidar", T_MOUNT_LIDAR)
        w.tf("/tf_static", T0, "base_link", "mount", T_BASE_MOUNT)
    scans = list(open_log(folder))[:n]
    for s in scans:
        t = T0 + s.timestamp
        w.odom_pose("/odom", t, s.odometry)
        w.cloud("/points", t, to_sensor(s.points, T_BASE_LIDAR).astype(np.float32))
    return w.write(), scans


def _read_mounted(reader, ref):
    """The scans of a bag whose laser sits at ``T_BASE_LIDAR`` (from /tf_static): the same
    base-frame points and odometry as ``ref``; returns the scans."""
    assert (reader.frame_id, reader.base_frame, reader.mounting_source) == ("lidar", "base_link", "/tf_static")
    np.testing.assert_allclose(reader.T_base_sensor, T_BASE_LIDAR, atol=1e-12)
    scans = list(reader)
    assert len(scans) == len(ref)
    for s, r in zip(scans, ref):
        np.testing.assert_allclose(s.points, r.points, atol=2e-5)
        np.testing.assert_allclose(s.odometry, r.odometry, atol=1e-12)
    return scans


@pytest.mark.parametrize("name", ["m.bag", "m.mcap"])
def test_tf_static_chain_gives_points_in_the_base_frame(small_rectangle, tmp_path, name):
    path, ref = mounted_bag(tmp_path / name, small_rectangle, n=10)
    scans = _read_mounted(open_log(path), ref)  # float32 sensor-frame points moved to the base
    assert all(s.planar for s in scans)
    # a tilted 3D lidar keeps its full transform (no projection)
    T = pose(0.1, 0.0, 1.2, pitch=math.radians(20), yaw=0.3)
    w = BagWriter(tmp_path / ("tilt" + path.suffix), frame="velodyne")
    w.tf("/tf_static", T0, "base_link", "velodyne", T)
    w.odom("/odom", T0, 0.0, 0.0, 0.0)
    cloud = random_clouds(1, 200)[0]
    w.cloud("/points", T0, cloud)
    (s,) = list(open_log(w.write()))
    assert not s.planar
    np.testing.assert_allclose(s.points, cloud.astype(np.float64) @ T[:3, :3].T + T[:3, 3], atol=1e-12)


def test_run_on_a_mounted_bag_matches_the_folder_run(small_rectangle, tmp_path):
    bag, _ = mounted_bag(tmp_path / "mounted.mcap", small_rectangle)
    runner = CliRunner()
    outs = {}
    for name, log in (("folder", small_rectangle), ("bag", bag)):
        r = runner.invoke(app, ["run", str(log), "--out", str(tmp_path / name), "--no-loops"])
        assert r.exit_code == 0, r.output
        outs[name] = read_tum(tmp_path / name / "poses_tum.txt")
    ref, got = outs["folder"], outs["bag"]
    assert len(got) == len(ref) == 100
    # the base's trajectory, not the lidar's (which would sit 0.3 m ahead and 30 deg off)
    assert np.abs(got.poses[:, :3, 3] - ref.poses[:, :3, 3]).max() < 2e-2
    yaw = lambda P: np.arctan2(P[:, 1, 0], P[:, 0, 0])  # noqa: E731
    assert np.abs(np.angle(np.exp(1j * (yaw(got.poses) - yaw(ref.poses))))).max() < 2e-3


def test_missing_chain_is_identity_with_one_warning_and_base_frame_option(tmp_path, caplog):
    w = BagWriter(tmp_path / "loose.mcap", frame="lidar")
    w.tf("/tf_static", T0, "base_link", "lidar", T_BASE_LIDAR)  # not connected to base_footprint
    cloud = random_clouds(1, 50)[0]
    for k in range(3):
        w.odom("/odom", T0 + 0.1 * k, 0.1 * k, 0.0, 0.0, child="base_footprint")
        w.cloud("/points", T0 + 0.1 * k, cloud)
    path = w.write()
    with caplog.at_level("WARNING", logger="submapslam.io.rosbag"):
        reader = open_log(path)
        scans = list(reader)
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "'base_footprint'" in warnings[0] and "'lidar'" in warnings[0]
    assert reader.mounting_source == "none" and reader.base_frame == "base_footprint"
    np.testing.assert_array_equal(reader.T_base_sensor, np.eye(4))
    for s in scans:
        np.testing.assert_array_equal(s.points, cloud.astype(np.float64))
    # naming the base frame finds the chain
    reader = open_log(path, base_frame="base_link")
    assert reader.mounting_source == "/tf_static"
    np.testing.assert_allclose(next(iter(reader)).points, cloud @ T_BASE_LIDAR[:3, :3].T + T_BASE_LIDAR[:3, 3],
                               atol=1e-5)


def test_explicit_T_base_sensor_overrides_tf_static(small_rectangle, tmp_path):
    path, ref = mounted_bag(tmp_path / "m.mcap", small_rectangle, n=3)
    T = pose(1.0, 2.0, 0.0, yaw=0.5)
    reader = open_log(path, T_base_sensor=T.tolist())
    assert reader.mounting_source == "option"
    s = next(iter(reader))
    sensor = to_sensor(ref[0].points, T_BASE_LIDAR)
    np.testing.assert_allclose(s.points, sensor @ T[:3, :3].T + T[:3, 3], atol=2e-5)
    np.testing.assert_array_equal(next(iter(RosbagReader(path, T_base_sensor=np.eye(4)))).points[:, :2],
                                  sensor[:, :2].astype(np.float32).astype(np.float64))
    with pytest.raises(InputError, match="T_base_sensor is not a rigid transform"):
        RosbagReader(path, T_base_sensor=2 * np.eye(4))
    with pytest.raises(InputError, match="4x4"):
        RosbagReader(path, T_base_sensor=np.eye(3))


def test_static_transforms_on_tf_when_the_bag_has_no_tf_static(tmp_path):
    cloud = random_clouds(1, 50)[0]
    for moving, expect in ((False, "/tf"), (True, "none")):
        w = BagWriter(tmp_path / f"tf{moving}.bag", frame="lidar")
        for k in range(4):
            t = T0 + 0.1 * k
            w.tf("/tf", t, "odom", "base_link", pose(0.2 * k))  # the robot moves: never used as mounting
            w.tf("/tf", t, "base_link", "mount", T_BASE_MOUNT @ pose(0.01 * k * moving))
            w.tf("/tf", t, "mount", "lidar", T_MOUNT_LIDAR)
            w.odom("/odom", t, 0.2 * k, 0.0, 0.0)
            w.cloud("/points", t, cloud)
        reader = open_log(w.write())
        assert reader.mounting_source == expect
        np.testing.assert_allclose(reader.T_base_sensor, np.eye(4) if moving else T_BASE_LIDAR, atol=1e-12)


def mounted_folder(folder, out, n):
    """``folder``'s first ``n`` scans as a cloud folder in the frame of a laser at ``T_BASE_LIDAR``
    (KITTI .bin scans, meta.yaml's T_base_sensor), with the same times and odometry."""
    import yaml

    (out / "scans").mkdir(parents=True)
    scans = list(open_log(folder))[:n]
    for s in scans:
        rec = np.zeros((len(s.points), 4), dtype=np.float32)
        rec[:, :3] = to_sensor(s.points, T_BASE_LIDAR)
        rec.tofile(out / "scans" / f"{s.index:06d}.bin")
    (out / "times.txt").write_text("".join(f"{s.timestamp:.9f}\n" for s in scans))
    shutil.copy(folder / "odometry_tum.txt", out / "odometry_tum.txt")
    meta = yaml.safe_load((folder / "meta.yaml").read_text())
    meta["T_base_sensor"] = T_BASE_LIDAR.tolist()
    (out / "meta.yaml").write_text(yaml.safe_dump(meta))
    return out, scans


def test_converter_round_trips_the_mounting(small_rectangle, tmp_path):
    folder, ref = mounted_folder(small_rectangle, tmp_path / "mounted", n=5)
    for name in ("m.bag", "m_ros2"):
        _read_mounted(open_log(to_bag.convert(folder, tmp_path / name, msg="cloud")), ref)  # back in the base frame


def test_cloud_folder_with_the_mounting_matches_the_bag(small_rectangle, tmp_path):
    folder, _ = mounted_folder(small_rectangle, tmp_path / "mounted", n=3)
    bag, _ = mounted_bag(tmp_path / "m.mcap", small_rectangle, n=3)
    from_folder, from_bag = list(open_log(folder)), list(open_log(bag))
    assert len(from_folder) == len(from_bag) == 3  # zip alone would stop at the shorter reader
    for a, b in zip(from_folder, from_bag, strict=True):
        np.testing.assert_allclose(a.points, b.points, atol=2e-5)


def test_run_cli_base_frame_reaches_the_reader(small_rectangle, tmp_path):
    folder, _ = mounted_folder(small_rectangle, tmp_path / "mounted", n=30)
    bag = to_bag.convert(folder, tmp_path / "m.mcap", msg="cloud", odom_topic="")
    assert open_log(bag).mounting_source == "/tf_static"  # no odometry: base_link by default
    assert open_log(bag, base_frame="lidar").mounting_source == "same frame"
    runs = {}
    for name, extra in (("base", []), ("sensor", ["--base-frame", "lidar"])):
        r = CliRunner().invoke(app, ["run", str(bag), "--out", str(tmp_path / name), "--no-loops", *extra])
        assert r.exit_code == 0, r.output
        runs[name] = read_tum(tmp_path / name / "poses_tum.txt").poses
    # the same motion seen from the base and from the rotated, offset sensor: the headings agree,
    # the travelled displacement does not (it is rotated by the mounting's yaw)
    d_base = runs["base"][-1, :2, 3] - runs["base"][0, :2, 3]
    d_sensor = runs["sensor"][-1, :2, 3] - runs["sensor"][0, :2, 3]
    assert np.linalg.norm(d_base) > 0.5
    assert np.linalg.norm(d_base - d_sensor) > 0.1 * np.linalg.norm(d_base)
