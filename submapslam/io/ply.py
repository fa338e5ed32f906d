"""PLY point-cloud output (binary little-endian, double x y z, optional uchar red green blue).

Written with numpy: the same layout open3d writes, without importing open3d (about a second)
just to save a cloud.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import SubmapSlamError


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Write ``(N, 3)`` points (and optional ``(N, 3)`` colours in [0, 1]) to a PLY file."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if colors is not None:
        colors = np.asarray(colors, dtype=np.float64).reshape(-1, 3)
        if len(colors) != len(points):
            raise SubmapSlamError(f"{path}: {len(colors)} colours for {len(points)} points")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    props = "".join(f"property {'double' if t == '<f8' else 'uchar'} {name}\n" for name, t in fields)
    header = ("ply\nformat binary_little_endian 1.0\ncomment Created by submapslam\n"
              f"element vertex {len(points)}\n{props}end_header\n")
    if colors is None:
        rows = np.ascontiguousarray(points, dtype="<f8")  # no copy for the usual float64 map
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
