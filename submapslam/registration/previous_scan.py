"""A planar (2D laser) scan's odometry pose checked against the scan just before it.

Registered to the map of the last scans from the wheels' guess, a scan can end in a wrong
minimum when the step between scans is large (a log recorded at a low scan rate, a fast turn):
the wheels miss part of a turn the scans show (FR079 at a third of its rate: wheels -3 deg where
the scans turned +15), ICP from there stays near them, and once one scan is off, the map of the
last scans holds it, so the next scans fit that error better than the truth. The scan before
the new one is consistent with itself whatever the map holds. So a pose that fits the map poorly
is checked here: the new scan is matched to the previous one by an exhaustive correlative
search around the predicted step (+-1 m, +-45 deg; :func:`correlative_step`: Olson's search on a
likelihood grid, coarse then fine, numpy only, so that the odometry's child process loads no
scipy), that pose is refined against the map as usual (by the caller), and it is preferred when
it puts clearly more of the scan on the previous scan's points.

Frames: points ``(N, 2)`` or ``(N, 3)`` (z ignored) in each scan's sensor frame; poses ``(x, y,
yaw)`` in the odometry frame [m, rad]; ``T_previous_new`` ``(4, 4)``.
"""

from __future__ import annotations

import math

import numpy as np

from ..geometry import matrix_to_se2, se2_to_matrix
from .kdtree2d import KdTree2D
from .point_to_line import first_point_per_cell

#: [m] a point of the new scan this close to the previous scan's counts for the match's fitness
MATCH_INLIER_M = 0.2
#: [m] the search uses the points of both scans within this range of their sensor: its fine grid
#: (0.05 m cells over the previous scan's extent) then holds at most 2 M cells (16 MB) for a 180 deg
#: laser; the real logs' scans reach 25-42 m
SEARCH_REACH_M = 50.0


class PreviousScan:
    """The scan before the one being registered, placed in the odometry frame.

    ``window_m`` / ``yaw_window_deg``: half widths of the correlative search around the predicted
    step; ``min_match_fitness``: the share of the scan within :data:`MATCH_INLIER_M` of the
    previous scan at the match, below which it proposes nothing; ``distance`` [m]: a point on the
    previous scan's points for :meth:`share`; ``margin`` / ``min_share``: a candidate is
    preferred when its share beats the registered pose's by ``margin`` and is at least
    ``min_share``. The defaults were chosen on the three real CARMEN logs at their full rate and
    at a half and a third of it (BENCHMARKS.md: of 2,938 checked scans, the candidate these
    thresholds take was the better pose against the reference in 115 of 138, worse in 8).
    """

    def __init__(self, points_xy: np.ndarray, xyt: np.ndarray, *, window_m: float = 1.0,
                 yaw_window_deg: float = 45.0, min_match_fitness: float = 0.5, distance: float = 0.1,
                 margin: float = 0.1, min_share: float = 0.5) -> None:
        self.points = np.ascontiguousarray(np.asarray(points_xy, dtype=np.float64)[:, :2])
        self.xyt = np.asarray(xyt, dtype=np.float64)
        self.window_m = window_m
        self.yaw_window = math.radians(yaw_window_deg)
        self.min_match_fitness = min_match_fitness
        self.distance = distance
        self.margin = margin
        self.min_share = min_share
        self._tree: KdTree2D | None = None

    def share(self, points_xy: np.ndarray, xyt: np.ndarray, distance: float | None = None) -> float:
        """Share of ``points_xy`` placed at ``xyt`` within ``distance`` [m] (None: :attr:`distance`)
        of this scan's points."""
        distance = self.distance if distance is None else distance
        if len(points_xy) == 0 or len(self.points) == 0:
            return 0.0
        if self._tree is None:
            self._tree = KdTree2D(_placed(self.points, self.xyt))
        d, _ = self._tree.query(_placed(np.asarray(points_xy, dtype=np.float64)[:, :2], xyt),
                                distance_upper_bound=distance)
        return float(np.count_nonzero(d <= distance)) / len(points_xy)

    def candidate(self, points_xy: np.ndarray, T_previous_new: np.ndarray) -> np.ndarray | None:
        """The new scan's odometry pose ``(3,)`` by matching it to this scan from the predicted
        step ``T_previous_new`` (:func:`correlative_step` on the points within :data:`SEARCH_REACH_M`);
        None when either scan has fewer than 20 there, or when fewer than ``min_match_fitness`` of its
        points then lie within :data:`MATCH_INLIER_M` of this scan's."""
        pts = np.asarray(points_xy, dtype=np.float64)[:, :2]
        source, target = _within(pts, SEARCH_REACH_M), _within(self.points, SEARCH_REACH_M)
        if len(source) < 20 or len(target) < 20:
            return None
        step = correlative_step(source, target, matrix_to_se2(T_previous_new), self.window_m, self.yaw_window)
        pose = matrix_to_se2(se2_to_matrix(*self.xyt) @ se2_to_matrix(*step))
        return pose if self.share(pts, pose, MATCH_INLIER_M) >= self.min_match_fitness else None

    def prefers(self, points_xy: np.ndarray, candidate_xyt: np.ndarray, registered_xyt: np.ndarray) -> bool:
        """Whether ``candidate_xyt`` puts clearly more of the scan on this scan's points than
        ``registered_xyt`` does (:meth:`share`, ``margin``, ``min_share``)."""
        candidate = self.share(points_xy, candidate_xyt)
        return candidate >= self.min_share and candidate > self.share(points_xy, registered_xyt) + self.margin


def correlative_step(source_xy: np.ndarray, target_xy: np.ndarray, guess_xyt: np.ndarray, window_m: float,
                     yaw_window: float) -> np.ndarray:
    """``(x, y, yaw)`` of the source scan ``(N, 2)`` in the target scan's frame (``(M, 2)``) that best
    puts it on the target: every pose within ``window_m`` [m] and ``yaw_window`` [rad] of
    ``guess_xyt`` scored on the target's likelihood grid (a Gaussian around each target point),
    first on 0.25 m / 2 deg steps (0.3 m wide Gaussians), then on 0.05 m / 0.5 deg steps within
    one coarse step of the best (0.1 m wide). Ties keep the pose nearest the guess."""
    guess = np.asarray(guess_xyt, dtype=np.float64)
    best = guess
    for cell, sigma, half_m, half_rad, step_rad in ((0.25, 0.3, window_m, yaw_window, math.radians(2.0)),
                                                      (0.05, 0.1, 0.25, math.radians(2.0), math.radians(0.5))):
        max_shift = int(round(half_m / cell))
        grid = _LikelihoodGrid(target_xy, cell, sigma, max_shift)
        source = source_xy[first_point_per_cell(source_xy, cell)]
        steps = np.arange(-max_shift, max_shift + 1)
        steps = steps[np.argsort(np.abs(steps), kind="stable")]  # nearest the centre first: it wins ties
        shifts = np.stack(np.meshgrid(steps, steps, indexing="ij"), -1).reshape(-1, 2)  # in cells
        turns = np.arange(0.0, half_rad + 1e-9, step_rad)
        turns = np.concatenate([[0.0], np.ravel(np.column_stack([turns[1:], -turns[1:]]))])
        turned = np.stack([_placed(source, (best[0], best[1], best[2] + turn)) for turn in turns])
        scores = grid.scores(turned, shifts)
        k, j = np.unravel_index(int(np.argmax(scores)), scores.shape)
        best = np.array([best[0] + shifts[j, 0] * cell, best[1] + shifts[j, 1] * cell, best[2] + turns[k]])
    return best


class _LikelihoodGrid:
    """A Gaussian of ``sigma`` [m] around each target point ``(M, 2)`` on ``cell`` [m] squares (the
    largest where they overlap), with a border of empty cells that lookups off the grid land on.
    Lookups shift points by at most ``max_shift`` cells (:meth:`scores`)."""

    def __init__(self, target_xy: np.ndarray, cell: float, sigma: float, max_shift: int) -> None:
        r = int(math.ceil(3.0 * sigma / cell))
        self.cell = cell
        self.max_shift = max_shift
        self.lo = target_xy.min(axis=0) - (r + 1) * cell
        rows, cols = (np.floor((target_xy.max(axis=0) + (r + 1) * cell - self.lo) / cell).astype(np.int64) + 1).tolist()
        self.rows, self.cols = rows, cols  # the grid's cells from ``lo``; the Gaussians end a cell inside
        # stored with 2 * max_shift more empty cells on each side: a point up to max_shift cells off
        # the grid, shifted by up to max_shift, stays on the stored array without clipping
        self._pad = 2 * max_shift
        self._stride = cols + 2 * self._pad
        self.values = np.zeros((rows + 2 * self._pad) * self._stride)
        ij = np.unique(np.floor((target_xy - self.lo) / cell).astype(np.int64), axis=0) + self._pad
        centres = ij[:, 0] * self._stride + ij[:, 1]  # distinct cells: each offset's lookups need no ufunc.at
        for di in range(-r, r + 1):
            for dj in range(-r, r + 1):
                value = math.exp(-0.5 * cell * cell * (di * di + dj * dj) / (sigma * sigma))
                at = centres + (di * self._stride + dj)
                self.values[at] = np.maximum(self.values[at], value)

    def scores(self, points: np.ndarray, shifts: np.ndarray) -> np.ndarray:
        """``(T, S)`` summed likelihood of each of ``T`` placements of the points ``(T, N, 2)`` moved
        by each of ``shifts`` ``(S, 2)`` (whole cells, at most ``max_shift``); a point off the grid
        scores 0."""
        ij = np.floor((points - self.lo) / self.cell).astype(np.int64)
        # a point more than max_shift cells off the grid is off it at every shift: held there
        w = self.max_shift
        rows = np.clip(ij[..., 0], -w, self.rows - 1 + w) + self._pad
        cols = np.clip(ij[..., 1], -w, self.cols - 1 + w) + self._pad
        base = rows * self._stride + cols  # (T, N)
        offsets = shifts[:, 0] * self._stride + shifts[:, 1]  # (S,)
        out = np.empty((len(points), len(shifts)))
        chunk = max(1, 250_000 // max(1, base.shape[1] * len(shifts)))  # ~2 MB of lookups at a time
        for k in range(0, len(points), chunk):
            out[k:k + chunk] = self.values[base[k:k + chunk, None, :] + offsets[None, :, None]].sum(axis=2)
        return out


def _within(points_xy: np.ndarray, reach: float) -> np.ndarray:
    """The points ``(N, 2)`` within ``reach`` [m] of their sensor (the origin)."""
    return points_xy[np.einsum("ij,ij->i", points_xy, points_xy) <= reach * reach]


def _placed(points_xy: np.ndarray, xyt: np.ndarray) -> np.ndarray:
    """``(N, 2)`` sensor-frame points moved to the pose ``xyt``."""
    c, s = math.cos(xyt[2]), math.sin(xyt[2])
    return points_xy @ np.array([[c, s], [-s, c]]) + np.asarray(xyt[:2], dtype=np.float64)
