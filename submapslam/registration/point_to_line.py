"""Point-to-line refinement of planar (2D laser) odometry against the most recent scans.

KISS-ICP registers points to points. On sparse 2D scans that is biased: where a wall ends
(a door, a pillar, the edge of the sensor's reach) the last beam to hit it lands at a slightly
different place from scan to scan, and point-to-point ICP follows those edge points, so the
estimate lags the motion (about 1 % of the distance on a 1-degree laser with 10 m reach, more
along plain corridors). Point-to-line residuals measure only the distance *across* each wall,
so edge samples do not pull along it.

:class:`RecentScanMap` keeps the last scans (odometry frame), rebuilds a k-d tree with a line
normal per point every few scans (:class:`.kdtree2d.KdTree2D`: cKDTree's queries, faster), and refines a pose by Gauss-Newton on the point-to-line
residuals with a Cauchy kernel (:func:`point_to_line`, also the last step of planar submap
matching). The update is solved along the well-constrained eigenvectors only; directions the
scene does not constrain (a plain corridor's axis) take the prediction instead (the wheel
odometry when the log has it), else keep the initial guess.
"""

from __future__ import annotations

import math
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

from .kdtree2d import KdTree2D

if TYPE_CHECKING:  # a type only: a planar run's odometry process need not load scipy.spatial
    from scipy.spatial import cKDTree


def first_point_per_cell(xy: np.ndarray, cell: float) -> np.ndarray:
    """Indices (ascending) of the first of ``(N, 2)`` points in each occupied ``cell`` x ``cell`` square."""
    ij = np.floor(xy / cell).astype(np.int64)
    _, first = np.unique(ij[:, 0] * 4_000_003 + ij[:, 1], return_index=True)  # one key per cell
    return np.sort(first)


#: a neighbourhood scattered across its line by up to this many times the scanner's measured wall
#: noise (:mod:`.wall_noise`, the part beyond :data:`CLEAN_WALL_NOISE_M`) is still a line: 3 cm of
#: range noise keeps the walls (FR079 with it: 0.53 -> 0.10 m; factors 2 and 3 did worse on one
#: noisy log or another, BENCHMARKS.md stop 70)
LINE_NOISE_FACTOR = 2.5
#: [m] the wall noise of the scanners ``max_flatness`` was chosen on (Intel 0.005, FR079 0.006 m):
#: only the noise beyond it needs room
CLEAN_WALL_NOISE_M = 0.012
#: ... as long as its scatter across stays under this share of its scatter along: a compact blob
#: (clutter, a chair's legs) is no line however small it is
NOISY_LINE_FLATNESS = 0.3


def line_normals(points: np.ndarray, tree: cKDTree, k: int = 7, max_flatness: float = 0.1,
                 noise_m: float = 0.0) -> np.ndarray:
    """Unit normals ``(M, 2)`` of 2D points from their ``k`` nearest neighbours; NaN where not line-like.

    Line-like: the neighbours' scatter across their line is under ``max_flatness`` of their
    scatter along it, or (a noisy scanner, ``noise_m`` [m] its wall noise) within
    :data:`LINE_NOISE_FACTOR` x the noise beyond :data:`CLEAN_WALL_NOISE_M` rms and under
    :data:`NOISY_LINE_FLATNESS` of the scatter along. ``noise_m`` up to that clean figure changes nothing."""
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
    allowed = max_flatness * np.maximum(large, 1e-12)
    excess = noise_m * noise_m - CLEAN_WALL_NOISE_M**2  # beyond what max_flatness allows for
    if excess > 0.0:
        allowed = np.maximum(allowed, np.minimum(k * LINE_NOISE_FACTOR**2 * excess, NOISY_LINE_FLATNESS * large))
    normals[small > allowed] = np.nan
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
        self.noise_m = 0.0  # [m] the scanner's scatter across walls (:mod:`.wall_noise`) the line test allows
        self._scans: deque[np.ndarray] = deque(maxlen=window)
        self._since_rebuild = 0
        self._tree: KdTree2D | None = None
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
        normals = line_normals(pts, KdTree2D(pts), noise_m=self.noise_m)
        line = np.isfinite(normals[:, 0])  # corners and clutter have no line normal: not targets
        self._points, self._normals = pts[line], normals[line]
        self._tree = KdTree2D(self._points) if line.sum() >= 10 else None

    def fit(self, points_xy: np.ndarray, xyt: np.ndarray, distance: float) -> float:
        """Share of ``points_xy (N, 2)`` (sensor frame) placed at ``xyt`` that lie within ``distance``
        [m] of the target's line points (0 with no target)."""
        if self._tree is None or len(points_xy) == 0:
            return 0.0
        c, s = math.cos(xyt[2]), math.sin(xyt[2])
        moved = points_xy @ np.array([[c, s], [-s, c]]) + xyt[:2]
        d, _ = self._tree.query(moved, distance_upper_bound=distance)
        return float(np.count_nonzero(d <= distance)) / len(points_xy)

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
                             iterations=iterations, converged=self.converged)


def refit_first_scan(frames_xy: list[np.ndarray], xyts: np.ndarray, iterations: int = 20,
                     min_inliers: int = 50) -> np.ndarray | None:
    """The first scan's pose ``(3,)`` registered again, point-to-line, against the scans after it.

    ``frames_xy``: each scan's ``(n_k, 2)`` points in its sensor frame; ``xyts`` ``(K, 3)``: their
    odometry-frame poses, the first included (the start of the refit). None when fewer than
    ``min_inliers`` points matched."""
    target = RecentScanMap(window=max(len(frames_xy) - 1, 1), rebuild_every=1)
    for xy, xyt in zip(frames_xy[1:], xyts[1:]):
        target.add(xy, xyt)
    refined, inliers = target.refine(frames_xy[0], np.asarray(xyts[0], dtype=np.float64), iterations=iterations)
    return np.asarray(refined, dtype=np.float64) if inliers >= min_inliers else None


def _sym3_eigvals(a: float, b: float, c: float, d: float, e: float, f: float) -> tuple[float, float, float]:
    """Eigenvalues, ascending, of the symmetric ``[[a, d, e], [d, b, f], [e, f, c]]`` (closed form)."""
    p1 = d * d + e * e + f * f
    q = (a + b + c) / 3.0
    if p1 == 0.0:
        lo, mid, hi = sorted((a, b, c))
        return lo, mid, hi
    aq, bq, cq = a - q, b - q, c - q
    p = math.sqrt((aq * aq + bq * bq + cq * cq + 2.0 * p1) / 6.0)
    if p == 0.0:
        return q, q, q
    r = (aq * (bq * cq - f * f) - d * (d * cq - f * e) + e * (d * f - bq * e)) / (2.0 * p * p * p)
    phi = math.acos(min(1.0, max(-1.0, r))) / 3.0
    hi = q + 2.0 * p * math.cos(phi)
    lo = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    return lo, 3.0 * q - lo - hi, hi


def point_to_line(points_xy: np.ndarray, xyt: np.ndarray, tree: cKDTree, target: np.ndarray, normals: np.ndarray, *,
                  max_correspondence: float = 0.3, kernel: float = 0.05, min_eigen_fraction: float = 0.02,
                  prior_xyt: np.ndarray | None = None, iterations: int = 6,
                  converged: tuple[float, float] = (5e-5, 3e-6)) -> tuple[np.ndarray, int]:
    """Gauss-Newton on point-to-line residuals (Cauchy kernel) of ``points_xy (N, 2)`` moved by ``xyt``
    against line points ``target (M, 2)`` (k-d ``tree`` over them) with unit ``normals (M, 2)``.

    The update is solved only along well-constrained directions; degenerate ones move to
    ``prior_xyt`` when given, else keep ``xyt``. Iterations stop early once a step moves less
    than ``converged`` = ``(|dx| + |dy| [m], |dyaw| [rad])``. Returns the pose and the
    correspondences used (``xyt`` and 0 when fewer than 20 correspond).
    """
    if len(points_xy) < 20 or len(target) < 10:
        return np.asarray(xyt, dtype=np.float64), 0
    step_m, step_rad = converged
    x0, x1, x2 = (float(v) for v in xyt)
    prior = None if prior_xyt is None else np.asarray(prior_xyt, dtype=np.float64)
    # per target point: its normal and the line's offset n . q, gathered with one index per step
    lines = np.empty((len(target), 3))
    lines[:, :2] = normals
    lines[:, 2] = np.einsum("ij,ij->i", target, normals)
    n_used = 0
    points_xy = np.ascontiguousarray(points_xy, dtype=np.float64)
    inv_kernel2 = 1.0 / (kernel * kernel)
    threshold = min_eigen_fraction
    for _ in range(iterations):
        c, s = math.cos(x2), math.sin(x2)
        rotated = points_xy @ np.array([[c, s], [-s, c]])
        d, nn = tree.query(rotated + (x0, x1), distance_upper_bound=max_correspondence)
        ok = d < np.inf
        idx = nn[ok]
        n_used = len(idx)
        if n_used < 20:
            return np.asarray(xyt, dtype=np.float64), 0
        p, nq = rotated[ok], lines[idx]
        # rows (J, r): J = n^T [I, dR p], r = n . (p + t) - n . q
        A = np.empty((n_used, 4))
        A[:, :2] = nq[:, :2]
        A[:, 2] = nq[:, 1] * p[:, 0] - nq[:, 0] * p[:, 1]
        A[:, 3] = nq[:, 0] * (p[:, 0] + x0) + nq[:, 1] * (p[:, 1] + x1) - nq[:, 2]
        weights = 1.0 / (1.0 + np.square(A[:, 3]) * inv_kernel2)  # Cauchy
        (h00, h01, h02, g0), (_, h11, h12, g1), (_, _, h22, g2), _ = ((A * weights[:, None]).T @ A).tolist()
        # solve only in directions the scene constrains; yaw is scaled by the rms lever arm of
        # the matched points so the three directions compare in metres
        lever = max(math.sqrt(float(np.vdot(p, p)) / n_used), 1e-3)
        si = 1.0 / lever
        a, b, cc, dd, e, f = h00, h11, h22 * si * si, h01, h02 * si, h12 * si
        smallest = _sym3_eigvals(a, b, cc, dd, e, f)[0]
        if smallest > threshold * (a + b + cc):
            # every direction constrained: the plain Gauss-Newton step -H^-1 g (cofactors)
            m00, m01, m02 = h11 * h22 - h12 * h12, h02 * h12 - h01 * h22, h01 * h12 - h02 * h11
            m11, m12, m22 = h00 * h22 - h02 * h02, h01 * h02 - h00 * h12, h00 * h11 - h01 * h01
            det = h00 * m00 + h01 * m01 + h02 * m02
            s0 = -(m00 * g0 + m01 * g1 + m02 * g2) / det
            s1 = -(m01 * g0 + m11 * g1 + m12 * g2) / det
            s2 = -(m02 * g0 + m12 * g1 + m22 * g2) / det
        else:
            S = np.array([1.0, 1.0, si])
            H = np.array([[h00, h01, h02], [h01, h11, h12], [h02, h12, h22]])
            evals, evecs = np.linalg.eigh(H * np.outer(S, S))
            keep = evals > threshold * (evals[0] + evals[1] + evals[2])
            Vk = evecs[:, keep]
            step_s = -(Vk @ ((Vk.T @ (S * np.array([g0, g1, g2]))) / evals[keep]))
            if prior is not None:
                # degenerate directions: move to the prior (wheel odometry) instead of keeping the guess
                to_prior = prior - (x0, x1, x2)
                to_prior[2] = math.remainder(to_prior[2], 2 * math.pi)
                Vd = evecs[:, ~keep]
                step_s = step_s + Vd @ (Vd.T @ (to_prior / S))
            s0, s1, s2 = (S * step_s).tolist()
        x0, x1, x2 = x0 + s0, x1 + s1, x2 + s2
        if abs(s0) + abs(s1) < step_m and abs(s2) < step_rad:
            break
    return np.array([x0, x1, x2]), n_used
