"""Surface normals of a point cloud, one per query point, from the points of the 27 voxels around it.

Used by the mover split (:mod:`~submapslam.mapping.moving_points`) to tell how steeply a beam
meets the surface at a voxel: a beam that grazes a slope passes a ground voxel and ends on the
same ground metres further on. Numpy only (no scipy: the odometry's child process imports the
mapping package). Frames: any, as long as cloud and queries share it. Units: metres.
"""

from __future__ import annotations

import numpy as np

from .dynamic_removal import voxel_keys

_CUBE = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)])
# key differences to the voxel itself and its 26 neighbours, from voxel_keys itself
_OFFSETS = voxel_keys(_CUBE + 0.5, 1.0) - voxel_keys(np.full((1, 3), 0.5), 1.0)


def local_normals(cloud: np.ndarray | VoxelSums, query: np.ndarray, voxel: float, min_points: int = 5,
                  flatness: float = 1.0) -> np.ndarray:
    """``(Q, 3)`` unit normals at the ``query`` points ``(Q, 3)``: the least-variance direction
    (PCA) of the ``cloud`` points ``(N, 3)`` (or their :class:`VoxelSums` at ``voxel``, for a cloud
    asked again) in the query's ``voxel`` [m] cell and its 26 neighbours (a block 3 voxels wide).
    Zero where that block holds fewer than ``min_points`` or is no surface: its spread along the
    normal is more than ``flatness`` x its spread along the next direction (a pole, a blur of a car
    that moved while the points were taken), or the query lies more than ``voxel / 4`` off that
    surface (a car's sill above the road beside it).

    The block's statistics and its eigen decomposition are computed once per distinct query
    cell (a submap's points share cells by the dozen); only the off-surface test is per point."""
    query = np.asarray(query, dtype=np.float64).reshape(-1, 3)
    out = np.zeros((len(query), 3))
    if not len(query):
        return out
    cells, cell_of = np.unique(voxel_keys(query, voxel), return_inverse=True)
    mean, cov, ok = _block_moments(cloud, cells, voxel, min_points)
    if not ok.any():
        return out
    normal = np.zeros((len(cells), 3))
    surface = np.zeros(len(cells), dtype=bool)
    values, vectors = np.linalg.eigh(cov[ok])
    normal[ok] = vectors[:, :, 0]
    surface[ok] = np.maximum(values[:, 0], 0.0) <= flatness ** 2 * np.maximum(values[:, 1], 0.0)
    cell_of = cell_of.reshape(-1)
    off = np.einsum("ij,ij->i", query - mean[cell_of], normal[cell_of])
    keep = surface[cell_of] & (np.abs(off) <= voxel / 4)
    out[keep] = normal[cell_of[keep]]
    return out


def local_covariances(cloud: np.ndarray, query: np.ndarray, voxel: float,
                      min_points: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(mean, cov, ok)``: the mean ``(Q, 3)`` and covariance ``(Q, 3, 3)`` [m^2] of the ``cloud``
    points ``(N, 3)`` in each ``query`` point's ``voxel`` cell and its 26 neighbours, and ``ok``
    ``(Q,)``: that block holds at least ``min_points`` (elsewhere mean and covariance are zero)."""
    query = np.asarray(query, dtype=np.float64).reshape(-1, 3)
    if not len(query):
        return np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, dtype=bool)
    cells, cell_of = np.unique(voxel_keys(query, voxel), return_inverse=True)
    mean, cov, ok = _block_moments(cloud, cells, voxel, min_points)
    cell_of = cell_of.reshape(-1)
    return mean[cell_of], cov[cell_of], ok[cell_of]


_PAIRS = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]  # the second moments kept per voxel


class VoxelSums:
    """Per occupied ``voxel`` [m] cell of one cloud ``(N, 3)``: its key (sorted, :func:`voxel_keys`),
    point count, and first and second moments about the cloud's lowest corner (``origin``), so
    that the blocks around any queries are sums of 27 cells. Built once, asked many times: a cloud
    the mover split tests again and again (:class:`~submapslam.mapping.moving_points.Placed`)."""

    def __init__(self, cloud: np.ndarray, voxel: float) -> None:
        cloud = np.asarray(cloud, dtype=np.float64).reshape(-1, 3)
        self.voxel = float(voxel)
        self.origin = cloud.min(axis=0) if len(cloud) else np.zeros(3)
        self.keys, inverse = np.unique(voxel_keys(cloud, voxel), return_inverse=True)
        n_vox = len(self.keys)
        self.count = np.bincount(inverse, minlength=n_vox).astype(np.float64)

        def centred(a: int) -> np.ndarray:  # one axis at a time: a split's 700k points are 17 MB a copy
            return cloud[:, a] - self.origin[a]  # sums of squares near the data, not the frame's origin

        self.first = np.stack([np.bincount(inverse, centred(a), n_vox) for a in range(3)], axis=1)
        self.second = np.stack([np.bincount(inverse, centred(a) * centred(b), n_vox) for a, b in _PAIRS], axis=1)

    def block_moments(self, cells: np.ndarray, min_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(mean, cov, ok)`` as :func:`local_covariances`, per voxel key of ``cells`` ``(C,)``."""
        cov = np.zeros((len(cells), 3, 3))
        centre = np.zeros((len(cells), 3))
        n_vox = len(self.keys)
        if not n_vox or not len(cells):
            return centre, cov, np.zeros(len(cells), dtype=bool)
        n = np.zeros(len(cells))
        s1 = np.zeros((len(cells), 3))
        s2 = np.zeros((len(cells), 6))
        for off in _OFFSETS:
            k = cells + off
            pos = np.minimum(np.searchsorted(self.keys, k), n_vox - 1)
            found = np.flatnonzero(self.keys[pos] == k)
            n[found] += self.count[pos[found]]
            s1[found] += self.first[pos[found]]
            s2[found] += self.second[pos[found]]
        ok = n >= min_points
        mean = s1[ok] / n[ok, None]
        m2 = s2[ok] / n[ok, None]
        block = np.empty((int(ok.sum()), 3, 3))
        for (a, b), col in zip(_PAIRS, m2.T):
            block[:, a, b] = block[:, b, a] = col - mean[:, a] * mean[:, b]
        cov[ok] = block
        centre[ok] = mean + self.origin
        return centre, cov, ok


def _block_moments(cloud: np.ndarray | VoxelSums, cells: np.ndarray, voxel: float,
                   min_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(mean, cov, ok)`` as :func:`local_covariances`, per voxel key of ``cells`` ``(C,)``;
    ``cloud``: the points, or their :class:`VoxelSums` at ``voxel``."""
    sums = cloud if isinstance(cloud, VoxelSums) else VoxelSums(cloud, voxel)
    if sums.voxel != float(voxel):
        raise ValueError(f"voxel sums at {sums.voxel} m asked at {voxel} m")
    return sums.block_moments(cells, min_points)
