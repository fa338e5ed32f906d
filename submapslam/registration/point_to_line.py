"""Point-to-line refinement of planar (2D laser) odometry against the most recent scans.

KISS-ICP registers points to points. On sparse 2D scans that is biased: where a wall ends
(a door, a pillar, the edge of the sensor's reach) the last beam to hit it lands at a slightly
different place from scan to scan, and point-to-point ICP follows those edge points, so the
estimate lags the motion (about 1 % of the distance on a 1-degree laser with 10 m reach, more
along plain corridors). Point-to-line residuals measure only the distance *across* each wall,
so edge samples do not pull along it.

:class:`RecentScanMap` keeps the last scans (odometry frame), rebuilds its line points (a line
normal per point) every few scans, and refines a pose by Gauss-Newton on the point-to-line
residuals with a Cauchy kernel (:func:`point_to_line`, also the last step of planar submap
matching). The update is solved along the well-constrained eigenvectors only; directions the
scene does not constrain (a plain corridor's axis) take the prediction instead (the wheel
odometry when the log has it), else keep the initial guess. The arithmetic is compiled
(:mod:`.line_kernels`, numba): the recent-scan map runs a whole refinement in one call.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from scipy.spatial import cKDTree

from .line_kernels import LineGrid, gn_step, rotate


def first_point_per_cell(xy: np.ndarray, cell: float) -> np.ndarray:
    """Indices (ascending) of the first of ``(N, 2)`` points in each occupied ``cell`` x ``cell`` square."""
    ij = np.floor(xy / cell).astype(np.int64)
    _, first = np.unique(ij[:, 0] * 4_000_003 + ij[:, 1], return_index=True)  # one key per cell
    return np.sort(first)


def line_normals(points: np.ndarray, tree: cKDTree, k: int = 7, max_flatness: float = 0.1) -> np.ndarray:
    """Unit normals ``(M, 2)`` of 2D points from their ``k`` nearest neighbours; NaN where not line-like."""
    k = min(k, len(points))
    _, idx = tree.query(points, k=k)
    nb = points[idx]
    nb = nb - nb.mean(axis=1, keepdims=True)
    # closed-form eigen decomposition of each 2x2 scatter matrix [[a, b], [b, c]]
    a = np.einsum("nk,nk->n", nb[:, :, 0], nb[:, :, 0])
    b = np.einsum("nk,nk->n", nb[:, :, 0], nb[:, :, 1])
    c = np.einsum("nk,nk->n", nb[:, :, 1], nb[:, :, 1])
    half_gap = np.sqrt((0.5 * (a - c)) ** 2 + b**2)
    small, large = 0.5 * (a + c) - half_gap, 0.5 * (a + c) + half_gap
    angle = 0.5 * np.arctan2(2 * b, a - c)  # direction of the larger eigenvector (the line)
    normals = np.stack([-np.sin(angle), np.cos(angle)], axis=1)
    normals[small > max_flatness * np.maximum(large, 1e-12)] = np.nan
    return normals


class RecentScanMap:
    """The last ``window`` scans as a 2D point-to-line target in the odometry frame."""

    def __init__(self, window: int = 20, rebuild_every: int = 8, voxel: float = 0.05,
                 max_correspondence: float = 0.3, kernel: float = 0.05, min_eigen_fraction: float = 0.02,
                 converged: tuple[float, float] = (5e-5, 3e-6)) -> None:
        self.window = window
        self.converged = converged  # Gauss-Newton stops once a step is below (|dx| + |dy|, |dyaw|)
        self.rebuild_every = rebuild_every
        self.voxel = voxel
        self.max_correspondence = max_correspondence
        self.kernel = kernel
        self.min_eigen_fraction = min_eigen_fraction
        self._scans: deque[np.ndarray] = deque(maxlen=window)
        self._since_rebuild = 0
        self._grid: LineGrid | None = None  # nearest line point lookup, compiled
        self._lines = np.zeros((0, 3))  # per line point: unit normal, offset n . q

    def add(self, points_xy: np.ndarray, xyt: np.ndarray) -> None:
        """Add a scan ``(N, 2)`` (sensor frame) seen from the odometry-frame pose ``xyt``."""
        c, s = np.cos(xyt[2]), np.sin(xyt[2])
        self._scans.append(points_xy @ np.array([[c, s], [-s, c]]) + xyt[:2])
        self._since_rebuild += 1
        if self._grid is None or self._since_rebuild >= self.rebuild_every:
            self._rebuild()

    def _rebuild(self) -> None:
        pts = np.concatenate(list(self._scans))
        pts = pts[first_point_per_cell(pts, self.voxel)]
        self._since_rebuild = 0
        if len(pts) < 10:
            self._grid = None
            return
        normals = line_normals(pts, cKDTree(pts))
        line = np.isfinite(normals[:, 0])  # corners and clutter have no line normal: not targets
        if line.sum() < 10:
            self._grid = None
            return
        self._grid = LineGrid(pts[line], self.max_correspondence)
        self._lines = line_offsets(pts[line], normals[line])

    def fit(self, points_xy: np.ndarray, xyt: np.ndarray, distance: float) -> float:
        """Share of ``points_xy (N, 2)`` (sensor frame) placed at ``xyt`` that lie within ``distance``
        [m] of the target's line points (0 with no target)."""
        if self._grid is None or len(points_xy) == 0:
            return 0.0
        return self._grid.fit(points_xy, xyt, distance) / len(points_xy)

    def refine(self, points_xy: np.ndarray, xyt: np.ndarray, prior_xyt: np.ndarray | None = None,
               iterations: int = 6) -> tuple[np.ndarray, int]:
        """Refine ``xyt`` (odometry frame) of a scan ``(N, 2)``; returns the pose and the inlier count.

        Directions the scene does not constrain (a plain corridor's axis) take ``prior_xyt``
        (e.g. the wheel-odometry prediction) if given, else keep ``xyt``. Returns ``xyt``
        unchanged when there is no map yet or fewer than 20 correspondences.
        """
        if self._grid is None or len(points_xy) < 20:
            return xyt, 0
        return self._grid.refine(points_xy, xyt, self._lines, self.max_correspondence, self.kernel,
                                 self.min_eigen_fraction, prior_xyt, iterations, self.converged)


def line_offsets(target: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``(M, 3)``: per line point of ``target (M, 2)`` its unit normal ``(M, 2)`` and the line's offset ``n . q``."""
    lines = np.empty((len(target), 3))
    lines[:, :2] = normals
    lines[:, 2] = np.einsum("ij,ij->i", target, normals)
    return lines


def point_to_line(points_xy: np.ndarray, xyt: np.ndarray, tree: cKDTree, target: np.ndarray, normals: np.ndarray, *,
                  max_correspondence: float = 0.3, kernel: float = 0.05, min_eigen_fraction: float = 0.02,
                  prior_xyt: np.ndarray | None = None, iterations: int = 6,
                  converged: tuple[float, float] = (5e-5, 3e-6)) -> tuple[np.ndarray, int]:
    """Gauss-Newton on point-to-line residuals (Cauchy kernel) of ``points_xy (N, 2)`` moved by ``xyt``
    against line points ``target (M, 2)`` (``tree``: anything with ``cKDTree.query``'s
    ``query(x, distance_upper_bound=...)`` over them) with unit ``normals (M, 2)``.

    The update is solved only along well-constrained directions; degenerate ones move to
    ``prior_xyt`` when given, else keep ``xyt``. Iterations stop early once a step moves less
    than ``converged`` = ``(|dx| + |dy| [m], |dyaw| [rad])``. Returns the pose and the
    correspondences used (``xyt`` and 0 when fewer than 20 correspond). Each step is
    :func:`.line_kernels.gn_step`; :class:`RecentScanMap` runs the whole loop compiled.
    """
    if len(points_xy) < 20 or len(target) < 10:
        return np.asarray(xyt, dtype=np.float64), 0
    step_m, step_rad = converged
    x0, x1, x2 = (float(v) for v in xyt)
    has_prior = prior_xyt is not None
    prior = np.asarray(prior_xyt, dtype=np.float64) if has_prior else np.zeros(3)
    lines = line_offsets(target, normals)
    points_xy = np.ascontiguousarray(points_xy, dtype=np.float64)
    inv_kernel2 = 1.0 / (kernel * kernel)
    n_used = 0
    for _ in range(iterations):
        rotated = rotate(points_xy, x2)
        d, nn = tree.query(rotated + (x0, x1), distance_upper_bound=max_correspondence)
        nn = np.where(d < np.inf, nn, -1).astype(np.int64)
        s0, s1, s2, n_used = gn_step(rotated, nn, lines, x0, x1, x2, inv_kernel2, min_eigen_fraction, prior, has_prior)
        if n_used < 20:
            return np.asarray(xyt, dtype=np.float64), 0
        x0, x1, x2 = x0 + s0, x1 + s1, x2 + s2
        if abs(s0) + abs(s1) < step_m and abs(s2) < step_rad:
            break
    return np.array([x0, x1, x2]), n_used
