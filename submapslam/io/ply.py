"""PLY point-cloud output through open3d (binary little-endian, float32 x y z)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import SubmapSlamError


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Write ``(N, 3)`` points (and optional ``(N, 3)`` colours in [0, 1]) to a PLY file."""
    from .._deps import open3d

    o3d = open3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if colors is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.asarray(colors, dtype=np.float64))
    if not o3d.io.write_point_cloud(str(path), pcd, write_ascii=False):
        raise SubmapSlamError(f"{path}: open3d could not write the PLY file")
