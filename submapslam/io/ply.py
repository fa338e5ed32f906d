"""PLY point-cloud output (binary little-endian, float or double x y z, optional uchar red green blue).

Written with numpy: the same layout open3d writes, without importing open3d (about a second)
just to save a cloud.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import SubmapSlamError


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Write ``(N, 3)`` points (and optional ``(N, 3)`` colours in [0, 1]) to a PLY file.

    float32 points are written as ``float`` (a large map stays float32 from fusion to file, 12
    bytes a point), anything else as ``double``.
    """
    points = np.asarray(points).reshape(-1, 3)
    if points.dtype != np.float32:
        points = points.astype(np.float64, copy=False)
    kind, code = ("float", "<f4") if points.dtype == np.float32 else ("double", "<f8")
    fields = [("x", code), ("y", code), ("z", code)]
    if colors is not None:
        colors = np.asarray(colors, dtype=np.float64).reshape(-1, 3)
        if len(colors) != len(points):
            raise SubmapSlamError(f"{path}: {len(colors)} colours for {len(points)} points")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    props = "".join(f"property {kind if t == code else 'uchar'} {name}\n" for name, t in fields)
    header = ("ply\nformat binary_little_endian 1.0\ncomment Created by submapslam\n"
              f"element vertex {len(points)}\n{props}end_header\n")
    if colors is None:
        rows = np.ascontiguousarray(points, dtype=code)  # no copy for a contiguous array
    else:
        rows = np.empty(len(points), dtype=fields)
        rows["x"], rows["y"], rows["z"] = points.T
        rgb = np.round(np.clip(colors, 0.0, 1.0) * 255.0).astype(np.uint8)
        rows["red"], rows["green"], rows["blue"] = rgb.T
    write_header_and_records(path, header, rows, "PLY")


def write_header_and_records(path: str | Path, header: str, rows: np.ndarray, kind: str) -> None:
    """Write an ASCII ``header`` and then ``rows``' bytes as they lie in memory (a binary cloud
    file of ``kind``, e.g. "PLY"); a file that cannot be written is one :class:`SubmapSlamError`."""
    try:
        with open(path, "wb") as fh:
            fh.write(header.encode("ascii"))
            rows.tofile(fh)
    except OSError as exc:
        raise SubmapSlamError(f"{path}: could not write the {kind} file ({exc})") from exc


PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
             "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
             "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}  # PLY scalar type -> numpy code


def vertex_dtype(header: bytes) -> tuple[np.dtype, int, int] | None:
    """``(record dtype, vertex count, body offset)`` of a binary PLY whose first element is
    ``vertex`` with scalar properties only (what LiDAR tools and open3d write), from the bytes
    at the start of the file; None for anything else (ASCII, lists, other elements first)."""
    end = header.find(b"end_header")
    if not header.startswith(b"ply") or end < 0:
        return None
    lines = [line.split() for line in header[:end].decode("ascii", errors="replace").splitlines()]
    order, fields, count, element = None, [], None, None
    for words in lines:
        if words[:1] == ["format"] and len(words) > 1:
            order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(words[1])
        elif words[:1] == ["element"] and len(words) > 2:
            if element is not None:
                break  # the vertex element's properties are complete
            element = words[1]
            if element != "vertex" or not words[2].isdigit():
                return None
            count = int(words[2])
        elif words[:1] == ["property"] and element == "vertex":
            if len(words) != 3 or words[1] not in PLY_TYPES:
                return None  # a list property or an unknown type
            fields.append((words[2], order + PLY_TYPES[words[1]] if order else ""))
    names = [name for name, _ in fields]
    if order is None or count is None or len(set(names)) != len(names) or not {"x", "y", "z"} <= set(names):
        return None
    return np.dtype(fields), count, header.find(b"\n", end) + 1


def read_ply_vertices(path: str | Path, header: bytes) -> np.ndarray | None:
    """The vertex records of a binary PLY as a structured array (fields named as in the file),
    read with numpy in one call; None when :func:`vertex_dtype` does not describe the file or
    the file is shorter than its header claims (the caller's slower reader then decides)."""
    layout = vertex_dtype(header)
    if layout is None:
        return None
    dtype, count, offset = layout
    records = np.fromfile(path, dtype=dtype, count=count, offset=offset)
    return records if len(records) == count else None
