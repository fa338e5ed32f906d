"""Compiled (numba) kernels of the planar point-to-line Gauss-Newton.

:func:`gn_step` is one Gauss-Newton step from given correspondences; it is the arithmetic of
every point-to-line refinement (:func:`.point_to_line.point_to_line`, whatever the
nearest-neighbour lookup). :class:`LineGrid` is an exact nearest-neighbour lookup over 2D line
points within a fixed radius (a uniform grid with cells at least that radius wide, 3 x 3 cells
searched), with which a whole refinement (:func:`refine_in_grid`) and the fit share
(:func:`fit_in_grid`) run in compiled code, one call per scan.

Frames: ``points_xy`` are in the scan's frame, poses ``(x, y, yaw)`` [m, m, rad] and the target
are in the target's frame. ``lines`` is ``(M, 3)``: each target point's unit normal and the
line's offset ``n . q``. Compiled on first use and cached on disk (``cache=True``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: a grid with more cells than this gets coarser cells (the search stays exact)
_MAX_CELLS = 4_000_000
_TWO_PI = 2.0 * math.pi


@njit(cache=True)
def _sym3_smallest(a: float, b: float, c: float, d: float, e: float, f: float) -> float:
    """Smallest eigenvalue of the symmetric ``[[a, d, e], [d, b, f], [e, f, c]]`` (closed form)."""
    p1 = d * d + e * e + f * f
    q = (a + b + c) / 3.0
    if p1 == 0.0:
        return min(a, min(b, c))
    aq, bq, cq = a - q, b - q, c - q
    p = math.sqrt((aq * aq + bq * bq + cq * cq + 2.0 * p1) / 6.0)
    if p == 0.0:
        return q
    r = (aq * (bq * cq - f * f) - d * (d * cq - f * e) + e * (d * f - bq * e)) / (2.0 * p * p * p)
    phi = math.acos(min(1.0, max(-1.0, r))) / 3.0
    return q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)


@njit(cache=True)
def gn_step(rotated: np.ndarray, nn: np.ndarray, lines: np.ndarray, x0: float, x1: float, x2: float,
            inv_kernel2: float, threshold: float, prior: np.ndarray, has_prior: bool) -> tuple:
    """One Gauss-Newton step on point-to-line residuals with a Cauchy kernel.

    ``rotated (N, 2)``: the scan's points turned by the pose's yaw (not yet translated by
    ``x0, x1``); ``nn (N,)``: each point's target row in ``lines``, -1 for none. The step is
    solved along the directions the scene constrains (smallest eigenvalue of the metric-scaled
    Hessian above ``threshold`` times the trace); the other directions move to ``prior``
    ``(3,)`` when ``has_prior``, else stay. Returns ``(dx, dy, dyaw, correspondences)``.
    """
    h00 = h01 = h02 = h11 = h12 = h22 = g0 = g1 = g2 = 0.0
    lever2 = 0.0
    n_used = 0
    for i in range(rotated.shape[0]):
        j = nn[i]
        if j < 0:
            continue
        px, py = rotated[i, 0], rotated[i, 1]
        n0, n1, off = lines[j, 0], lines[j, 1], lines[j, 2]
        a2 = n1 * px - n0 * py
        r = n0 * (px + x0) + n1 * (py + x1) - off
        w = 1.0 / (1.0 + r * r * inv_kernel2)  # Cauchy
        h00 += w * n0 * n0
        h01 += w * n0 * n1
        h02 += w * n0 * a2
        h11 += w * n1 * n1
        h12 += w * n1 * a2
        h22 += w * a2 * a2
        g0 += w * n0 * r
        g1 += w * n1 * r
        g2 += w * a2 * r
        lever2 += px * px + py * py
        n_used += 1
    if n_used < 20:
        return 0.0, 0.0, 0.0, n_used
    # yaw is scaled by the rms lever arm of the matched points so the three directions compare in metres
    lever = max(math.sqrt(lever2 / n_used), 1e-3)
    si = 1.0 / lever
    a, b, cc = h00, h11, h22 * si * si
    if _sym3_smallest(a, b, cc, h01, h02 * si, h12 * si) > threshold * (a + b + cc):
        # every direction constrained: the plain Gauss-Newton step -H^-1 g (cofactors)
        m00, m01, m02 = h11 * h22 - h12 * h12, h02 * h12 - h01 * h22, h01 * h12 - h02 * h11
        m11, m12, m22 = h00 * h22 - h02 * h02, h01 * h02 - h00 * h12, h00 * h11 - h01 * h01
        det = h00 * m00 + h01 * m01 + h02 * m02
        s0 = -(m00 * g0 + m01 * g1 + m02 * g2) / det
        s1 = -(m01 * g0 + m11 * g1 + m12 * g2) / det
        s2 = -(m02 * g0 + m12 * g1 + m22 * g2) / det
        return s0, s1, s2, n_used
    scale = np.array([1.0, 1.0, si])
    H = np.array([[h00, h01, h02], [h01, h11, h12], [h02, h12, h22]])
    evals, evecs = np.linalg.eigh(H * np.outer(scale, scale))
    bound = threshold * (evals[0] + evals[1] + evals[2])
    g_s = scale * np.array([g0, g1, g2])
    to_prior = np.zeros(3)
    if has_prior:
        to_prior[0], to_prior[1] = prior[0] - x0, prior[1] - x1
        dyaw = prior[2] - x2
        to_prior[2] = (dyaw - _TWO_PI * np.round(dyaw / _TWO_PI)) / si
    step = np.zeros(3)
    for k in range(3):
        v = evecs[:, k]
        if evals[k] > bound:
            step -= v * ((v[0] * g_s[0] + v[1] * g_s[1] + v[2] * g_s[2]) / evals[k])
        elif has_prior:
            # degenerate direction: move to the prior (wheel odometry) instead of keeping the guess
            step += v * (v[0] * to_prior[0] + v[1] * to_prior[1] + v[2] * to_prior[2])
    return step[0], step[1], step[2] * si, n_used


@njit(cache=True)
def rotate(points_xy: np.ndarray, yaw: float) -> np.ndarray:
    """``points_xy (N, 2)`` turned by ``yaw`` [rad] about the origin."""
    c, s = math.cos(yaw), math.sin(yaw)
    out = np.empty_like(points_xy)
    for i in range(points_xy.shape[0]):
        px, py = points_xy[i, 0], points_xy[i, 1]
        out[i, 0] = c * px - s * py
        out[i, 1] = s * px + c * py
    return out


@njit(cache=True)
def _build_grid(points: np.ndarray, cell: float, max_cells: int) -> tuple:
    """CSR grid over ``points (M, 2)``: ``(origin (2,), cell, nx, ny, starts (nx*ny+1,), order (M,))``."""
    lo_x, lo_y = points[:, 0].min(), points[:, 1].min()
    span_x, span_y = points[:, 0].max() - lo_x, points[:, 1].max() - lo_y
    while (int(span_x / cell) + 1) * (int(span_y / cell) + 1) > max_cells:
        cell *= 2.0
    nx, ny = int(span_x / cell) + 1, int(span_y / cell) + 1
    keys = np.empty(points.shape[0], dtype=np.int64)
    counts = np.zeros(nx * ny + 1, dtype=np.int64)
    for i in range(points.shape[0]):
        ix = min(int((points[i, 0] - lo_x) / cell), nx - 1)
        iy = min(int((points[i, 1] - lo_y) / cell), ny - 1)
        keys[i] = ix * ny + iy
        counts[keys[i] + 1] += 1
    starts = np.cumsum(counts)
    fill = starts[:-1].copy()
    order = np.empty(points.shape[0], dtype=np.int64)
    for i in range(points.shape[0]):
        order[fill[keys[i]]] = i
        fill[keys[i]] += 1
    return np.array([lo_x, lo_y]), cell, nx, ny, starts, order


@njit(cache=True)
def _nearest(points: np.ndarray, origin: np.ndarray, cell: float, nx: int, ny: int, starts: np.ndarray,
             order: np.ndarray, qx: float, qy: float, max_d2: float) -> int:
    """Row of the point nearest to ``(qx, qy)`` at a squared distance below ``max_d2``, or -1."""
    fx, fy = (qx - origin[0]) / cell, (qy - origin[1]) / cell
    if fx < -1.0 or fy < -1.0 or fx >= nx + 1.0 or fy >= ny + 1.0:
        return -1
    cx, cy = int(math.floor(fx)), int(math.floor(fy))
    best, best_d2 = -1, max_d2
    for ix in range(max(cx - 1, 0), min(cx + 2, nx)):
        for iy in range(max(cy - 1, 0), min(cy + 2, ny)):
            key = ix * ny + iy
            for k in range(starts[key], starts[key + 1]):
                j = order[k]
                dx, dy = points[j, 0] - qx, points[j, 1] - qy
                d2 = dx * dx + dy * dy
                if d2 < best_d2:
                    best, best_d2 = j, d2
    return best


class LineGrid:
    """Exact nearest-neighbour lookup over line points ``(M, 2)`` within ``radius`` [m] (M >= 1)."""

    def __init__(self, points: np.ndarray, radius: float) -> None:
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.radius = float(radius)
        self._grid = _build_grid(self.points, self.radius, _MAX_CELLS)

    def nearest(self, query: np.ndarray, radius: float) -> np.ndarray:
        """Row of each query point's nearest point ``(N,)`` closer than ``radius`` (at most the
        grid's own), -1 for none."""
        if radius > self.radius:
            raise ValueError(f"radius {radius} beyond the grid's {self.radius}")
        return _nearest_all(self.points, *self._grid, np.ascontiguousarray(query, dtype=np.float64), radius * radius)

    def refine(self, points_xy: np.ndarray, xyt: np.ndarray, lines: np.ndarray, max_correspondence: float,
               kernel: float, threshold: float, prior_xyt: np.ndarray | None, iterations: int,
               converged: tuple[float, float]) -> tuple[np.ndarray, int]:
        """:func:`refine_in_grid` on this grid; ``(xyt (3,), correspondences)``."""
        if max_correspondence > self.radius:
            raise ValueError(f"max_correspondence {max_correspondence} beyond the grid's {self.radius}")
        prior = np.zeros(3) if prior_xyt is None else np.asarray(prior_xyt, dtype=np.float64)
        out, n_used = refine_in_grid(np.ascontiguousarray(points_xy, dtype=np.float64),
                                     np.asarray(xyt, dtype=np.float64), self.points, *self._grid, lines,
                                     max_correspondence * max_correspondence, 1.0 / (kernel * kernel), threshold,
                                     prior, prior_xyt is not None, iterations, converged[0], converged[1])
        return out, n_used

    def fit(self, points_xy: np.ndarray, xyt: np.ndarray, distance: float) -> int:
        """How many of ``points_xy (N, 2)`` placed at ``xyt`` lie closer than ``distance`` [m] to a line point."""
        if distance > self.radius:
            raise ValueError(f"distance {distance} beyond the grid's {self.radius}")
        return fit_in_grid(np.ascontiguousarray(points_xy, dtype=np.float64), np.asarray(xyt, dtype=np.float64),
                           self.points, *self._grid, distance * distance)


@njit(cache=True)
def _nearest_all(points, origin, cell, nx, ny, starts, order, query, max_d2):
    out = np.empty(query.shape[0], dtype=np.int64)
    for i in range(query.shape[0]):
        out[i] = _nearest(points, origin, cell, nx, ny, starts, order, query[i, 0], query[i, 1], max_d2)
    return out


@njit(cache=True)
def refine_in_grid(points_xy, xyt, target, origin, cell, nx, ny, starts, order, lines, max_d2, inv_kernel2,
                   threshold, prior, has_prior, iterations, step_m, step_rad):
    """Point-to-line Gauss-Newton of ``points_xy (N, 2)`` from ``xyt`` against the grid's ``target``
    (see :func:`.point_to_line.point_to_line` for the parameters); ``(xyt (3,), correspondences)``,
    ``xyt`` unchanged and 0 when fewer than 20 correspond."""
    x0, x1, x2 = xyt[0], xyt[1], xyt[2]
    n_used = 0
    nn = np.empty(points_xy.shape[0], dtype=np.int64)
    for _ in range(iterations):
        rotated = rotate(points_xy, x2)
        for i in range(rotated.shape[0]):
            nn[i] = _nearest(target, origin, cell, nx, ny, starts, order, rotated[i, 0] + x0, rotated[i, 1] + x1,
                             max_d2)
        s0, s1, s2, n_used = gn_step(rotated, nn, lines, x0, x1, x2, inv_kernel2, threshold, prior, has_prior)
        if n_used < 20:
            return xyt.copy(), 0
        x0, x1, x2 = x0 + s0, x1 + s1, x2 + s2
        if abs(s0) + abs(s1) < step_m and abs(s2) < step_rad:
            break
    return np.array([x0, x1, x2]), n_used


@njit(cache=True)
def fit_in_grid(points_xy, xyt, target, origin, cell, nx, ny, starts, order, max_d2):
    """How many of ``points_xy (N, 2)`` placed at ``xyt`` have a target point at a squared distance below ``max_d2``."""
    c, s = math.cos(xyt[2]), math.sin(xyt[2])
    count = 0
    for i in range(points_xy.shape[0]):
        px, py = points_xy[i, 0], points_xy[i, 1]
        qx, qy = c * px - s * py + xyt[0], s * px + c * py + xyt[1]
        if _nearest(target, origin, cell, nx, ny, starts, order, qx, qy, max_d2) >= 0:
            count += 1
    return count
