"""A planar (2D laser) scan's odometry pose checked against the scan just before it.

Registered to the map of the last scans from the wheels' guess, a scan can end in a wrong
minimum when the step between scans is large (a log recorded at a low scan rate, a fast turn):
the wheels miss part of a turn the scans show (FR079 at a third of its rate: wheels -3 deg where
the scans turned +15), ICP from there stays near them, and once one scan is off, the map of the
last scans holds it, so the next scans fit that error better than the truth. The scan before
the new one is consistent with itself whatever the map holds. So a pose that fits the map poorly
is checked here: the new scan is matched to the previous one by an exhaustive correlative
search around the predicted step (:func:`~submapslam.registration.planar.match_planar`, +-1 m,
+-45 deg), that pose is refined against the map as usual (by the caller), and it is preferred
when it puts clearly more of the scan on the previous scan's points.

Frames: points ``(N, 2)`` or ``(N, 3)`` (z ignored) in each scan's sensor frame; poses ``(x, y,
yaw)`` in the odometry frame [m, rad]; ``T_previous_new`` ``(4, 4)``.
"""

from __future__ import annotations

import math

import numpy as np

from ..geometry import matrix_to_se2, se2_to_matrix
from .kdtree2d import KdTree2D


class PreviousScan:
    """The scan before the one being registered, placed in the odometry frame.

    ``window_m`` / ``yaw_window_deg``: half widths of the correlative search around the predicted
    step; ``min_match_fitness``: the search's own fitness (share of the scan within its inlier
    distance of the previous scan) below which it proposes nothing; ``distance`` [m]: a point on
    the previous scan's points for :meth:`share`; ``margin`` / ``min_share``: a candidate is
    preferred when its share beats the registered pose's by ``margin`` and is at least
    ``min_share``. The defaults were chosen on the three real CARMEN logs at their full rate and
    at a half and a third of it (BENCHMARKS.md: of 2,940 checked scans, the candidate taken by
    these thresholds was the better pose against the reference in 117 of 137).
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

    def share(self, points_xy: np.ndarray, xyt: np.ndarray) -> float:
        """Share of ``points_xy`` placed at ``xyt`` within ``distance`` of this scan's points."""
        if len(points_xy) == 0 or len(self.points) == 0:
            return 0.0
        if self._tree is None:
            self._tree = KdTree2D(_placed(self.points, self.xyt))
        d, _ = self._tree.query(_placed(np.asarray(points_xy, dtype=np.float64)[:, :2], xyt),
                                distance_upper_bound=self.distance)
        return float(np.count_nonzero(d <= self.distance)) / len(points_xy)

    def candidate(self, points_xy: np.ndarray, T_previous_new: np.ndarray) -> np.ndarray | None:
        """The new scan's odometry pose ``(3,)`` by matching it to this scan from the predicted
        step ``T_previous_new``; None when the match's fitness is below ``min_match_fitness``."""
        # scipy's FFT and image filters: loaded by the first check, not by every planar odometry process
        from .planar import match_planar

        if len(points_xy) < 20 or len(self.points) < 20:
            return None
        pts = np.asarray(points_xy, dtype=np.float64)
        match = match_planar(pts, self.points, initial_guess=T_previous_new, window=self.window_m,
                             yaw_window=self.yaw_window)
        if match.fitness < self.min_match_fitness:
            return None
        return matrix_to_se2(se2_to_matrix(*self.xyt) @ match.T)

    def prefers(self, points_xy: np.ndarray, candidate_xyt: np.ndarray, registered_xyt: np.ndarray) -> bool:
        """Whether ``candidate_xyt`` puts clearly more of the scan on this scan's points than
        ``registered_xyt`` does (:meth:`share`, ``margin``, ``min_share``)."""
        candidate = self.share(points_xy, candidate_xyt)
        return candidate >= self.min_share and candidate > self.share(points_xy, registered_xyt) + self.margin


def _placed(points_xy: np.ndarray, xyt: np.ndarray) -> np.ndarray:
    """``(N, 2)`` sensor-frame points moved to the pose ``xyt``."""
    c, s = math.cos(xyt[2]), math.sin(xyt[2])
    return points_xy @ np.array([[c, s], [-s, c]]) + np.asarray(xyt[:2], dtype=np.float64)
