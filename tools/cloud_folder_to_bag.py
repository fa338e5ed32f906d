"""Write a cloud-folder log (e.g. ``submapslam synth rectangle --out DIR``) as a ROS bag.

Usage: python tools/cloud_folder_to_bag.py SRC_FOLDER OUT [--msg laser|cloud] [--topic T]
                                           [--odom-topic T] [--storage sqlite3|mcap]

OUT ending in ``.bag`` is a ROS 1 bag, ``.mcap`` a bare ROS 2 MCAP file, anything else a ROS 2
bag folder (``metadata.yaml`` + ``.db3``, or ``.mcap`` with ``--storage mcap``). Each scan becomes
a ``sensor_msgs/LaserScan`` (planar logs, the default for them: beams laid out as in the log's
``meta.yaml`` sensor, missing beams +inf) or a ``sensor_msgs/PointCloud2`` (float32 x y z and a
float32 ``time`` field in seconds from the sweep start) stamped with the scan's timestamp; the
log's ``odometry_tum.txt`` becomes ``nav_msgs/Odometry`` on ``--odom-topic`` at the same stamps
(``child_frame_id`` ``base_link``). The sensor mounting, ``meta.yaml``'s ``T_base_sensor``
(identity when absent), becomes one ``tf2_msgs/TFMessage`` on ``/tf_static`` from ``base_link`` to
the scans' frame (``laser`` or ``lidar``), so reading the bag gives the points in the base frame.
Written with the ``rosbags`` writers.
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def beam_layout(meta: dict) -> tuple[float, float, int, float]:
    """``(angle_min, angle_increment, beams, max_range)`` of a planar log's laser (meta.yaml ``sensor``).

    Follows ``datasets_synth.sensors.Laser2D``: ``beams`` over ``fov_deg`` from ``-fov/2``
    (a full circle steps ``2 pi / beams`` from ``-pi``). Defaults: 361 beams over 180 degrees.
    """
    sensor = meta.get("sensor") or {}
    beams = int(sensor.get("beams", 361))
    fov = float(sensor.get("fov_deg", 180.0))
    max_range = float(sensor.get("max_range", 30.0))
    if fov >= 360.0:
        return -math.pi, 2 * math.pi / beams, beams, max_range
    return -math.radians(fov) / 2, math.radians(fov) / (beams - 1), beams, max_range


def points_to_ranges(points: np.ndarray, angle_min: float, inc: float, beams: int) -> np.ndarray:
    """Planar points -> float32 ranges per beam (+inf where no point); one point per beam."""
    ang = np.arctan2(points[:, 1], points[:, 0])
    idx = np.rint((ang - angle_min) / inc).astype(int)
    if beams * inc >= 2 * math.pi - 1e-9:
        idx %= beams
    if np.any((idx < 0) | (idx >= beams)):
        raise ValueError("a point lies outside the laser's field of view")
    if len(np.unique(idx)) != len(idx):
        raise ValueError("two points fall on the same beam: not a single-echo planar scan")
    ranges = np.full(beams, np.inf, dtype=np.float32)
    ranges[idx] = np.hypot(points[:, 0], points[:, 1])
    return ranges


class _Messages:
    """Builds ROS messages with one rosbags typestore (ROS 1 Noetic or ROS 2 Humble)."""

    LASER_FRAME = "laser"
    CLOUD_FRAME = "lidar"

    def __init__(self, ros1: bool) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.ros1 = ros1
        self.store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        if "tf2_msgs/msg/TFMessage" not in self.store.types:  # not in rosbags' Noetic store
            from rosbags.typesys import get_types_from_msg

            self.store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                   "tf2_msgs/msg/TFMessage"))
        self.T = self.store.types
        self.seq = 0

    def header(self, t: float, frame: str):
        sec = math.floor(t)
        nsec = int(round((t - sec) * 1e9))
        if nsec >= 1_000_000_000:
            sec, nsec = sec + 1, nsec - 1_000_000_000
        stamp = self.T["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=nsec)
        Header = self.T["std_msgs/msg/Header"]
        if self.ros1:
            self.seq += 1
            return Header(seq=self.seq, stamp=stamp, frame_id=frame)
        return Header(stamp=stamp, frame_id=frame)

    def serialize(self, msg, msgtype: str) -> bytes:
        if self.ros1:
            return self.store.serialize_ros1(msg, msgtype)
        return self.store.serialize_cdr(msg, msgtype)

    def laser(self, t: float, ranges: np.ndarray, angle_min: float, inc: float, max_range: float):
        finite = ranges[np.isfinite(ranges)]
        rmax = np.float32(max(max_range, float(finite.max()) if len(finite) else 0.0))
        return self.T["sensor_msgs/msg/LaserScan"](
            header=self.header(t, self.LASER_FRAME), angle_min=angle_min, angle_max=angle_min + inc * (len(ranges) - 1),
            angle_increment=inc, time_increment=0.0, scan_time=0.0, range_min=0.0, range_max=float(rmax),
            ranges=ranges, intensities=np.zeros(0, dtype=np.float32))

    def cloud(self, t: float, points: np.ndarray, times: np.ndarray | None, sweep_s: float):
        PointField = self.T["sensor_msgs/msg/PointField"]
        rec = np.zeros(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("time", "<f4")])
        rec["x"], rec["y"], rec["z"] = points[:, 0], points[:, 1], points[:, 2]
        rec["time"] = 0.0 if times is None else times * sweep_s
        fields = [PointField(name=n, offset=4 * k, datatype=7, count=1) for k, n in enumerate(("x", "y", "z", "time"))]
        return self.T["sensor_msgs/msg/PointCloud2"](
            header=self.header(t, self.CLOUD_FRAME), height=1, width=len(rec), fields=fields, is_bigendian=False,
            point_step=16, row_step=16 * len(rec), data=np.frombuffer(rec.tobytes(), dtype=np.uint8),
            is_dense=True)

    def _xyz_quat(self, pose: np.ndarray) -> tuple[tuple[float, float, float], object]:
        """Translation ``(x, y, z)`` and a ``geometry_msgs/Quaternion`` of a ``(4, 4)`` pose."""
        from submapslam.geometry import matrix_to_quat

        q = matrix_to_quat(pose[:3, :3])
        xyz = tuple(float(v) for v in pose[:3, 3])
        return xyz, self.T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])

    def tf(self, t: float, parent: str, child: str, T_parent_child: np.ndarray):
        """``tf2_msgs/TFMessage`` with one transform ``T_parent_child``."""
        T = self.T
        (x, y, z), rotation = self._xyz_quat(T_parent_child)
        transform = T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z), rotation=rotation)
        stamped = T["geometry_msgs/msg/TransformStamped"](
            header=self.header(t, parent), child_frame_id=child, transform=transform)
        return T["tf2_msgs/msg/TFMessage"](transforms=[stamped])

    def odometry(self, t: float, T_odom_base: np.ndarray):
        T = self.T
        (x, y, z), orientation = self._xyz_quat(T_odom_base)
        pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                                           orientation=orientation)
        zero3 = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        return T["nav_msgs/msg/Odometry"](
            header=self.header(t, "odom"), child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=zero3, angular=zero3), covariance=np.zeros(36)))


def convert(src: str | Path, out: str | Path, *, msg: str | None = None, topic: str | None = None,
            odom_topic: str = "/odom", storage: str = "sqlite3", max_scans: int | None = None) -> Path:
    """Write the cloud-folder log ``src`` as a bag at ``out`` (see module docstring); returns ``out``."""
    import itertools

    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    from submapslam.io.cloud_folder import CloudFolderReader

    reader = CloudFolderReader(Path(src), sensor_frame=True)  # the bag carries the mounting in /tf_static
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out} exists already")
    msg = msg or ("laser" if reader.planar else "cloud")
    if msg not in ("laser", "cloud"):
        raise ValueError(f"--msg must be laser or cloud, not {msg!r}")
    if msg == "laser" and not reader.planar:
        raise ValueError(f"{src} is not a planar log: use --msg cloud")
    topic = topic or ("/scan" if msg == "laser" else "/points")
    ros1 = out.suffix == ".bag"
    bare_mcap = out.suffix == ".mcap"
    m = _Messages(ros1)
    scan_type = "sensor_msgs/msg/LaserScan" if msg == "laser" else "sensor_msgs/msg/PointCloud2"
    odom_type = "nav_msgs/msg/Odometry"
    layout = beam_layout(reader.meta) if msg == "laser" else None
    rate = float(reader.meta.get("rate_hz", 10.0) or 10.0)
    T_base_sensor = reader.T_base_sensor
    tf_type = "tf2_msgs/msg/TFMessage"

    tmp = None
    if ros1:
        writer = Writer1(out)
    else:
        target = out
        if bare_mcap:
            tmp = Path(tempfile.mkdtemp(prefix=".bagtmp", dir=out.parent))
            target = tmp / out.stem
        plugin = StoragePlugin.MCAP if (bare_mcap or storage == "mcap") else StoragePlugin.SQLITE3
        writer = Writer2(target, version=9, storage_plugin=plugin)
    try:
        with writer:
            scan_conn = writer.add_connection(topic, scan_type, typestore=m.store)
            odom_conn = (writer.add_connection(odom_topic, odom_type, typestore=m.store)
                         if reader.odometry is not None and odom_topic else None)
            tf_conn = writer.add_connection("/tf_static", tf_type, typestore=m.store)
            for scan in itertools.islice(reader, max_scans):
                t_ns = int(round(scan.timestamp * 1e9))
                if tf_conn is not None:  # once, before the first scan
                    frame = m.LASER_FRAME if msg == "laser" else m.CLOUD_FRAME
                    tf = m.tf(scan.timestamp, "base_link", frame, T_base_sensor)
                    writer.write(tf_conn, t_ns, m.serialize(tf, tf_type))
                    tf_conn = None
                if odom_conn is not None:
                    writer.write(odom_conn, t_ns, m.serialize(m.odometry(scan.timestamp, scan.odometry), odom_type))
                if layout is not None:
                    angle_min, inc, beams, max_range = layout
                    ranges = points_to_ranges(scan.points, angle_min, inc, beams)
                    message = m.laser(scan.timestamp, ranges, angle_min, inc, max_range)
                else:
                    message = m.cloud(scan.timestamp, scan.points, scan.point_times, 1.0 / rate)
                writer.write(scan_conn, t_ns, m.serialize(message, scan_type))
        if bare_mcap:
            shutil.move(str(target / f"{target.name}.mcap"), out)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", type=Path, help="cloud-folder log (synth output)")
    ap.add_argument("out", type=Path, help="OUT.bag (ROS 1), OUT.mcap (ROS 2 MCAP file) or a ROS 2 bag folder")
    ap.add_argument("--msg", choices=("laser", "cloud"), help="LaserScan or PointCloud2 (default: laser if planar)")
    ap.add_argument("--topic", help="scan topic (default /scan or /points)")
    ap.add_argument("--odom-topic", default="/odom", help="odometry topic ('' for none)")
    ap.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3", help="ROS 2 folder storage")
    ap.add_argument("--max-scans", type=int, help="write only the first N scans")
    args = ap.parse_args(argv)
    from submapslam.errors import SubmapSlamError

    try:
        out = convert(args.src, args.out, msg=args.msg, topic=args.topic, odom_topic=args.odom_topic,
                      storage=args.storage, max_scans=args.max_scans)
    except (SubmapSlamError, ValueError, FileExistsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
