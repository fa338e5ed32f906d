"""CARMEN laser logs (``.clf`` / ``.log``, plain, ``.gz`` or ``.bz2``).

Lines read:
    ``FLASER n r_1..r_n x y theta odom_x odom_y odom_theta ipc_timestamp host logger_timestamp``
    ``RLASER`` (same layout, rear laser), ``ODOM x y theta tv rv accel ipc_ts host logger_ts``.
Beams span 180 degrees starting at -90 degrees (rear laser: starting at +90 degrees). ``x y theta``
is the robot pose the logger recorded (raw odometry in raw logs) and becomes ``Scan.odometry``.
The scan timestamp is the line's ``ipc_timestamp``. Other message types are skipped.
"""

from __future__ import annotations

import bz2
import gzip
import lzma
import math
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Literal

import numpy as np

from ..errors import ConfigError, InputError
from ..geometry import se2_to_matrix
from .compression import base_suffix, open_text, open_text_prefetched
from .registry import register_reader
from .scan import Scan

_LASERS = {"front": "FLASER", "rear": "RLASER"}
_LASER_TAGS = set(_LASERS.values())
_KNOWN_TAGS = _LASER_TAGS | {"ODOM", "PARAM", "SYNC", "TRUEPOS", "NEFF", "ROBOTLASER1", "NMEA-GGA"}


def beam_angles(n: int, rear: bool = False) -> np.ndarray:
    """Angles [rad] of ``n`` beams over 180 degrees starting at -90 (or +90 for the rear laser).

    Odd counts (181, 361) include both ends; even counts (180, 360) step 180/n degrees.
    """
    step = math.pi / (n - 1) if n % 2 == 1 else math.pi / n
    start = math.pi / 2 if rear else -math.pi / 2
    return start + step * np.arange(n)


def _parse_laser(tokens: list[str], path: Path, lineno: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Return ranges ``(n,)``, pose ``(3,)`` (x, y, theta) and ipc timestamp of a laser line."""
    try:
        n = int(tokens[1])
    except (IndexError, ValueError):
        raise InputError(path, f"{tokens[0]} line has no valid beam count", lineno) from None
    if n <= 0 or len(tokens) < n + 9:
        raise InputError(
            path,
            f"{tokens[0]} line is truncated: {len(tokens)} fields, expected {n + 11} for {n} beams",
            lineno,
        )
    try:
        ranges = np.array(tokens[2 : 2 + n], dtype=np.float64)
        pose = np.array(tokens[2 + n : 5 + n], dtype=np.float64)
        stamp = float(tokens[8 + n])
    except ValueError as exc:
        raise InputError(path, f"{tokens[0]} line has a non-numeric field ({exc})", lineno) from None
    if not np.all(np.isfinite(pose)) or not math.isfinite(stamp):
        raise InputError(path, f"{tokens[0]} line has a NaN/inf pose or timestamp", lineno)
    return ranges, pose, stamp


def _check_odom(tokens: list[str], path: Path, lineno: int) -> None:
    """Validate an ``ODOM x y theta tv rv accel ipc_ts host logger_ts`` line."""
    if len(tokens) < 10:
        raise InputError(path, f"ODOM line is truncated: {len(tokens)} fields, expected 10", lineno)
    try:
        values = [float(v) for v in tokens[1:8]]
    except ValueError:
        raise InputError(path, "ODOM line has a non-numeric field", lineno) from None
    if not all(math.isfinite(v) for v in values):
        raise InputError(path, "ODOM line has a NaN/inf value", lineno)


class CarmenReader:
    """Iterate the laser scans of a CARMEN log as planar :class:`Scan` objects.

    Args:
        path: the log file.
        laser: ``"front"`` reads FLASER lines, ``"rear"`` RLASER lines; any other value is a
            :class:`~submapslam.errors.ConfigError`.
        max_valid_range: readings at or above this [m] are "no return" and dropped.
    """

    name = "carmen"

    def __init__(self, path: Path, laser: Literal["front", "rear"] = "front", max_valid_range: float = 80.0) -> None:
        self.path = Path(path)
        if laser not in _LASERS:
            raise ConfigError(f"unknown CARMEN laser {laser!r}: use front (FLASER lines) or rear (RLASER lines)")
        self.tag = _LASERS[laser]
        self.rear = laser == "rear"
        self.max_valid_range = max_valid_range

    def __iter__(self) -> Iterator[Scan]:
        index = 0
        angles_cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        try:
            with open_text_prefetched(self.path) as fh:
                for lineno, line in enumerate(fh, start=1):
                    tokens = line.split()
                    if not tokens or tokens[0].startswith("#"):
                        continue
                    tag = tokens[0]
                    if tag == "ODOM":
                        _check_odom(tokens, self.path, lineno)
                        continue
                    if tag != self.tag:
                        if tag not in _KNOWN_TAGS and not tag.isupper():
                            raise InputError(self.path, f"garbled line starting {tag[:20]!r}", lineno)
                        continue
                    ranges, pose, stamp = _parse_laser(tokens, self.path, lineno)
                    n = len(ranges)
                    if n not in angles_cache:
                        a = beam_angles(n, self.rear)
                        angles_cache[n] = (np.cos(a), np.sin(a))
                    cos_a, sin_a = angles_cache[n]
                    valid = np.isfinite(ranges) & (ranges > 0.0) & (ranges < self.max_valid_range)
                    r = ranges[valid]
                    points = np.zeros((len(r), 3))
                    points[:, 0] = r * cos_a[valid]
                    points[:, 1] = r * sin_a[valid]
                    yield Scan(
                        index=index,
                        timestamp=stamp,
                        points=points,
                        odometry=se2_to_matrix(*pose),
                        planar=True,
                        source=f"{self.path.name}:{lineno}",
                    )
                    index += 1
        except (OSError, EOFError, lzma.LZMAError, zlib.error, gzip.BadGzipFile) as exc:
            raise InputError(self.path, f"cannot read compressed log ({exc})") from None
        except UnicodeDecodeError:
            raise InputError(self.path, "not a text CARMEN log") from None
        if index == 0:
            raise InputError(self.path, f"no {self.tag} lines: not a CARMEN laser log")


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
