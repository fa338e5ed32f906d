"""CARMEN laser logs (``.clf`` / ``.log``, plain, ``.gz`` or ``.bz2``).

Laser records read (one per line, fields separated by blanks; every line ends
``ipc_timestamp host logger_timestamp`` and the scan's timestamp is its ``ipc_timestamp``):

``FLASER n r_1..r_n x y theta odom_x odom_y odom_theta ...`` (``RLASER``: rear laser)
    the old format: beams over 180 degrees starting at -90 (rear: +90); ``x y theta`` is the
    robot pose the logger recorded (raw odometry in raw logs) and becomes ``Scan.odometry``.
``ROBOTLASER1 laser_type start_angle fov angular_resolution max_range accuracy remission_mode
n r_1..r_n m e_1..e_m laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv
forward_safety_dist side_safety_dist turn_axis ...`` (``ROBOTLASER2``: the second laser)
    the newer format (many Freiburg logs hold only these): beam ``i`` at ``start_angle + i *
    angular_resolution`` [rad] in the laser frame; the laser's and the robot's poses are both
    given, so the points are moved into the robot's base frame (the laser's offset on the robot)
    and the robot pose becomes ``Scan.odometry``. Older writers omit the remission block
    ``m e_1..e_m`` or ``turn_axis``; both layouts are read.
``RAWLASER1..4 laser_type start_angle fov angular_resolution max_range accuracy remission_mode
n r_1..r_n m e_1..e_m ...``
    the bare sensor reading with no pose: ``Scan.odometry`` is the ``ODOM x y theta tv rv accel
    ...`` pose interpolated at the scan's timestamp (None when the log has no ODOM lines); the
    points stay in the laser frame.

A log holding several kinds is read through one: FLASER first, then ROBOTLASER1, RAWLASER1,
RLASER, ROBOTLASER2, RAWLASER2..4, unless ``laser=`` names one. Readings at or beyond the
record's maximum range (and ``max_valid_range``) are "no return" and dropped. Other message
types are skipped. With ``skip_bad=True`` a damaged record (truncated, non-numeric, NaN) is
skipped and counted instead of stopping the reading; :attr:`CarmenReader.log_info` says which
record was read and how many were skipped.
"""

from __future__ import annotations

import bisect
import bz2
import functools
import gzip
import logging
import lzma
import math
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError, InputError
from ..geometry import se2_to_matrix
from .compression import base_suffix, count_line_starts, open_text, open_text_prefetched
from .registry import register_reader
from .scan import Scan

log = logging.getLogger(__name__)

RECORD_PRIORITY = ("FLASER", "ROBOTLASER1", "RAWLASER1", "RLASER", "ROBOTLASER2",
                   "RAWLASER2", "RAWLASER3", "RAWLASER4")
"""Laser records in the order a log holding several kinds picks them."""

_ALIASES = {"front": "FLASER", "rear": "RLASER"}
_LASER_TAGS = set(RECORD_PRIORITY)
_KNOWN_TAGS = _LASER_TAGS | {"ODOM", "PARAM", "SYNC", "TRUEPOS", "NEFF", "NMEA-GGA", "NMEAGGA", "NMEARMC",
                             "ROBOTLASER0", "POSITIONLASER", "LASER3", "LASER4"}
_DETECT_LINES = 5000  # lines read past the first laser record to see which kinds a log holds
_MAX_BEAMS = 1_000_000
_SKIPPED_LINES_KEPT = 20
_NO_RETURN = 80.0
_NO_RETURN_SCAN_LINES = 3000  # laser records read ahead to find the log's no-return reading


def detect_no_return_range(ranges: np.ndarray, min_count: int = 20, min_share: float = 0.001) -> float | None:
    """The value a laser writes when a beam returns nothing, found in its readings ``(N,)`` [m].

    A scanner reports "no return" as its maximum range: the largest reading, repeated exactly
    far more often than any real distance is (ACES-like logs: 11,139 readings of exactly 50.0 m;
    Intel 81.83 m, 6x as often as its most common real reading). Returns that value when it
    makes up at least ``min_count`` readings and ``min_share`` of them, is at least 3x as
    frequent as any other value, and at least ``min_count`` readings lie below it; else None
    (the log's largest readings are real distances, or there is too little to tell).
    """
    r = np.asarray(ranges, dtype=np.float64)
    r = r[np.isfinite(r) & (r > 0.0)]
    if len(r) == 0:
        return None
    top = float(r.max())
    count = int(np.count_nonzero(r == top))
    below = r[r < top]
    if count < min_count or count < min_share * len(r) or len(below) < min_count:
        return None
    _, counts = np.unique(below, return_counts=True)
    return top if count >= 3 * int(counts.max()) else None


def laser_choices() -> list[str]:
    """Values ``laser=`` accepts: ``front``, ``rear`` and the record names in lower case."""
    return ["front", "rear", *(tag.lower() for tag in RECORD_PRIORITY)]


def _record_of(laser: str | None) -> str | None:
    if laser is None:
        return None
    if laser in _ALIASES:
        return _ALIASES[laser]
    if laser.upper() in _LASER_TAGS and laser in (laser.upper(), laser.lower()):
        return laser.upper()
    raise ConfigError(f"unknown CARMEN laser {laser!r}: use one of {', '.join(laser_choices())}")


@functools.lru_cache(maxsize=8)
def beam_angles(n: int, rear: bool = False) -> np.ndarray:
    """Angles [rad] of ``n`` FLASER beams over 180 degrees starting at -90 (or +90 for the rear laser).

    Odd counts (181, 361) include both ends; even counts (180, 360) step 180/n degrees. One
    read-only array per count, shared by every record.
    """
    step = math.pi / (n - 1) if n % 2 == 1 and n > 1 else math.pi / n  # one beam: straight at the start
    start = math.pi / 2 if rear else -math.pi / 2
    angles = start + step * np.arange(n)
    angles.flags.writeable = False
    return angles


@dataclass
class LaserReading:
    """One parsed laser record: ranges along ``angles`` in the laser frame."""

    ranges: np.ndarray  # (n,) [m]
    angles: np.ndarray  # (n,) [rad]
    max_range: float  # [m] readings at or beyond are no return
    stamp: float  # ipc_timestamp [s]
    robot_pose: np.ndarray | None  # (3,) x y theta, or None (RAWLASER)
    T_base_laser: np.ndarray | None  # (4, 4) the laser on the robot, or None (in the base frame already)


def _floats(tokens: list[str], what: str, path: Path, lineno: int) -> np.ndarray:
    try:
        # Python's float() parses as numpy does (correctly rounded), in a third less time; it also
        # takes digit separators ("1_0"), which numpy does not and a log must not hold
        if "_" in "".join(tokens):
            raise ValueError("could not convert string to float: a '_' digit separator")
        values = np.fromiter(map(float, tokens), dtype=np.float64, count=len(tokens))
    except ValueError as exc:
        raise InputError(path, f"{what} line has a non-numeric field ({exc})", lineno) from None
    return values


def _count(token: str, what: str, field: str, path: Path, lineno: int) -> int:
    try:
        n = int(token)
    except ValueError:
        raise InputError(path, f"{what} line has no valid {field}", lineno) from None
    if n < 0 or n > _MAX_BEAMS:
        raise InputError(path, f"{what} line has an impossible {field} ({n})", lineno)
    return n


def _finite(values, what: str, path: Path, lineno: int, name: str) -> None:
    if not np.all(np.isfinite(values)):
        raise InputError(path, f"{what} line has a NaN/inf {name}", lineno)


def _stamp(tokens: list[str], path: Path, lineno: int) -> float:
    """The ``ipc_timestamp``: third field from the end."""
    try:
        stamp = float(tokens[-3])
    except ValueError:
        raise InputError(path, f"{tokens[0]} line has a non-numeric timestamp {tokens[-3][:20]!r}", lineno) from None
    if not math.isfinite(stamp):
        raise InputError(path, f"{tokens[0]} line has a NaN/inf pose or timestamp", lineno)
    return stamp


def _parse_flaser(tokens: list[str], path: Path, lineno: int) -> LaserReading:
    """``FLASER``/``RLASER n r_1..r_n x y theta odom_x odom_y odom_theta ipc_ts host logger_ts``."""
    tag = tokens[0]
    try:
        n = int(tokens[1])
    except (IndexError, ValueError):
        raise InputError(path, f"{tag} line has no valid beam count", lineno) from None
    if n <= 0 or len(tokens) < n + 9:
        raise InputError(path, f"{tag} line is truncated: {len(tokens)} fields, expected {n + 11} for {n} beams",
                         lineno)
    ranges = _floats(tokens[2: 2 + n], tag, path, lineno)
    pose = _floats(tokens[2 + n: 5 + n], tag, path, lineno)
    try:
        stamp = float(tokens[8 + n])
    except ValueError as exc:
        raise InputError(path, f"{tag} line has a non-numeric field ({exc})", lineno) from None
    if not np.all(np.isfinite(pose)) or not math.isfinite(stamp):
        raise InputError(path, f"{tag} line has a NaN/inf pose or timestamp", lineno)
    return LaserReading(ranges, beam_angles(n, tag == "RLASER"), math.inf, stamp, pose, None)


def _parse_sensor_header(tokens: list[str], path: Path, lineno: int) -> tuple[np.ndarray, float, int, np.ndarray]:
    """The header shared by ROBOTLASER and RAWLASER: ``(angles, max_range, next_field, ranges)``."""
    tag = tokens[0]
    if len(tokens) < 9:
        raise InputError(path, f"{tag} line is truncated: {len(tokens)} fields", lineno)
    header = _floats(tokens[2:7], tag, path, lineno)  # start_angle fov resolution max_range accuracy
    _finite(header, tag, path, lineno, "angle or range setting")
    start, _fov, resolution, max_range, _accuracy = header
    n = _count(tokens[8], tag, "beam count", path, lineno)
    if n == 0 or len(tokens) < 9 + n + 3:
        raise InputError(path, f"{tag} line is truncated: {len(tokens)} fields for {n} beams", lineno)
    ranges = _floats(tokens[9: 9 + n], tag, path, lineno)
    angles = start + resolution * np.arange(n)
    return angles, (float(max_range) if max_range > 0 else math.inf), 9 + n, ranges


def _parse_rawlaser(tokens: list[str], path: Path, lineno: int) -> LaserReading:
    """``RAWLASERk ... n r_1..r_n m e_1..e_m ipc_ts host logger_ts``: no pose."""
    angles, max_range, k, ranges = _parse_sensor_header(tokens, path, lineno)
    m = _count(tokens[k], tokens[0], "remission count", path, lineno)
    if len(tokens) < k + 1 + m + 3:
        raise InputError(path, f"{tokens[0]} line is truncated: {len(tokens)} fields, expected "
                         f"{k + m + 4} for {len(ranges)} beams and {m} remissions", lineno)
    return LaserReading(ranges, angles, max_range, _stamp(tokens, path, lineno), None, None)


def parse_robotlaser(tokens: list[str], path: Path, lineno: int) -> LaserReading:
    """``ROBOTLASERk ... n r_1..r_n [m e_1..e_m] laser_xyt robot_xyt tv rv fsd ssd [turn_axis] ipc_ts host logger_ts``."""
    tag = tokens[0]
    angles, max_range, k, ranges = _parse_sensor_header(tokens, path, lineno)
    rest = len(tokens) - k - 3  # fields between the ranges and the timestamps
    tail = None
    if tokens[k].isascii() and tokens[k].isdigit() and rest - 1 - int(tokens[k]) in (10, 11):
        tail = k + 1 + int(tokens[k])  # with the remission block
    elif rest in (10, 11):
        tail = k  # an older writer: no remission block
    if tail is None:
        raise InputError(path, f"{tag} line is truncated or has extra fields: {len(tokens)} fields for "
                         f"{len(ranges)} beams", lineno)
    poses = _floats(tokens[tail: tail + 6], tag, path, lineno)
    _finite(poses, tag, path, lineno, "pose")
    laser, robot = poses[:3], poses[3:]
    T_base_laser = np.linalg.inv(se2_to_matrix(*robot)) @ se2_to_matrix(*laser)
    return LaserReading(ranges, angles, max_range, _stamp(tokens, path, lineno), robot, T_base_laser)


_PARSERS = {"FLASER": _parse_flaser, "RLASER": _parse_flaser,
            "ROBOTLASER1": parse_robotlaser, "ROBOTLASER2": parse_robotlaser,
            **{f"RAWLASER{k}": _parse_rawlaser for k in range(1, 5)}}


def _parse_odom(tokens: list[str], path: Path, lineno: int) -> tuple[float, np.ndarray]:
    """``ODOM x y theta tv rv accel ipc_ts host logger_ts`` -> ``(ipc_ts, (x, y, theta))``."""
    if len(tokens) < 10:
        raise InputError(path, f"ODOM line is truncated: {len(tokens)} fields, expected 10", lineno)
    try:
        values = [float(v) for v in tokens[1:8]]
    except ValueError:
        raise InputError(path, "ODOM line has a non-numeric field", lineno) from None
    if not all(math.isfinite(v) for v in values):
        raise InputError(path, "ODOM line has a NaN/inf value", lineno)
    return values[6], np.array(values[:3])


class OdometryTrack:
    """ODOM readings kept sorted by time, for poses at any scan time [s].

    Loggers write messages in arrival order and their ``ipc_timestamp``s are not always in
    order (Intel: 631 of 13,631 scans are stamped before the one above them), so each scan's pose
    is interpolated by time among the recent readings, not between the two lines around it.
    """

    def __init__(self, keep: int = 512) -> None:
        self.times: list[float] = []
        self.poses: list[np.ndarray] = []
        self.latest = -math.inf  # the newest time read so far
        self.keep = keep

    def add(self, t: float, pose: np.ndarray) -> None:
        k = bisect.bisect_right(self.times, t)
        self.times.insert(k, t)
        self.poses.insert(k, pose)
        self.latest = max(self.latest, t)
        if len(self.times) > 2 * self.keep:  # forget the oldest half
            del self.times[: self.keep], self.poses[: self.keep]

    def pose_at(self, t: float) -> np.ndarray | None:
        """``(x, y, theta)`` at ``t``: interpolated, held before the first and after the last reading."""
        if not self.times:
            return None
        k = bisect.bisect_left(self.times, t)
        if k < len(self.times) and self.times[k] == t:
            return self.poses[k]
        if k == 0 or k == len(self.times):
            return self.poses[min(k, len(self.times) - 1)]
        (ta, a), (tb, b) = (self.times[k - 1], self.poses[k - 1]), (self.times[k], self.poses[k])
        w = (t - ta) / (tb - ta)
        d = b - a
        d[2] = math.atan2(math.sin(d[2]), math.cos(d[2]))
        return a + w * d


def detect_records(path: Path, max_lines_after_first: int = _DETECT_LINES) -> list[str]:
    """Laser record kinds seen at the start of a CARMEN log, in :data:`RECORD_PRIORITY` order.

    Reads until a FLASER line or ``max_lines_after_first`` lines past the first laser record.
    """
    seen: set[str] = set()
    after = 0
    try:
        with open_text(path) as fh:
            for line in fh:
                tag = line.split(maxsplit=1)[0] if line.strip() else ""
                if tag in _LASER_TAGS:
                    seen.add(tag)
                    if tag == "FLASER":
                        break
                if seen:
                    after += 1
                    if after >= max_lines_after_first:
                        break
    except (OSError, EOFError, lzma.LZMAError, zlib.error, gzip.BadGzipFile):
        pass  # the reading proper reports it, with the text before the damage
    return [tag for tag in RECORD_PRIORITY if tag in seen]


class CarmenReader:
    """Iterate the laser scans of a CARMEN log as planar :class:`Scan` objects.

    Args:
        path: the log file.
        laser: the record to read: ``"flaser"``, ``"rlaser"``, ``"robotlaser1"``,
            ``"robotlaser2"``, ``"rawlaser1"``..``"rawlaser4"`` (or upper case; ``"front"`` and
            ``"rear"`` name FLASER and RLASER); None picks the first of
            :data:`RECORD_PRIORITY` the log holds. Anything else is a
            :class:`~submapslam.errors.ConfigError`.
        max_valid_range: readings at or above this [m] are "no return" and dropped.
        skip_bad: skip damaged records (and count them in :attr:`log_info`) instead of stopping
            with an :class:`InputError` naming the line.
    """

    name = "carmen"

    def __init__(self, path: Path, laser: str | None = None, max_valid_range: float = _NO_RETURN,
                 skip_bad: bool = False) -> None:
        self.path = Path(path)
        if self.path.is_dir():
            raise InputError(self.path, "is a folder, not a CARMEN log file (a folder of scans is "
                             "read as --format cloud_folder)")
        chosen = _record_of(laser)
        if chosen is None:
            kinds = detect_records(self.path)
            chosen = kinds[0] if kinds else "FLASER"
            if len(kinds) > 1:
                log.info("%s holds %s records; reading %s", self.path.name, "/".join(kinds), chosen)
        self.tag = chosen
        self.max_valid_range = max_valid_range
        self.skip_bad = skip_bad
        self.skipped_records = 0
        self.skipped_lines: list[int] = []
        self.no_return_range: float | None = None  # found in the data when the scans are read
        self.nan_ranges = 0  # NaN beam ranges read (as no return)

    @property
    def log_info(self) -> dict:
        """What ``summary.json`` reports about the reading: record used, damaged records skipped,
        the reading found to mean "no return" (None: none found)."""
        return {"log_format": self.name, "laser_record": self.tag, "skipped_records": self.skipped_records,
                "skipped_record_lines": list(self.skipped_lines), "no_return_range_m": self.no_return_range,
                "nan_ranges": self.nan_ranges}

    def estimated_len(self) -> tuple[int, bool]:
        """``(scans, exact)``: the log's lines of the record read, counted (plain file) or
        estimated from a sample (compressed; see :func:`~.compression.count_line_starts`)."""
        return count_line_starts(self.path, self.tag.encode() + b" ")

    def _find_no_return(self) -> float | None:
        """:func:`detect_no_return_range` over the first ``_NO_RETURN_SCAN_LINES`` records read
        (damaged ones left to the reading proper)."""
        parse = _PARSERS[self.tag]
        chunks: list[np.ndarray] = []
        try:
            with open_text(self.path) as fh:
                for lineno, line in enumerate(fh, start=1):
                    tokens = line.split()
                    if not tokens or tokens[0] != self.tag:
                        continue
                    try:
                        chunks.append(parse(tokens, self.path, lineno).ranges)
                    except InputError:
                        continue
                    if len(chunks) >= _NO_RETURN_SCAN_LINES:
                        break
        except (OSError, EOFError, lzma.LZMAError, zlib.error, gzip.BadGzipFile, UnicodeDecodeError):
            return None  # the reading proper reports it
        return detect_no_return_range(np.concatenate(chunks)) if chunks else None

    def _skip(self, exc: InputError) -> None:
        if not self.skip_bad:
            raise exc
        self.skipped_records += 1
        if len(self.skipped_lines) < _SKIPPED_LINES_KEPT:
            self.skipped_lines.append(exc.line or 0)
        log.debug("skipped a damaged record: %s", exc)

    def _scan(self, reading: LaserReading, index: int, odometry: np.ndarray | None, lineno: int) -> Scan:
        limit = min(self.max_valid_range, reading.max_range)
        if self.no_return_range is not None:
            limit = min(limit, self.no_return_range)
        self.nan_ranges += int(np.isnan(reading.ranges).sum())
        finite = np.isfinite(reading.ranges) & (reading.ranges > 0.0)
        valid = finite & (reading.ranges < limit)
        points = self._points(reading, reading.ranges[valid], reading.angles[valid])
        nothing = finite & ~valid  # at or beyond the maximum: no return, free up to the limit
        no_returns = None
        if math.isfinite(limit):
            no_returns = self._points(reading, np.full(int(nothing.sum()), limit), reading.angles[nothing])
        return Scan(index=index, timestamp=reading.stamp, points=points,
                    odometry=None if odometry is None else se2_to_matrix(*odometry),
                    planar=True, source=f"{self.path.name}:{lineno}", no_returns=no_returns)

    @staticmethod
    def _points(reading: LaserReading, r: np.ndarray, a: np.ndarray) -> np.ndarray:
        """``(n, 3)`` points of ranges ``r`` along angles ``a`` (laser frame) in the robot frame."""
        points = np.zeros((len(r), 3))
        points[:, 0] = r * np.cos(a)
        points[:, 1] = r * np.sin(a)
        if reading.T_base_laser is not None:
            points = points @ reading.T_base_laser[:3, :3].T + reading.T_base_laser[:3, 3]
            points[:, 2] = 0.0
        return points

    def __iter__(self) -> Iterator[Scan]:
        self.skipped_records = 0
        self.skipped_lines = []
        self.nan_ranges = 0
        self.no_return_range = self._find_no_return()
        parse = _PARSERS[self.tag]
        needs_odom = self.tag.startswith("RAWLASER")
        index = 0
        pending: list[tuple[LaserReading, int]] = []  # RAWLASER readings newer than every ODOM yet
        track = OdometryTrack()
        seen: set[str] = set()  # other laser records the log holds
        try:
            with open_text_prefetched(self.path) as fh:
                for lineno, line in enumerate(fh, start=1):
                    tokens = line.split()
                    if not tokens or tokens[0].startswith("#"):
                        continue
                    tag = tokens[0]
                    try:
                        if tag == "ODOM":
                            odom = _parse_odom(tokens, self.path, lineno)
                            if needs_odom:
                                track.add(*odom)
                                while pending and pending[0][0].stamp <= track.latest:  # in log order
                                    reading, at = pending.pop(0)
                                    yield self._scan(reading, index, track.pose_at(reading.stamp), at)
                                    index += 1
                            continue
                        if tag != self.tag:
                            if tag in _LASER_TAGS:
                                seen.add(tag)
                            elif tag not in _KNOWN_TAGS and not tag.isupper():
                                if "\ufffd" in line or "\x00" in line:  # undecodable bytes
                                    raise InputError(self.path, "binary data, not a text CARMEN log", lineno)
                                raise InputError(self.path, f"garbled line starting {tag[:20]!r}", lineno)
                            continue
                        reading = parse(tokens, self.path, lineno)
                    except InputError as exc:
                        self._skip(exc)
                        continue
                    if needs_odom:
                        pending.append((reading, lineno))
                        continue
                    yield self._scan(reading, index, reading.robot_pose, lineno)
                    index += 1
        except (OSError, EOFError, lzma.LZMAError, zlib.error, gzip.BadGzipFile) as exc:
            raise InputError(self.path, f"cannot read compressed log ({exc})") from None
        except UnicodeDecodeError:
            raise InputError(self.path, "not a text CARMEN log") from None
        finally:
            if self.skipped_records:
                log.info("%s: skipped %d damaged record(s)", self.path.name, self.skipped_records)
        for reading, at in pending:  # after the last ODOM: hold its pose (None: no ODOM lines)
            yield self._scan(reading, index, track.pose_at(reading.stamp), at)
            index += 1
        if index == 0:
            others = [k for k in RECORD_PRIORITY if k in seen]
            hint = f" (it holds {', '.join(others)}: choose one with laser=/--laser)" if others else ""
            if self.skipped_records:
                raise InputError(self.path, f"no readable {self.tag} lines ({self.skipped_records} damaged ones skipped)")
            raise InputError(self.path, f"no {self.tag} lines: not a CARMEN laser log{hint}")


def _sniff(path: Path) -> bool:
    if path.is_dir():
        return False
    if base_suffix(path) in {".clf", ".log", ".carmen"}:
        return True
    try:
        with open_text(path) as fh:
            for _ in range(50):
                tokens = fh.readline().split()
                if tokens and not tokens[0].startswith("#"):
                    return tokens[0] in _KNOWN_TAGS
    except (OSError, EOFError, lzma.LZMAError, zlib.error, UnicodeDecodeError):
        return False
    return False


_ = bz2  # bz2 errors surface as OSError
register_reader("carmen", _sniff, CarmenReader)
