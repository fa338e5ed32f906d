"""PLY/PCD headers read without open3d: how many points a scan file claims, and whether the
file can hold them.

open3d trusts the header: a damaged file claiming 10^9 points makes it allocate and read for
minutes. :func:`check_cloud_file` refuses such a file in one line before open3d sees it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError
from .pcd import pcd_header_values
from .ply import PLY_TYPES

_PLY_SIZES = {name: int(code[1]) for name, code in PLY_TYPES.items()}  # bytes of each PLY scalar type
_HEADER_BYTES = 65536
_MAX_LZF_RATIO = 100  # LZF, PCD's compression, packs at most ~90:1


@dataclass(frozen=True)
class CloudHeader:
    """What a PLY/PCD header claims: ``points`` records of ``record_bytes`` bytes each
    (None: a text or compressed body), after ``header_bytes`` bytes of header."""

    points: int
    record_bytes: int | None
    fields: int
    header_bytes: int
    compressed: tuple[int, int] | None = None  # PCD binary_compressed: (compressed, unpacked) bytes
    packed_record_bytes: int = 0  # PCD: bytes a point takes once unpacked


def read_cloud_header(path: Path) -> CloudHeader | None:
    """The header of a ``.ply`` or ``.pcd`` file; None when it cannot be parsed here (open3d
    then decides)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(_HEADER_BYTES)
    except OSError:
        return None
    try:
        if head.startswith(b"ply"):
            return _ply_header(head)
        return _pcd_header(head)
    except (ValueError, IndexError, KeyError):
        return None


def _ply_header(head: bytes) -> CloudHeader | None:
    end = head.find(b"end_header")
    if end < 0:
        return None
    body_start = head.find(b"\n", end) + 1
    binary, points, record, fields, in_vertex = False, None, 0, 0, False
    for raw in head[:end].split(b"\n"):
        words = raw.decode("ascii", errors="replace").split()
        if words[:1] == ["format"]:
            binary = words[1].startswith("binary")
        elif words[:1] == ["element"]:
            in_vertex = words[1] == "vertex"
            if in_vertex:
                points = int(words[2])
        elif words[:1] == ["property"] and in_vertex:
            # a list holds at least its count (an empty list): the record's smallest size
            record += _PLY_SIZES[words[2] if words[1] == "list" else words[1]]
            fields += 1
    if points is None:
        return None
    return CloudHeader(points, record if binary else None, max(fields, 1), body_start)


def _pcd_header(head: bytes) -> CloudHeader | None:
    header = pcd_header_values(head)
    if header is None:
        return None
    values, offset = header
    claims = [int(values["POINTS"][0])] if "POINTS" in values else []
    if "WIDTH" in values and "HEIGHT" in values:
        claims.append(int(values["WIDTH"][0]) * int(values["HEIGHT"][0]))
    points = max(claims, key=abs)  # a reader may trust either
    sizes = [int(v) for v in values.get("SIZE", [])]
    counts = [int(v) for v in values.get("COUNT", ["1"] * len(sizes))]
    record = sum(s * c for s, c in zip(sizes, counts))
    data = values["DATA"][0]
    blocks = None
    if data == "binary_compressed":  # the body starts with the compressed and unpacked sizes (uint32)
        blocks = struct.unpack("<II", head[offset: offset + 8]) if len(head) >= offset + 8 else (-1, -1)
    return CloudHeader(points, record if data == "binary" else None, max(len(sizes), 1), offset,
                       compressed=blocks, packed_record_bytes=record)


def header_point_count(path: Path) -> int | None:
    """Points a scan file holds, from its size (KITTI ``.bin``) or its header (PLY ``element
    vertex``, PCD ``POINTS``); None when the header does not say."""
    if path.suffix.lower() == ".bin":
        size = path.stat().st_size
        return size // 16 if size % 16 == 0 else None  # a damaged size: the reader says so
    header = read_cloud_header(path)
    return None if header is None else header.points


def check_cloud_file(path: Path) -> None:
    """An :class:`InputError` when a PLY/PCD header claims a negative point count or more points
    than the file's bytes can hold (a binary record each, or at least two characters a field)."""
    header = read_cloud_header(path)
    if header is None:
        return
    if header.points < 0:
        raise InputError(path, f"header claims {header.points} points")
    body = path.stat().st_size - header.header_bytes
    if header.compressed is not None:
        packed, unpacked = header.compressed
        if header.points and (packed < 0 or packed > body - 8 or unpacked != header.points * header.packed_record_bytes
                              or unpacked > _MAX_LZF_RATIO * max(packed, 1)):
            raise InputError(path, f"header claims {header.points} points but the compressed block "
                             f"({packed} -> {unpacked} bytes) cannot hold them (truncated or damaged file)")
        return
    per_point = header.record_bytes if header.record_bytes is not None else 2 * header.fields
    if header.points * per_point > max(body, 0):
        raise InputError(path, f"header claims {header.points} points but the file holds at most "
                         f"{max(body, 0) // max(per_point, 1)} (truncated or damaged file)")
