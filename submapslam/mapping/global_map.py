"""Global occupancy map: local grids per submap fused through optimised anchors (2D lasers, and
3D LiDAR through the obstacle slice of each scan)."""

from __future__ import annotations

import numpy as np

from ..geometry import transform_points
from ..result import SlamResult
from .evidence_grid import EvidenceGrid, GridParams, fuse_submap_grids


def local_grid(T_anchor_scans: np.ndarray, scan_points: list[np.ndarray], params: GridParams) -> EvidenceGrid | None:
    """Evidence grid of one submap in its anchor frame from its scans (``(n_k, 3)`` sensor frame)."""
    world = [transform_points(T, p)[:, :2] for T, p in zip(T_anchor_scans, scan_points) if len(p)]
    if not world:
        return None
    extent = np.vstack([*world, T_anchor_scans[:, :2, 3]])
    grid = EvidenceGrid.covering(extent, params)
    for n, (T, pts) in enumerate(zip(T_anchor_scans, scan_points)):
        grid.integrate_scan(T, pts, carve_free=n % params.free_scan_stride == 0)
    return grid


def grid_params(result: SlamResult) -> GridParams:
    """Grid parameters for a run: the configured cell size; 3D LiDAR carves free space farther."""
    mapping = result.config.mapping
    if result.planar:
        return GridParams(resolution=mapping.grid_resolution)
    return GridParams(resolution=mapping.grid_resolution_3d, max_free_range=30.0)


def build_global_grid(result: SlamResult, params: GridParams | None = None) -> tuple[EvidenceGrid, int]:
    """Fuse every submap's local grid in time order; return the grid and cells cleared as dynamic."""
    params = params or grid_params(result)
    corners = []
    locals_: list[tuple[EvidenceGrid, np.ndarray]] = []
    for k, T_world_anchor in enumerate(result.submap_poses):
        grid = local_grid(result.submap_scan_poses[k], result.submap_scan_points[k], params)
        if grid is None:
            continue
        h, w = grid.logodds.shape
        box = grid.origin + np.array([[0, 0], [w, 0], [0, h], [w, h]]) * params.resolution
        box3 = np.c_[box, np.zeros(4)]
        corners.append(transform_points(T_world_anchor, box3)[:, :2])
        locals_.append((grid, T_world_anchor))
    if not locals_:
        raise ValueError("no scans to build a grid from")
    global_grid = EvidenceGrid.covering(np.vstack(corners), params, margin=0.5)
    cleared = sum(fuse_submap_grids(global_grid, g, T) for g, T in locals_)
    return global_grid, cleared
