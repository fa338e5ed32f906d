"""A k-d tree over 2D points with :class:`scipy.spatial.cKDTree`'s ``query``, on small_gicp's KdTree.

The planar odometry queries a few hundred line points with about a hundred scan points, five
times per scan: cKDTree spends ~100-150 us a call in its Python-level set-up, small_gicp's
nanoflann tree ~20 us. Same neighbours, same distances (the squared distance is
``dx * dx + dy * dy`` in both; a neighbour counts when it is strictly below
``distance_upper_bound`` squared, as in cKDTree).
"""

from __future__ import annotations

import numpy as np
import small_gicp


class KdTree2D:
    """Nearest neighbours among ``points (M, 2)``; ``query`` as :meth:`cKDTree.query`."""

    def __init__(self, points: np.ndarray) -> None:
        self.n = len(points)
        self._tree = small_gicp.KdTree(_lift(points)) if self.n else None

    def query(self, x: np.ndarray, k: int = 1, distance_upper_bound: float = np.inf
              ) -> tuple[np.ndarray, np.ndarray]:
        """Distances and rows of the ``k`` nearest points of each ``x (N, 2)``: ``(N,)`` each for
        ``k == 1``, else ``(N, k)``, nearest first; a neighbour not strictly closer than
        ``distance_upper_bound`` is ``inf`` with row ``M``."""
        if self._tree is None:  # no points: every neighbour missing
            shape = (len(x),) if k == 1 else (len(x), k)
            return np.full(shape, np.inf), np.zeros(shape, dtype=np.int64)
        # batch_knn_search returns arrays; batch_nearest_neighbor_search (k = 1, the same
        # neighbours and distances) returns Python lists, 1.4-1.6x slower a call with their conversion
        rows, d2 = self._tree.batch_knn_search(_lift(x), k)
        rows = rows.astype(np.int64)  # uint64 from small_gicp: a missing neighbour (-1) becomes -1 again
        d2 = np.asarray(d2, dtype=np.float64)
        if k == 1:
            rows, d2 = rows.reshape(-1), d2.reshape(-1)
        missing = ~(d2 < distance_upper_bound * distance_upper_bound) | (rows < 0) | (rows >= self.n)
        d = np.sqrt(d2)
        if missing.any():
            d[missing] = np.inf
            rows[missing] = self.n
        return d, rows


def _lift(xy: np.ndarray) -> np.ndarray:
    """``(N, 2)`` -> ``(N, 3)`` float64 with z = 0 (small_gicp's points are 3D)."""
    out = np.zeros((len(xy), 3))
    out[:, :2] = xy
    return out
