"""PCD files with a ``DATA binary`` body read and written with numpy (about 20x faster than open3d).

The body of such a file is ``POINTS`` fixed-size records laid out as the header's ``FIELDS``,
``SIZE``, ``TYPE`` and ``COUNT`` say; ASCII and ``binary_compressed`` bodies are left to open3d.
Maps are written as PCL writes an unorganised cloud (``x y z`` float32, ``HEIGHT 1``), the form
PCL-based tools load (ROS ``pcl_ros``, Autoware's map loader, NDT localisers).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .ply import write_header_and_records

_KINDS = {"F": "f", "U": "u", "I": "i"}  # PCD TYPE -> numpy kind
_HEADER_BYTES = 65536


def pcd_header_values(head: bytes) -> tuple[dict[str, list[str]], int] | None:
    """The header lines of a PCD file's first bytes ``head`` as ``{KEY: words}`` (keys upper-case,
    comments left out) and the byte offset of the body after the ``DATA`` line; None without one."""
    values: dict[str, list[str]] = {}
    offset = 0
    for raw in head.split(b"\n"):
        offset += len(raw) + 1
        words = raw.decode("ascii", errors="replace").split()
        if not words or words[0].startswith("#"):
            continue
        values[words[0].upper()] = words[1:]
        if words[0].upper() == "DATA":
            return values, offset
    return None


def read_pcd_records(path: Path) -> np.ndarray | None:
    """The records of a binary PCD file as a structured array ``(POINTS,)`` (little-endian fields
    named as in ``FIELDS``; a field of ``COUNT`` > 1 is a sub-array), or None when the file is not
    a plain binary PCD this reads (ASCII, compressed, an unknown type, a body of the wrong size)."""
    with open(path, "rb") as fh:
        header = pcd_header_values(fh.read(_HEADER_BYTES))
    if header is None:
        return None
    values, offset = header
    try:
        if values["DATA"][0] != "binary":
            return None
        fields, sizes, types = values["FIELDS"], [int(v) for v in values["SIZE"]], values["TYPE"]
        counts = [int(v) for v in values.get("COUNT", ["1"] * len(fields))]
        points = int(values["POINTS"][0])
        if not (len(fields) == len(sizes) == len(types) == len(counts)) or len(set(fields)) != len(fields):
            return None
        dtype = np.dtype([(name, f"<{_KINDS[kind]}{size}", (count,) if count > 1 else ())
                          for name, size, kind, count in zip(fields, sizes, types, counts)])
    except (KeyError, IndexError, ValueError, TypeError):
        return None
    if offset + points * dtype.itemsize != path.stat().st_size:
        return None
    return np.fromfile(path, dtype=dtype, count=points, offset=offset)


def write_pcd(path: str | Path, points: np.ndarray) -> None:
    """Write ``(N, 3)`` points [m] as a binary PCD v0.7 file (``x y z`` float32, unorganised)."""
    rows = np.ascontiguousarray(np.asarray(points).reshape(-1, 3), dtype="<f4")
    header = ("# .PCD v0.7 - Point Cloud Data file format (written by submapslam)\nVERSION 0.7\n"
              "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
              f"WIDTH {len(rows)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(rows)}\nDATA binary\n")
    write_header_and_records(path, header, rows, "PCD")
