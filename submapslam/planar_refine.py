"""Point-to-line refinement of planar (2D laser) odometry against the most recent scans.

KISS-ICP registers points to points. On sparse 2D scans that is biased: where a wall ends
(a door, a pillar, the edge of the sensor's reach) the last beam to hit it lands at a slightly
different place from scan to scan, and point-to-point ICP follows those edge points, so the
estimate lags the motion (about 1 % of the distance on a 1-degree laser with 10 m reach, more
along plain corridors). Point-to-line residuals measure only the distance *across* each wall,
so edge samples do not pull along it.

:class:`RecentScanMap` keeps the last scans (odometry frame), rebuilds a k-d tree with a line
normal per point every few scans, and refines a pose by Gauss-Newton on the point-to-line
residuals with a Cauchy kernel (:func:`point_to_line`, also the last step of planar submap
matching). The update is solved along the well-constrained eigenvectors only; directions the
scene does not constrain (a plain corridor's axis) take the prediction instead (the wheel
odometry when the log has it), else keep the initial guess.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from scipy.spatial import cKDTree


def first_point_per_cell(xy: np.ndarray, cell: float) -> np.ndarray:
    """Indices (ascending) of the first of ``(N, 2)`` points in each occupied ``cell`` x ``cell`` square."""
    ij = np.floor(xy / cell).astype(np.int64)
    _, first = np.unique(ij[:, 0] * 4_000_003 + ij[:, 1], return_index=True)  # one key per cell
    return np.sort(first)


def line_normals(points: np.ndarray, tree: cKDTree, k: int = 7, max_flatness: float = 0.1) -> np.ndarray:
    """Unit normals ``(M, 2)`` of 2D points from their ``k`` nearest neighbours; NaN where not line-like."""
    k = min(k, len(points))
    _, idx = tree.query(points, k=k)
    nb = points[idx] - points[idx].mean(axis=1, keepdims=True)
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
                 max_correspondence: float = 0.3, kernel: float = 0.05, min_eigen_fraction: float = 0.02) -> None:
        self.window = window
        self.rebuild_every = rebuild_every
        self.voxel = voxel
        self.max_correspondence = max_correspondence
        self.kernel = kernel
        self.min_eigen_fraction = min_eigen_fraction
        self._scans: deque[np.ndarray] = deque(maxlen=window)
        self._since_rebuild = 0
        self._tree: cKDTree | None = None
        self._points = np.zeros((0, 2))
        self._normals = np.zeros((0, 2))

    def add(self, points_xy: np.ndarray, xyt: np.ndarray) -> None:
        """Add a scan ``(N, 2)`` (sensor frame) seen from the odometry-frame pose ``xyt``."""
        c, s = np.cos(xyt[2]), np.sin(xyt[2])
        self._scans.append(points_xy @ np.array([[c, s], [-s, c]]) + xyt[:2])
        self._since_rebuild += 1
        if self._tree is None or self._since_rebuild >= self.rebuild_every:
            self._rebuild()

    def _rebuild(self) -> None:
        pts = np.concatenate(list(self._scans))
        pts = pts[first_point_per_cell(pts, self.voxel)]
        self._since_rebuild = 0
        if len(pts) < 10:
            self._tree = None
            return
        normals = line_normals(pts, cKDTree(pts))
        line = np.isfinite(normals[:, 0])  # corners and clutter have no line normal: not targets
        self._points, self._normals = pts[line], normals[line]
        self._tree = cKDTree(self._points) if line.sum() >= 10 else None

    def refine(self, points_xy: np.ndarray, xyt: np.ndarray, prior_xyt: np.ndarray | None = None,
               iterations: int = 6) -> tuple[np.ndarray, int]:
        """Refine ``xyt`` (odometry frame) of a scan ``(N, 2)``; returns the pose and the inlier count.

        Directions the scene does not constrain (a plain corridor's axis) take ``prior_xyt``
        (e.g. the wheel-odometry prediction) if given, else keep ``xyt``. Returns ``xyt``
        unchanged when there is no map yet or fewer than 20 correspondences.
        """
        if self._tree is None or len(points_xy) < 20:
            return xyt, 0
        return point_to_line(points_xy, xyt, self._tree, self._points, self._normals,
                             max_correspondence=self.max_correspondence, kernel=self.kernel,
                             min_eigen_fraction=self.min_eigen_fraction, prior_xyt=prior_xyt,
                             iterations=iterations)


def point_to_line(points_xy: np.ndarray, xyt: np.ndarray, tree: cKDTree, target: np.ndarray, normals: np.ndarray, *,
                  max_correspondence: float = 0.3, kernel: float = 0.05, min_eigen_fraction: float = 0.02,
                  prior_xyt: np.ndarray | None = None, iterations: int = 6) -> tuple[np.ndarray, int]:
    """Gauss-Newton on point-to-line residuals (Cauchy kernel) of ``points_xy (N, 2)`` moved by ``xyt``
    against line points ``target (M, 2)`` (k-d ``tree`` over them) with unit ``normals (M, 2)``.

    The update is solved only along well-constrained directions; degenerate ones move to
    ``prior_xyt`` when given, else keep ``xyt``. Returns the pose and the correspondences used
    (``xyt`` and 0 when fewer than 20 correspond).
    """
    if len(points_xy) < 20 or len(target) < 10:
        return np.asarray(xyt, dtype=np.float64), 0
    x = np.asarray(xyt, dtype=np.float64).copy()
    prior = None if prior_xyt is None else np.asarray(prior_xyt, dtype=np.float64)
    n_used = 0
    points_xy = np.ascontiguousarray(points_xy, dtype=np.float64)
    threshold = min_eigen_fraction
    for _ in range(iterations):
        c, s = math.cos(x[2]), math.sin(x[2])
        rotated = points_xy @ np.array([[c, s], [-s, c]])
        d, nn = tree.query(rotated + x[:2], distance_upper_bound=max_correspondence)
        ok = d < np.inf
        n_used = int(np.count_nonzero(ok))
        if n_used < 20:
            return np.asarray(xyt, dtype=np.float64), 0
        idx = nn[ok]
        p, n = rotated[ok], normals[idx]
        r = np.einsum("ij,ij->i", p + x[:2] - target[idx], n)
        J = np.empty((n_used, 3))
        J[:, :2] = n
        J[:, 2] = n[:, 1] * p[:, 0] - n[:, 0] * p[:, 1]
        Jw = J * (1.0 / (1.0 + (r / kernel) ** 2))[:, None]  # Cauchy weights
        H = Jw.T @ J
        g = Jw.T @ r
        # solve only in directions the scene constrains; yaw is scaled by the rms lever arm of
        # the matched points so the three directions compare in metres
        lever = max(math.sqrt(float(np.einsum("ij,ij->", p, p)) / n_used), 1e-3)
        S = np.array([1.0, 1.0, 1.0 / lever])
        Hs = H * np.outer(S, S)
        evals, evecs = np.linalg.eigh(Hs)
        keep = evals > threshold * (evals[0] + evals[1] + evals[2])
        Vk = evecs[:, keep]
        step_s = -(Vk @ ((Vk.T @ (S * g)) / evals[keep]))
        if prior is not None and not keep.all():
            # degenerate directions: move to the prior (wheel odometry) instead of keeping the guess
            to_prior = prior - x
            to_prior[2] = math.remainder(to_prior[2], 2 * math.pi)
            Vd = evecs[:, ~keep]
            step_s = step_s + Vd @ (Vd.T @ (to_prior / S))
        step = S * step_s
        x += step
        if abs(step[0]) + abs(step[1]) < 5e-5 and abs(step[2]) < 3e-6:
            break
    return x, n_used
