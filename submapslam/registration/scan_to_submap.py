"""Many planar scans against one planar cloud at once: point-to-line in a lookup grid.

Cartographer matches each scan against a submap's high-resolution grid. Here a submap's cloud
``(M, 2)`` (its anchor frame) is rasterised once into a grid of ``cell`` [m]; a Euclidean
distance transform gives every cell its nearest cloud point, so finding a correspondence is an
array lookup instead of a k-d tree query. All scans placed against that cloud are refined
together: Gauss-Newton on point-to-line residuals (Cauchy kernel) with one ``(3, 3)`` system per
scan, assembled and solved for all scans in a few vectorised operations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt


@dataclass
class BatchMatch:
    """Per scan ``(P, ...)``: pose ``xyt`` ``(P, 3)`` in the cloud's frame, point-to-line
    ``information`` ``(P, 3, 3)`` over ``(x, y, yaw)`` of that pose perturbed in the scan's own
    frame, ``fitness`` ``(P,)`` (share of the scan's points within the inlier distance of the
    cloud) and ``inlier_rmse`` ``(P,)`` [m] (point-to-line, of the inliers on line-like cloud
    points; inf without any)."""

    xyt: np.ndarray
    information: np.ndarray
    fitness: np.ndarray
    inlier_rmse: np.ndarray


class LookupGrid:
    """Nearest-point lookup of a planar cloud ``(M, 2)`` within ``reach`` [m] of it, on ``cell`` [m]
    squares over ``box`` = ``(lo (2,), hi (2,))`` (clipped to the cloud's extent)."""

    def __init__(self, cloud: np.ndarray, cell: float, reach: float, box: tuple[np.ndarray, np.ndarray]) -> None:
        lo = np.maximum(box[0], cloud.min(axis=0)) - reach
        hi = np.minimum(box[1], cloud.max(axis=0)) + reach
        self.cell = cell
        self.lo = lo
        shape = np.maximum(np.ceil((hi - lo) / cell).astype(int) + 1, 1)
        ij = np.floor((cloud - lo) / cell).astype(int)
        inside = (ij >= 0).all(axis=1) & (ij < shape).all(axis=1)
        occupied = np.zeros(shape, dtype=bool)
        occupied[ij[inside, 0], ij[inside, 1]] = True
        owner = np.full(shape, -1, dtype=np.int64)
        owner[ij[inside, 0], ij[inside, 1]] = np.flatnonzero(inside)
        if not occupied.any():
            self.nearest = np.full(shape, -1, dtype=np.int64)
            return
        _, (ia, ib) = distance_transform_edt(~occupied, return_indices=True)
        self.nearest = owner[ia, ib]  # the cloud point of the nearest occupied cell

    def lookup(self, xy: np.ndarray) -> np.ndarray:
        """Index of the (approximately) nearest cloud point of each of ``xy`` ``(n, 2)``; -1 outside."""
        ij = np.floor((xy - self.lo) / self.cell).astype(np.int64)
        shape = self.nearest.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < shape[0]) & (ij[:, 1] < shape[1])
        out = np.full(len(xy), -1, dtype=np.int64)
        out[inside] = self.nearest[ij[inside, 0], ij[inside, 1]]
        return out


def match_scans(cloud: np.ndarray, normals: np.ndarray, scans: list[np.ndarray], guesses: np.ndarray, *,
                reaches: tuple[float, ...] = (0.3, 0.3, 0.2, 0.1, 0.1, 0.1), inlier_distance: float = 0.1,
                kernel: float = 0.05, cell: float = 0.05, effective_points: int = 20) -> BatchMatch:
    """Refine scans ``(n_p, 2)`` (sensor frames) against ``cloud`` ``(M, 2)`` from ``guesses``
    ``(P, 3)`` (each scan's pose in the cloud's frame); ``normals`` ``(M, 2)``: unit line normals
    of the cloud's points, NaN where a point is not line-like (not a target). One Gauss-Newton
    step per entry of ``reaches`` (the correspondence distance [m] of that step). The information
    is scaled to ``effective_points`` observations at the inlier residual variance."""
    P = len(scans)
    counts = np.array([len(s) for s in scans], dtype=np.int64)
    pts = np.concatenate(scans) if P else np.zeros((0, 2))
    owner = np.repeat(np.arange(P), counts)
    xyt = np.array(guesses, dtype=np.float64).reshape(P, 3)
    out_info = np.zeros((P, 3, 3))
    fitness, rmse = np.zeros(P), np.full(P, np.inf)
    if P == 0 or len(cloud) == 0 or not len(pts):
        return BatchMatch(xyt, out_info, fitness, rmse)
    c, s = np.cos(xyt[owner, 2]), np.sin(xyt[owner, 2])
    moved = np.stack([c * pts[:, 0] - s * pts[:, 1], s * pts[:, 0] + c * pts[:, 1]], axis=1) + xyt[owner, :2]
    grid = LookupGrid(cloud, cell, max(reaches) + 0.5, (moved.min(axis=0) - 0.5, moved.max(axis=0) + 0.5))
    line = np.isfinite(normals[:, 0])
    offset = np.where(line, np.einsum("ij,ij->i", cloud, np.nan_to_num(normals)), 0.0)
    safe_normals = np.nan_to_num(normals)

    def residuals(reach: float, lines_only: bool):
        c, s = np.cos(xyt[owner, 2]), np.sin(xyt[owner, 2])
        rot = np.stack([c * pts[:, 0] - s * pts[:, 1], s * pts[:, 0] + c * pts[:, 1]], axis=1)
        moved = rot + xyt[owner, :2]
        nn = grid.lookup(moved)
        ok = nn >= 0
        d = np.full(len(pts), np.inf)
        d[ok] = np.hypot(*(moved[ok] - cloud[nn[ok]]).T)
        ok &= d <= reach
        if lines_only:
            ok &= line[np.maximum(nn, 0)]
        k = np.flatnonzero(ok)
        n = safe_normals[nn[k]]
        r = np.einsum("ij,ij->i", n, moved[k]) - offset[nn[k]]
        J = np.stack([n[:, 0], n[:, 1], n[:, 1] * rot[k, 0] - n[:, 0] * rot[k, 1]], axis=1)
        return k, r, J, d

    def normal_equations(k, J, w, r):
        H = np.zeros((P, 3, 3))
        g = np.zeros((P, 3))
        who = owner[k]
        JW = J * w[:, None]
        for a in range(3):
            g[:, a] = np.bincount(who, JW[:, a] * r, minlength=P)
            for b in range(a, 3):
                H[:, a, b] = H[:, b, a] = np.bincount(who, JW[:, a] * J[:, b], minlength=P)
        return H, g, np.bincount(who, minlength=P)

    for reach in reaches:
        k, r, J, _ = residuals(reach, True)
        w = 1.0 / (1.0 + (r / kernel) ** 2)
        H, g, used = normal_equations(k, J, w, r)
        live = used >= 20
        if not live.any():
            break
        damp = 1e-6 + 1e-3 * np.trace(H, axis1=1, axis2=2)[:, None, None] * np.eye(3)
        step = -np.linalg.solve(H[live] + damp[live], g[live][:, :, None])[:, :, 0]
        xyt[live] += step
    k, r, J, d = residuals(inlier_distance, True)
    H, _, used = normal_equations(k, J, np.ones(len(k)), r)
    fitness = np.bincount(owner[d <= inlier_distance], minlength=P) / np.maximum(counts, 1)
    # across the walls (point-to-line), not to the nearest sample along them
    rmse = np.where(used > 0, np.sqrt(np.bincount(owner[k], r**2, minlength=P) / np.maximum(used, 1)), np.inf)
    sigma2 = np.maximum(rmse, 0.02) ** 2
    scale = np.minimum(1.0, effective_points / np.maximum(used, 1))
    # the Gauss-Newton steps move the scan in the cloud's axes; its information is about the scan
    # pose perturbed in the scan's own frame (a Pose2 between-factor's tangent): A^T H A, A = diag(R, 1)
    A = np.zeros((P, 3, 3))
    cos_t, sin_t = np.cos(xyt[:, 2]), np.sin(xyt[:, 2])
    A[:, 0, 0], A[:, 0, 1], A[:, 1, 0], A[:, 1, 1], A[:, 2, 2] = cos_t, -sin_t, sin_t, cos_t, 1.0
    out_info = np.swapaxes(A, 1, 2) @ H @ A * (scale / sigma2)[:, None, None]
    out_info[used < 3] = np.eye(3) * 1e-6
    return BatchMatch(xyt, out_info, fitness, rmse)
