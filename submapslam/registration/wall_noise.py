"""How far a 2D laser's points scatter across the walls they hit, measured from its own scans.

A scanner's range noise differs by an order of magnitude between models (a SICK LMS about 1 cm,
cheaper scanners 3 cm and more). The planar odometry's line test (:func:`.point_to_line.line_normals`)
has to allow for it: on a scanner three times noisier than the logs it was written on, most wall
points lose their line normal, the point-to-line refinement has little left to hold on to, and
the odometry drifts (FR079 with 3 cm of range noise: 5.4 m instead of 0.9 m).

The measure needs no map: along a scan (points in bearing order) each point's distance from the chord of
its two neighbours is, on a wall, the noise across that wall (variance 1.5x a point's, the
chord's ends adding half each). The median of those distances is blind to the corners and edges
among them. It reads about 0.6x a Gaussian range noise's sigma (beams meet walls obliquely, so
the noise across the wall is smaller than along the beam): over whole logs 0.005 m on Intel,
0.006 m on FR079, 0.010 m on MIT CSAIL (up to 0.012 m along the way); 0.018-0.021 m with 3 cm of
range noise added, 0.022-0.030 m with 5 cm (the chord test loses the noisiest points).
"""

from __future__ import annotations

import math

import numpy as np

#: [m] neighbours further apart than this (a gap between two objects) give no reading
MAX_CHORD_M = 0.5
#: Gaussian scale of a median absolute deviation
MAD_TO_SIGMA = 1.0 / 0.6745
#: [m] the figure is held to this: more is no scanner's noise (points of several sweeps, say)
MAX_WALL_NOISE_M = 0.05


def chord_distances(points_xy: np.ndarray) -> np.ndarray:
    """Signed distances [m] ``(M,)`` of each inner point of a scan ``(N, 2)`` (sensor or robot frame)
    from the chord through its two neighbours in bearing, where those lie within :data:`MAX_CHORD_M`.
    The points are taken in bearing order (a scanner's beam order, whatever order they came in)."""
    points_xy = points_xy[np.isfinite(points_xy).all(axis=1)]
    if len(points_xy) < 3:
        return np.zeros(0)
    points_xy = points_xy[np.argsort(np.arctan2(points_xy[:, 1], points_xy[:, 0]), kind="stable")]
    before, mid, after = points_xy[:-2], points_xy[1:-1], points_xy[2:]
    chord = after - before
    length = np.hypot(chord[:, 0], chord[:, 1])
    ok = (length > 1e-6) & (length < MAX_CHORD_M)
    normal = np.stack([-chord[ok, 1], chord[ok, 0]], axis=1) / length[ok, None]
    return np.einsum("ij,ij->i", mid[ok] - 0.5 * (before[ok] + after[ok]), normal)


class WallNoise:
    """The scatter across walls over a log's planar scans so far: a running robust figure (the
    median of the measured scans' chord distances, kept as a histogram of 0.1 mm bins), so that a
    run and its resumed replay, which see the same scans, use the same figures. The first
    ``first_scans`` scans are all measured, then every ``then_every``-th (36 us a scan measured)."""

    BIN_M = 1e-4  # [m] histogram bin
    BINS = 1000  # up to 0.1 m; larger distances (corners, edges) count in the last bin

    def __init__(self, first_scans: int = 20, then_every: int = 10) -> None:
        self.first_scans, self.then_every = first_scans, then_every
        self._scans = 0
        self._counts = np.zeros(self.BINS, dtype=np.int64)
        self.sigma_m = 0.0  # [m] 0 until a scan gave a reading

    def add(self, points_xy: np.ndarray) -> None:
        """Offer a scan's points ``(N, 2)`` (sensor frame) to the figure."""
        self._scans += 1
        if self._scans > self.first_scans and self._scans % self.then_every:
            return
        d = np.abs(chord_distances(points_xy))
        if len(d) == 0:
            return
        self._counts += np.bincount(np.minimum((d / self.BIN_M).astype(np.int64), self.BINS - 1),
                                    minlength=self.BINS)
        cumulative = np.cumsum(self._counts)
        median = (np.searchsorted(cumulative, 0.5 * cumulative[-1]) + 0.5) * self.BIN_M
        self.sigma_m = min(median * MAD_TO_SIGMA / math.sqrt(1.5), MAX_WALL_NOISE_M)
