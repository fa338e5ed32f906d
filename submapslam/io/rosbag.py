"""ROS logs: ROS 1 bags (``.bag``) and ROS 2 bags (a folder with ``metadata.yaml`` and ``.db3``
or ``.mcap`` files, or a bare ``.mcap`` / ``.db3`` file), read with the ``rosbags`` package.

Messages read:
    ``sensor_msgs/msg/PointCloud2``  x, y, z (float32/float64) at their offsets, honouring
        ``point_step``, ``row_step`` and ``is_bigendian``; per-point times from a ``t``,
        ``time`` or ``timestamp`` field, normalised to [0, 1] over the sweep; NaN/inf points
        are dropped. A cloud whose points all have z = 0 (a projected 2D laser) is planar.
    ``sensor_msgs/msg/LaserScan``    ranges -> planar points (z = 0); NaN/inf beams and beams
        outside ``[range_min, range_max]`` are dropped; ``planar=True``.
    ``nav_msgs/msg/Odometry``        optional wheel odometry ``T_odom_base``, interpolated at
        each scan's header stamp (position linearly, rotation by slerp; clamped to the first /
        last odometry message outside their time span).
    ``tf2_msgs/msg/TFMessage``       the sensor's mounting (below).
The scan timestamp is the message's header stamp [s].

Sensor mounting: points are given in the robot's base frame, as the wheel odometry is, by
applying ``T_base_sensor`` (``p_base = T_base_sensor @ p_sensor``; the transform a cloud folder's
``meta.yaml`` documents). It is the chain of transforms from the base frame to the scan's
``header.frame_id`` (of the first scan) in ``/tf_static``, composed through intermediate frames
(``base_link -> mount -> lidar``); for bags recorded without ``/tf_static``, transforms on
``/tf`` that never change over its first messages are used. The base frame is ``base_frame=``,
else the odometry's ``child_frame_id``, else ``base_link``; ``T_base_sensor=`` (4x4) overrides
the lookup. Without a chain the points stay in the scan's frame (identity) with one warning.
Planar scans (LaserScan, or clouds with all z = 0) keep z = 0 in the base frame: the mounting
height is dropped (a scan plane tilted by the mounting is projected; warned once for LaserScan).

Topic choice: a bag with one PointCloud2/LaserScan topic uses it; with several, the reader
raises an :class:`InputError` listing them: pick one with ``RosbagReader(path, topic=...)``.
Odometry is used when the bag has exactly one Odometry topic, or the one given by
``odometry_topic`` (``odometry_topic=""`` ignores odometry).

Damaged files: a bag whose index is missing (ROS 1 bags or MCAP files cut off while
recording) cannot be opened by ``rosbags``; a bare MCAP file cut off midway is then read
linearly with rosbags' own MCAP record scanner, so the scans before the damage are yielded
and an :class:`InputError` is raised where the data breaks off. A ROS 1 bag without its index
ends with an error that says to run ``rosbag reindex`` on a copy.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry import inverse, pose_from_xyz_quat
from .registry import register_reader
from .scan import Scan, apply_mounting, check_transform

log = logging.getLogger(__name__)

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
LASER_TYPE = "sensor_msgs/msg/LaserScan"
ODOM_TYPE = "nav_msgs/msg/Odometry"
TF_TYPE = "tf2_msgs/msg/TFMessage"
TF_STATIC_TOPICS = ("/tf_static", "tf_static")
TF_TOPICS = ("/tf", "tf")
TF_SCAN_LIMIT = 2000  # /tf messages looked at for transforms that never change
DEFAULT_BASE_FRAME = "base_link"
SCAN_TYPES = (CLOUD_TYPE, LASER_TYPE)
BAG_SUFFIXES = (".bag", ".mcap", ".db3")
TIME_FIELDS = ("t", "time", "timestamp", "offset_time")  # offset_time: Livox drivers'
# sensor_msgs/PointField datatypes -> numpy type codes
_POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_FLOAT_TYPES = {7, 8}


def _short(name: str) -> str:
    return name.rsplit("/", 1)[-1]


def _first_line(exc: BaseException) -> str:
    text = " ".join(str(a) for a in exc.args) if exc.args else type(exc).__name__
    return (text.strip().splitlines() or [type(exc).__name__])[0][:200]


class _BagReadError(Exception):
    """rosbags could not read the file's bytes (damaged, cut off, not a bag). The message is
    the library's first line. Raised only by :class:`_AnyBag` / :class:`_PartialMcap`, so an
    exception in this module's own decoding is never mistaken for a damaged bag."""


def _rosbags_errors() -> tuple[type[BaseException], ...]:
    """Exceptions rosbags raises on bad input (imported lazily).

    Besides its own error types, its readers hit plain Python errors on damaged bytes: a bare
    ``assert`` on a record's time, ``ord()`` of an empty read (TypeError), a lookup of a corrupt
    connection id (KeyError), an undecodable name (UnicodeDecodeError), a huge corrupt length
    (OverflowError, or MemoryError when it asks for petabytes). They are caught only around
    calls into rosbags, never around this module's own code, and become :class:`_BagReadError`.
    """
    import sqlite3

    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as ReaderError1
    from rosbags.rosbag2 import ReaderError as ReaderError2
    from rosbags.serde import SerdeError
    from rosbags.typesys import TypesysError

    return (AnyReaderError, ReaderError1, ReaderError2, SerdeError, TypesysError, sqlite3.Error,
            OSError, EOFError, struct.error, ValueError, KeyError, IndexError, TypeError,
            AssertionError, OverflowError, MemoryError)


def stamp_ns(header) -> int:
    """Header stamp -> integer nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


# ---------------------------------------------------------------------------- message decoding
def pointcloud2_to_points(msg, where: Path, what: str) -> tuple[np.ndarray, np.ndarray | None]:
    """``sensor_msgs/PointCloud2`` -> ``(N, 3)`` float64 finite points, ``(N,)`` times in [0, 1] or None.

    ``what`` names the message in error messages (``"/points message 12"``).
    """
    fields = {f.name: f for f in msg.fields}
    missing = [c for c in "xyz" if c not in fields]
    if missing:
        have = ", ".join(fields) or "none"
        raise InputError(where, f"PointCloud2 {what} has no {'/'.join(missing)} field (fields: {have})")
    step = int(msg.point_step)
    width, height = int(msg.width), int(msg.height)
    n = width * height
    endian = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    time_name = next((t for t in TIME_FIELDS if t in fields), None)
    for name in ("x", "y", "z") + ((time_name,) if time_name else ()):
        f = fields[name]
        code = _POINTFIELD_TYPES.get(int(f.datatype))
        if code is None:
            raise InputError(where, f"PointCloud2 {what}: field {name!r} has unknown datatype {f.datatype}")
        if name in "xyz" and int(f.datatype) not in _FLOAT_TYPES:
            raise InputError(where, f"PointCloud2 {what}: field {name!r} is not float32/float64")
        if int(f.offset) + np.dtype(code).itemsize > step:
            raise InputError(where, f"PointCloud2 {what}: field {name!r} at offset {f.offset} "
                                    f"does not fit in point_step {step}")
        names.append(name)
        formats.append(endian + code)
        offsets.append(int(f.offset))
    if n == 0:
        return np.zeros((0, 3)), None
    data = np.asarray(msg.data, dtype=np.uint8)
    row_step = int(msg.row_step) or width * step
    if row_step < width * step or len(data) < (height - 1) * row_step + width * step:
        raise InputError(where, f"PointCloud2 {what}: {len(data)} data bytes for {height}x{width} "
                                f"points of {step} bytes (row_step {row_step})")
    if row_step != width * step:  # rows padded: keep each row's points
        rows = np.lib.stride_tricks.as_strided(data, shape=(height, width * step), strides=(row_step, 1))
        data = np.ascontiguousarray(rows).reshape(-1)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    rec = np.frombuffer(data[: n * step].tobytes(), dtype=dtype, count=n)
    points = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    keep = np.all(np.isfinite(points), axis=1)
    points = points[keep]
    times = None
    if time_name is not None and len(points):
        t = rec[time_name].astype(np.float64)[keep]
        if np.all(np.isfinite(t)):
            span = t.max() - t.min()
            times = (t - t.min()) / span if span > 0 else np.zeros_like(t)
    return points, times


def laserscan_to_points(msg) -> tuple[np.ndarray, np.ndarray | None]:
    """``sensor_msgs/LaserScan`` -> ``(N, 3)`` planar points (z = 0) and per-beam times or None.

    Beam ``i`` points at ``angle_min + i * angle_increment``; NaN/inf readings and readings
    outside ``[range_min, range_max]`` (or not positive) are dropped. Times are ``i / (n - 1)``
    when ``time_increment > 0``.
    """
    r = np.asarray(msg.ranges, dtype=np.float64)
    n = len(r)
    i = np.arange(n)
    angles = float(msg.angle_min) + i * float(msg.angle_increment)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(r) & (r > 0.0) & (r >= float(msg.range_min))
        if np.isfinite(msg.range_max) and msg.range_max > 0:
            valid &= r <= float(msg.range_max)
    rv = r[valid]
    points = np.zeros((len(rv), 3))
    points[:, 0] = rv * np.cos(angles[valid])
    points[:, 1] = rv * np.sin(angles[valid])
    times = None
    if float(msg.time_increment) > 0 and n > 1:
        times = i[valid] / (n - 1.0)
    return points, times


class OdometryTrack:
    """Odometry messages ``T_odom_base`` at integer-nanosecond stamps, interpolated on demand."""

    def __init__(self, stamps_ns: np.ndarray, xyz: np.ndarray, quats_xyzw: np.ndarray) -> None:
        order = np.argsort(stamps_ns, kind="stable")
        stamps_ns, xyz, quats = np.asarray(stamps_ns)[order], np.asarray(xyz)[order], np.asarray(quats_xyzw)[order]
        _, first = np.unique(stamps_ns, return_index=True)  # one pose per stamp
        self.stamps_ns = stamps_ns[first].astype(np.int64)
        self.xyz = xyz[first].astype(np.float64)
        q = quats[first].astype(np.float64)
        self.quats = q / np.linalg.norm(q, axis=1, keepdims=True)

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def at(self, t_ns: int) -> np.ndarray:
        """``(4, 4)`` pose at ``t_ns`` (clamped to the first/last message outside the span)."""
        s = self.stamps_ns
        if t_ns <= s[0]:
            return pose_from_xyz_quat(self.xyz[0], self.quats[0])
        if t_ns >= s[-1]:
            return pose_from_xyz_quat(self.xyz[-1], self.quats[-1])
        k = int(np.searchsorted(s, t_ns, side="right")) - 1
        if s[k] == t_ns:
            return pose_from_xyz_quat(self.xyz[k], self.quats[k])
        alpha = (t_ns - s[k]) / float(s[k + 1] - s[k])
        xyz = (1.0 - alpha) * self.xyz[k] + alpha * self.xyz[k + 1]
        return pose_from_xyz_quat(xyz, slerp(self.quats[k], self.quats[k + 1], alpha))


def slerp(q0: np.ndarray, q1: np.ndarray, alpha: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions ``(x, y, z, w)``, shortest arc."""
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + alpha * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    return (np.sin((1 - alpha) * theta) * q0 + np.sin(alpha * theta) * q1) / np.sin(theta)


# ---------------------------------------------------------------------------- frames (tf)
def frame_name(frame: str) -> str:
    """tf frame id without the leading ``/`` of old ROS 1 bags."""
    return str(frame).strip().lstrip("/")


def transform_to_matrix(transform) -> np.ndarray:
    """``geometry_msgs/Transform`` -> ``(4, 4)`` float64 ``T_parent_child``."""
    t, q = transform.translation, transform.rotation
    return pose_from_xyz_quat((t.x, t.y, t.z), (q.x, q.y, q.z, q.w))


class FrameTree:
    """tf frames: each child frame has one parent and ``T_parent_child``; looks up chains."""

    def __init__(self) -> None:
        self.edges: dict[str, tuple[str, np.ndarray]] = {}  # child -> (parent, T_parent_child)

    def add(self, parent: str, child: str, T_parent_child: np.ndarray) -> None:
        parent, child = frame_name(parent), frame_name(child)
        if parent and child and parent != child:
            self.edges[child] = (parent, np.asarray(T_parent_child, dtype=np.float64))

    def _to_root(self, frame: str) -> tuple[str, np.ndarray]:
        """``(root, T_root_frame)`` following parents up from ``frame``."""
        T = np.eye(4)
        seen = {frame}
        while frame in self.edges:
            parent, T_pc = self.edges[frame]
            if parent in seen:  # a loop in the tree: stop there
                break
            T = T_pc @ T
            frame = parent
            seen.add(frame)
        return frame, T

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        """``T_target_source`` (maps ``source`` coordinates into ``target``), or None without a chain."""
        target, source = frame_name(target), frame_name(source)
        root_t, T_rt = self._to_root(target)
        root_s, T_rs = self._to_root(source)
        if root_t != root_s:
            return None
        return inverse(T_rt) @ T_rs


# ---------------------------------------------------------------------------- bag access
def _decoded(records: Iterator, deserialize, truncated: tuple[type[BaseException], ...] = ()
             ) -> Iterator[tuple[str, str, object]]:
    """``(topic, msgtype, message)`` from rosbags' ``(connection, time, raw)`` records.

    Only rosbags' reading and decoding is guarded (its errors become :class:`_BagReadError`),
    not the caller's loop body: a bug there surfaces as itself.
    """
    errors = _rosbags_errors()
    while True:
        try:
            item = next(records, None)
            if item is None:
                return
            conn, _t, raw = item
            msg = deserialize(raw, conn.msgtype)
        except truncated as exc:
            raise _BagReadError(f"truncated record ({exc})") from exc
        except errors as exc:
            raise _BagReadError(_first_line(exc)) from exc
        yield conn.topic, conn.msgtype, msg


class _AnyBag:
    """A bag opened with ``rosbags.highlevel.AnyReader``."""

    partial = False

    def __init__(self, path: Path) -> None:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.path = path
        default = get_typestore(Stores.ROS1_NOETIC if path.suffix == ".bag" else Stores.ROS2_HUMBLE)
        try:
            self.reader = AnyReader([path], default_typestore=default)
            self.reader.open()
        except _rosbags_errors() as exc:
            raise _BagReadError(_first_line(exc)) from exc

    def close(self) -> None:
        self.reader.close()

    def topics(self) -> dict[str, tuple[str, int | None]]:
        return {name: (info.msgtype or "", info.msgcount) for name, info in self.reader.topics.items()}

    def messages(self, topics: set[str]) -> Iterator[tuple[str, str, object]]:
        conns = [c for c in self.reader.connections if c.topic in topics]
        return _decoded(self.reader.messages(connections=conns), self.reader.deserialize)


class _PartialMcap:
    """A bare MCAP file without its summary/footer (cut off while recording), read linearly.

    Uses rosbags' MCAP storage reader's own record scanner (``meta_scan``/``messages_scan``)
    from the data section to the end of the file; the scan raises ``ReaderError`` where the
    data breaks off.
    """

    partial = True

    def __init__(self, path: Path) -> None:
        from rosbags.rosbag2 import ReaderError
        from rosbags.rosbag2.storage_mcap import McapReader, skip_sized
        from rosbags.typesys import Stores, get_typestore

        self.path = path
        self.typestore = get_typestore(Stores.ROS2_HUMBLE)
        self.storage = McapReader(path)
        bio = self.storage.bio = path.open("rb")
        if bio.read(8) != b"\x89MCAP0\r\n" or bio.read(1) != b"\x01":
            bio.close()
            raise ReaderError("not an MCAP file")
        skip_sized(bio)  # the header record
        self.storage.data_start = bio.tell()
        self.storage.data_end = path.stat().st_size
        try:  # collect schemas and channels up to the damage
            self.storage.meta_scan()
        except (ReaderError, struct.error, TypeError, ValueError) as exc:
            log.debug("%s: metadata scan stopped: %s", path, exc)
        self.connections = list(self.storage.connections)

    def close(self) -> None:
        self.storage.bio.close()

    def topics(self) -> dict[str, tuple[str, int | None]]:
        return {c.topic: (c.msgtype, None) for c in self.connections}

    def messages(self, topics: set[str]) -> Iterator[tuple[str, str, object]]:
        conns = [c for c in self.connections if c.topic in topics]
        # a record cut inside its fixed-size header raises struct.error or TypeError
        return _decoded(self.storage.messages_scan(conns), self.typestore.deserialize_cdr,
                        truncated=(struct.error, TypeError))


def _printable(message: str, limit: int = 160) -> str:
    """``message`` for one error line: a decoder's quoted raw bytes (``b'\\x80...'``) are left out,
    unprintable characters become "?", and the rest is cut at ``limit`` characters."""
    for quote in ("b'", 'b"'):
        at = message.find(quote)
        if at >= 0 and (at == 0 or not message[at - 1].isalnum()):
            message = message[:at] + "(undecodable bytes)"
    message = "".join(ch if ch.isprintable() else "?" for ch in message)
    return message if len(message) <= limit else message[:limit] + "..."


def _open_bag(path: Path) -> _AnyBag | _PartialMcap:
    """Open ``path``; a bare MCAP file without its summary falls back to a linear scan."""
    try:
        return _AnyBag(path)
    except _BagReadError as exc:
        problem = _printable(str(exc).rstrip("."))
        mcap = _single_mcap(path)
        if mcap is not None and ("end magic" in problem or "footer" in problem.lower()):
            log.debug("%s: %s; reading the MCAP data linearly up to the damage", path, problem)
            try:
                return _PartialMcap(mcap)
            except (*_rosbags_errors(), ImportError, AttributeError):  # rosbags internals moved: no recovery
                pass
            raise InputError(path, f"cannot read the MCAP file ({problem})") from None
        if "index" in problem.lower() or "Header could not be read" in problem:
            raise InputError(path, f"bag index is missing or damaged, probably cut off while recording "
                                   f"({problem}); run 'rosbag reindex' on a copy") from None
        raise InputError(path, f"cannot read bag ({problem})") from None


def _single_mcap(path: Path) -> Path | None:
    if path.is_file():
        return path if path.suffix == ".mcap" else None
    files = sorted(path.glob("*.mcap"))
    return files[0] if len(files) == 1 else None


def _describe(topics: dict[str, tuple[str, int | None]], names: list[str]) -> str:
    parts = []
    for name in names:
        msgtype, count = topics[name]
        parts.append(f"{name} ({_short(msgtype)}" + (f", {count} msgs)" if count is not None else ")"))
    return ", ".join(parts)


# ---------------------------------------------------------------------------- the reader
class RosbagReader:
    """Iterate the scans of a ROS 1 / ROS 2 bag as :class:`Scan` objects (see module docstring).

    Args:
        path: ``.bag`` file, ROS 2 bag folder, or bare ``.mcap`` / ``.db3`` file.
        topic: the PointCloud2/LaserScan topic to read (needed when the bag has several).
        odometry_topic: the nav_msgs/Odometry topic; ``None`` uses the only one if there is
            exactly one, ``""`` ignores odometry.
        base_frame: the robot frame the points are given in; default the odometry's
            ``child_frame_id``, else ``base_link``.
        T_base_sensor: ``(4, 4)`` sensor mounting, overriding the bag's ``/tf_static``.

    After construction ``frame_id`` (the scans' frame), ``base_frame``, ``T_base_sensor`` and
    ``mounting_source`` (``"option"``, ``"/tf_static"``, ``"/tf"``, ``"same frame"`` or ``"none"``)
    say how the points were placed.
    """

    name = "rosbag"

    def __init__(self, path: Path, topic: str | None = None, odometry_topic: str | None = None,
                 base_frame: str | None = None, T_base_sensor=None) -> None:
        self.path = Path(path)
        self.odometry_frame: str | None = None
        bag = _open_bag(self.path)
        try:
            topics = bag.topics()
            self.partial = bag.partial
            if self.partial and not topics:
                raise InputError(self.path, "MCAP file is cut off before its first complete chunk: "
                                            "no topics could be read")
            self.topic = self._choose_scan_topic(topics, topic)
            self.msgtype = topics[self.topic][0]
            self.count = topics[self.topic][1]
            self.odometry_topic = self._choose_odometry_topic(topics, odometry_topic)
            self.tf_static_topics = sorted(t for t in TF_STATIC_TOPICS if topics.get(t, ("",))[0] == TF_TYPE)
            self.tf_topics = sorted(t for t in TF_TOPICS if topics.get(t, ("",))[0] == TF_TYPE)
        finally:
            bag.close()
        if self.partial:
            # info, not a warning: the reading ends in an InputError saying the same, printed once
            log.info("%s: MCAP file without summary/footer (cut off while recording?): "
                     "reading its data linearly up to the damage", self.path)
        self.odometry = self._read_odometry() if self.odometry_topic else None
        self.frame_id = self._first_scan_frame()
        self.base_frame = frame_name(base_frame or self.odometry_frame or DEFAULT_BASE_FRAME)
        if T_base_sensor is not None:
            self.T_base_sensor, self.mounting_source = check_transform(T_base_sensor, self.path), "option"
        else:
            self.T_base_sensor, self.mounting_source = self._find_mounting(explicit_base=base_frame is not None)
        self._identity = bool(np.array_equal(self.T_base_sensor, np.eye(4)))
        R = self.T_base_sensor[:3, :3]
        if not self._identity and abs(R[2, 2]) < 1.0 - 1e-6 and self.msgtype == LASER_TYPE:
            log.warning("%s: the mounting tilts the laser's scan plane by %.1f deg against %s; its points are "
                        "projected onto the base's xy plane", self.path,
                        math.degrees(math.acos(min(1.0, abs(R[2, 2])))), self.base_frame)

    def _first_scan_frame(self) -> str:
        """``header.frame_id`` of the first scan message ('' when it cannot be read here)."""
        bag = _open_bag(self.path)
        try:
            for _topic, _typ, msg in bag.messages({self.topic}):
                return frame_name(msg.header.frame_id)
        except _BagReadError:
            pass  # reported with its scan index when the scans are read
        finally:
            bag.close()
        return ""

    def _read_tf(self, tree: FrameTree, topics: list[str], static: bool) -> None:
        """Add the transforms on ``topics`` to ``tree``: every one from ``/tf_static``, and from
        ``/tf`` those that never change over its first :data:`TF_SCAN_LIMIT` messages."""
        first: dict[tuple[str, str], np.ndarray] = {}
        moving: set[tuple[str, str]] = set()
        bag = _open_bag(self.path)
        try:
            for n, (_topic, _typ, msg) in enumerate(bag.messages(set(topics))):
                if not static and n >= TF_SCAN_LIMIT:
                    break
                for tr in msg.transforms:
                    key = (frame_name(tr.header.frame_id), frame_name(tr.child_frame_id))
                    T = transform_to_matrix(tr.transform)
                    if static:
                        tree.add(*key, T)
                    elif key not in first:
                        first[key] = T
                    elif not np.allclose(T, first[key], atol=1e-9):
                        moving.add(key)
        except _BagReadError as exc:
            log.debug("%s: reading %s stopped: %s", self.path, "/".join(topics), exc)
        finally:
            bag.close()
        for (parent, child), T in first.items():
            if (parent, child) not in moving and frame_name(child) not in tree.edges:
                tree.add(parent, child, T)

    def _find_mounting(self, explicit_base: bool) -> tuple[np.ndarray, str]:
        """``(T_base_sensor, source)`` from the bag's tf, identity (with a warning) without a chain."""
        base, sensor = self.base_frame, self.frame_id
        if sensor == base:
            return np.eye(4), "same frame"
        tree = FrameTree()
        for topics, static, source in ((self.tf_static_topics, True, "/tf_static"), (self.tf_topics, False, "/tf")):
            if not topics or not sensor:
                continue
            self._read_tf(tree, topics, static)
            T = tree.lookup(base, sensor)
            if T is not None:
                log.debug("%s: T_base_sensor from %s (%s -> %s)", self.path, source, base, sensor)
                return T, source
        # a bag with nothing but scans has no base to disagree with: no warning then
        noisy = explicit_base or self.odometry is not None or self.tf_static_topics or self.tf_topics
        (log.warning if noisy else log.debug)(
            "%s: no transform from base frame %r to scan frame %r in /tf_static or /tf; points stay in "
            "the scan frame (T_base_sensor = identity)", self.path, base, sensor)
        return np.eye(4), "none"

    def __len__(self) -> int:
        if self.count is None:
            raise TypeError("scan count unknown for a damaged MCAP file")
        return self.count

    def _choose_scan_topic(self, topics: dict[str, tuple[str, int | None]], topic: str | None) -> str:
        scan_topics = sorted(t for t, (typ, _) in topics.items() if typ in SCAN_TYPES)
        if topic is not None:
            if topic not in topics:
                raise InputError(self.path, f"no topic {topic!r}; scan topics: {_describe(topics, scan_topics) or 'none'}")
            if topics[topic][0] not in SCAN_TYPES:
                raise InputError(self.path, f"topic {topic!r} is {topics[topic][0]}, not PointCloud2/LaserScan; "
                                            f"scan topics: {_describe(topics, scan_topics) or 'none'}")
            return topic
        if not scan_topics:
            others = _describe(topics, sorted(topics)) or "none"
            raise InputError(self.path, f"no sensor_msgs PointCloud2 or LaserScan topic (topics: {others})")
        if len(scan_topics) > 1:
            raise InputError(self.path, f"several scan topics: {_describe(topics, scan_topics)}; "
                                        "pick one with --topic (RosbagReader(path, topic=...))")
        return scan_topics[0]

    def _choose_odometry_topic(self, topics: dict[str, tuple[str, int | None]], topic: str | None) -> str | None:
        if topic == "":
            return None
        odom_topics = sorted(t for t, (typ, _) in topics.items() if typ == ODOM_TYPE)
        if topic is not None:
            if topics.get(topic, ("", None))[0] != ODOM_TYPE:
                raise InputError(self.path, f"no nav_msgs/Odometry topic {topic!r}; odometry topics: "
                                            f"{', '.join(odom_topics) or 'none'}")
            return topic
        if len(odom_topics) > 1:
            raise InputError(self.path, f"several odometry topics: {', '.join(odom_topics)}; pick one with "
                                        "--odometry-topic (RosbagReader(path, odometry_topic=...)), '' for none")
        return odom_topics[0] if odom_topics else None

    def _read_odometry(self) -> OdometryTrack | None:
        stamps, xyz, quats = [], [], []
        bag = _open_bag(self.path)
        try:
            for _topic, _typ, msg in bag.messages({self.odometry_topic}):
                if self.odometry_frame is None:
                    self.odometry_frame = frame_name(msg.child_frame_id) or None
                p, q = msg.pose.pose.position, msg.pose.pose.orientation
                stamps.append(stamp_ns(msg.header))
                xyz.append((p.x, p.y, p.z))
                quats.append((q.x, q.y, q.z, q.w))
        except _BagReadError as exc:
            if not bag.partial:
                raise InputError(self.path, f"cannot read odometry on {self.odometry_topic} ({exc})") from None
            # damaged MCAP: the scans stop at the same place; keep the odometry read so far
        finally:
            bag.close()
        if not stamps:
            return None
        track = OdometryTrack(np.array(stamps, dtype=np.int64), np.array(xyz), np.array(quats))
        if not np.all(np.isfinite(track.xyz)) or not np.all(np.isfinite(track.quats)):
            raise InputError(self.path, f"odometry on {self.odometry_topic} has NaN/inf poses")
        return track

    def __iter__(self) -> Iterator[Scan]:
        bag = _open_bag(self.path)
        index = 0
        laser = self.msgtype == LASER_TYPE
        try:
            for _topic, _typ, msg in bag.messages({self.topic}):
                what = f"{self.topic} message {index}"
                if laser:
                    points, times = laserscan_to_points(msg)
                    planar = True
                else:
                    points, times = pointcloud2_to_points(msg, self.path, what)
                    planar = len(points) > 0 and not np.any(points[:, 2])  # a projected 2D laser
                if not self._identity:
                    points = apply_mounting(points, self.T_base_sensor, planar)
                t_ns = stamp_ns(msg.header)
                yield Scan(
                    index=index,
                    timestamp=int(msg.header.stamp.sec) + int(msg.header.stamp.nanosec) * 1e-9,
                    points=points,
                    point_times=times,
                    odometry=None if self.odometry is None else self.odometry.at(t_ns),
                    planar=planar,
                    source=f"{self.path.name}:{self.topic}:{index}",
                )
                index += 1
        except _BagReadError as exc:
            raise InputError(self.path, f"bag breaks off or is damaged after {index} scans on "
                                        f"{self.topic} ({exc})") from None
        finally:
            bag.close()
        if bag.partial:
            raise InputError(self.path, f"MCAP file has no summary/footer (cut off while recording?); "
                                        f"read {index} scans on {self.topic} before its end")
        if index == 0:
            raise InputError(self.path, f"no messages on {self.topic}")


def _sniff(path: Path) -> bool:
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix.lower() in BAG_SUFFIXES


register_reader("rosbag", _sniff, RosbagReader)
