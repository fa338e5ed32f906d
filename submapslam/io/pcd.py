"""PCD files with a ``DATA binary`` body read with numpy (about 20x faster than open3d).

The body of such a file is ``POINTS`` fixed-size records laid out as the header's ``FIELDS``,
``SIZE``, ``TYPE`` and ``COUNT`` say; ASCII and ``binary_compressed`` bodies are left to open3d.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

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
