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
    try:
        with open(path, "wb") as fh:
            fh.write(header.encode("ascii"))
            rows.tofile(fh)
    except OSError as exc:
        raise SubmapSlamError(f"{path}: could not write the PLY file ({exc})") from exc
