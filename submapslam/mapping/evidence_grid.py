"""Evidence (occupancy) grids in log-odds, and a global grid that forgets what moved.

Each submap gets a local grid in its anchor frame from its own scans (rays: free space along
the beam, an occupied cell at the hit). The global grid fuses the local grids through the
optimised anchors in time order; where a newer local grid sees a cell as *confidently free*,
an occupied cell of the global grid is cleared — people and moved boxes leave the map while
walls, which every submap sees occupied, stay. Planar (x, y) only.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..config import GridParams
from ..geometry import transform_points

if TYPE_CHECKING:
    from .tiled_grid import TiledLogOdds

#: ray points (cells along one scan's rays) traced at once: above this a scan's rays go in parts
RAY_POINTS_AT_ONCE = 250_000


def box_covering(points_xy: np.ndarray, resolution: float, margin: float) -> tuple[np.ndarray, tuple[int, int]]:
    """``(origin (2,) [m], (rows, cols))`` of a grid of ``resolution`` [m] cells covering
    ``(N, 2)`` points [m] plus ``margin`` [m]."""
    lo = points_xy.min(axis=0) - margin
    hi = points_xy.max(axis=0) + margin
    shape = np.ceil((hi - lo) / resolution).astype(int) + 1
    return lo, (int(shape[1]), int(shape[0]))


def cells_of(xy: np.ndarray, origin: np.ndarray, resolution: float,
             shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row, column and inside-mask of ``(N, 2)`` points [m] in a grid of ``shape`` ``(rows, cols)``
    cells of ``resolution`` [m] from ``origin`` [m]."""
    rc = np.floor((xy - origin) / resolution).astype(np.int64)
    inside = (rc[:, 0] >= 0) & (rc[:, 1] >= 0) & (rc[:, 0] < shape[1]) & (rc[:, 1] < shape[0])
    return rc[:, 1], rc[:, 0], inside


def logistic_in_place(negated: np.ndarray) -> np.ndarray:
    """Occupancy probabilities from *negated* log-odds ``-l``: ``1 / (1 + exp(-l))``, computed in
    ``negated``'s own array (returned)."""
    np.exp(negated, out=negated)
    negated += 1.0
    return np.reciprocal(negated, out=negated)


class EvidenceGrid:
    """A log-odds grid over a fixed extent; cell ``(r, c)`` covers
    ``x in [x0 + c*res, x0 + (c+1)*res)``, ``y in [y0 + r*res, ...)``."""

    def __init__(self, origin_xy: np.ndarray, shape: tuple[int, int], params: GridParams,
                 track_free_runs: bool = True) -> None:
        """``track_free_runs``: count each cell's free observations since its last hit (a local
        grid, for :func:`fuse_submap_grids`; the global grid does not need them)."""
        self.origin = np.asarray(origin_xy, dtype=np.float64)
        self.params = params
        self.logodds = np.zeros(shape, dtype=np.float32)
        # free observations of each cell since its last hit (saturating): what the cell is *now*
        self.free_run = np.zeros(shape, dtype=np.uint8) \
            if track_free_runs and params.recent_free_observations else None
        self._is_hit: np.ndarray | None = None  # scratch masks reused by integrate_scan
        self._is_free: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)`` cells."""
        return self.logodds.shape

    def cell_index(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Index of cells ``(rows, cols)`` into :meth:`values` (the interface
        :class:`~.tiled_grid.TiledLogOdds` shares)."""
        return rows * self.logodds.shape[1] + cols

    def values(self) -> np.ndarray:
        """The log-odds as one flat view, indexed by :meth:`cell_index`."""
        return self.logodds.reshape(-1)

    @classmethod
    def covering(cls, points_xy: np.ndarray, params: GridParams, margin: float = 1.0,
                 track_free_runs: bool = True) -> EvidenceGrid:
        """An empty grid covering ``(N, 2)`` points plus a margin [m]."""
        origin, shape = box_covering(points_xy, params.resolution, margin)
        return cls(origin, shape, params, track_free_runs)

    def cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Row, column and inside-mask of ``(N, 2)`` points."""
        return cells_of(xy, self.origin, self.params.resolution, self.logodds.shape)

    def integrate_scan(self, T_grid_sensor: np.ndarray, points: np.ndarray, carve_free: bool = True,
                       no_returns: np.ndarray | None = None) -> None:
        """Trace rays from the sensor to ``(N, 3)`` hits (sensor frame) into the grid.

        Free evidence is laid along each ray up to one cell short of the hit (and at most
        ``params.max_free_range`` metres); the hit cell gets occupied evidence. ``no_returns``
        ``(M, 3)``: ends of beams that returned nothing: free along them (at most
        ``max_free_range``), no hit.
        """
        hits = transform_points(T_grid_sensor, points)[:, :2]
        if no_returns is not None and len(no_returns) and carve_free:
            self._carve_no_returns(T_grid_sensor, np.asarray(no_returns, dtype=np.float64), hits)
        if len(points) == 0:
            return
        p = self.params
        flat = self.logodds.reshape(-1)
        width = self.logodds.shape[1]
        r, c, inside = self.cells(hits)
        hit_idx = r[inside] * width + c[inside]
        # ``a[idx] = a[idx] + v`` adds v once per distinct index even when idx repeats: each cell
        # counts once per scan without sorting (a scan traced in parts gathers them in a mask)
        if carve_free:
            origin = T_grid_sensor[:2, 3]
            vec = hits - origin
            lengths = np.linalg.norm(vec, axis=1)
            free_len = np.minimum(lengths - p.resolution, p.max_free_range)
            steps = np.maximum(0, np.floor(free_len / p.resolution).astype(int))
            o_r, o_c, o_in = self.cells(origin[None, :])
            # sensor and hits a cell inside the border: every point between them is inside
            within = bool(o_in[0] and inside.all() and min(r.min(), o_r[0]) >= 1 and min(c.min(), o_c[0]) >= 1
                          and max(r.max(), o_r[0]) < self.logodds.shape[0] - 1 and max(c.max(), o_c[0]) < width - 1)
            if steps.sum() <= RAY_POINTS_AT_ONCE:
                free_idx = self._free_index(origin, vec, lengths, steps, within)
            else:
                free_idx = self._free_index_in_parts(origin, vec, lengths, steps, within)
            self._add_free(free_idx, hit_idx)
        flat[hit_idx] = np.minimum(flat[hit_idx] + p.l_occ, p.l_max)
        if self.free_run is not None:
            self.free_run.reshape(-1)[hit_idx] = 0

    def _free_index(self, origin: np.ndarray, vec: np.ndarray, lengths: np.ndarray, steps: np.ndarray,
                    within: bool) -> np.ndarray:
        """Flat indices (int64, repeats allowed) of the cells ``steps (N,)`` points along the rays
        from ``origin (2,)`` along ``vec (N, 2)`` fall in (:meth:`_ray_cells`); ``within``: every one
        of them is inside the grid (no test)."""
        row, col = self._ray_cells(origin, vec, lengths, steps)
        if not within:
            return self._inside_index(row, col)
        row *= self.logodds.shape[1]
        row += col
        return row.astype(np.int64)

    def _free_index_in_parts(self, origin: np.ndarray, vec: np.ndarray, lengths: np.ndarray,
                             steps: np.ndarray, within: bool) -> np.ndarray:
        """:meth:`_free_index` without repeats, about :data:`RAY_POINTS_AT_ONCE` ray points at a
        time: a 64-ring scan's obstacle rays (up to 150 points each) reach 1.1 M ray points, 44 MB
        of temporaries at once. The cells are gathered in a scratch mask of the grid, so each
        counts once per scan, as the repeats do in :meth:`_add_free`."""
        if self._is_free is None:
            self._is_free = np.zeros(self.logodds.size, dtype=bool)
        ends = np.cumsum(steps)
        start = 0
        while start < len(steps):
            stop = max(int(np.searchsorted(ends, ends[start] - steps[start] + RAY_POINTS_AT_ONCE, side="right")),
                       start + 1)
            part = slice(start, stop)
            self._is_free[self._free_index(origin, vec[part], lengths[part], steps[part], within)] = True
            start = stop
        free_idx = np.flatnonzero(self._is_free)
        self._is_free[free_idx] = False
        return free_idx

    def _ray_cells(self, origin: np.ndarray, vec: np.ndarray, lengths: np.ndarray,
                   steps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows and columns (float64, whole numbers) of the points one cell apart along rays from
        ``origin (2,)`` along ``vec (N, 2)`` of ``lengths (N,)``: ``steps (N,)`` points a ray,
        from the origin on. The arithmetic of :meth:`cells` on ``origin + vec * k * res / length``,
        in place, column by column."""
        res = self.params.resolution
        ray = np.repeat(np.arange(len(steps)), steps)
        offsets = np.arange(int(steps.sum()), dtype=np.float64)  # whole numbers: exact as float64
        offsets -= np.repeat((np.cumsum(steps) - steps).astype(np.float64), steps)
        offsets *= res
        offsets /= lengths[ray]  # each point's fraction of its ray
        out = []
        for axis in (1, 0):  # y -> row, x -> column
            v = np.ascontiguousarray(vec[:, axis])[ray]
            v *= offsets
            v += origin[axis]
            v -= self.origin[axis]
            v /= res
            out.append(np.floor(v, out=v))
        return out[0], out[1]

    def _inside_index(self, row: np.ndarray, col: np.ndarray) -> np.ndarray:
        """Flat indices (int64) of the cells ``row``, ``col`` (float64 whole numbers) inside the grid."""
        height, width = self.logodds.shape
        ok = (col >= 0) & (row >= 0) & (col < width) & (row < height)
        return (row[ok] * width + col[ok]).astype(np.int64)

    def _add_free(self, free_idx: np.ndarray, hit_idx: np.ndarray) -> None:
        """Free evidence once in each cell of ``free_idx`` (repeats allowed) not among the scan's
        hit cells ``hit_idx``."""
        p = self.params
        flat = self.logodds.reshape(-1)
        if self._is_hit is None:
            self._is_hit = np.zeros(flat.shape, dtype=bool)
        self._is_hit[hit_idx] = True
        free_idx = free_idx[~self._is_hit[free_idx]]  # a hit cell is not also free
        self._is_hit[hit_idx] = False
        flat[free_idx] = np.maximum(flat[free_idx] + p.l_free, p.l_min)
        if self.free_run is not None:
            runs = self.free_run.reshape(-1)
            runs[free_idx] = np.minimum(runs[free_idx], 254) + 1

    def _carve_no_returns(self, T_grid_sensor: np.ndarray, no_returns: np.ndarray, hits: np.ndarray) -> None:
        """Free evidence along beams that returned nothing, up to ``max_free_range`` (clipped to
        the grid), sparing the cells ``hits (N, 2)`` of the same scan."""
        p = self.params
        ends = transform_points(T_grid_sensor, no_returns)[:, :2]
        origin = T_grid_sensor[:2, 3]
        vec = ends - origin
        lengths = np.linalg.norm(vec, axis=1)
        keep = lengths > 0
        vec, lengths = vec[keep], lengths[keep]
        steps = np.floor(np.minimum(lengths, p.max_free_range) / p.resolution).astype(int)
        if not len(steps) or steps.sum() == 0:
            return
        row, col = self._ray_cells(origin, vec, lengths, steps)
        hr, hc, h_in = self.cells(hits)
        self._add_free(self._inside_index(row, col), hr[h_in] * self.logodds.shape[1] + hc[h_in])

    def probabilities(self, consume: bool = False) -> np.ndarray:
        """Occupancy probability per cell, ``(rows, cols)`` float32 (the logistic of the log-odds).

        Computed in one array, in place: a city-sized grid (10 M cells) is 40 MB a copy, and the
        chained expression held three of them at the end of a run (the run's memory peak).
        ``consume``: computed in the log-odds' own array, which then holds the probabilities (for
        a grid that is done with: the 3.7 km KITTI 00 drive's 13 M cells held 52 MB of log-odds
        beside 52 MB of probabilities at the end of its run)."""
        return logistic_in_place(np.negative(self.logodds, out=self.logodds if consume else None))


def fuse_submap_grids(global_grid: EvidenceGrid | TiledLogOdds, local: EvidenceGrid, T_global_local: np.ndarray,
                      cleared_mask: np.ndarray | None = None, mark_where: np.ndarray | None = None) -> int:
    """Fuse a local grid into the global grid (dense, or :class:`~.tiled_grid.TiledLogOdds`);
    return how many occupied cells were cleared (and set them in ``cleared_mask``, a bool array of
    the global grid's shape, when given; only those also set in ``mark_where`` when that is given).

    Local cells are mapped through ``T_global_local`` by their centres. Confidently free local
    cells reset occupied global cells to the local (free) value; cells the local grid saw free
    ``recent_free_observations`` times since their last hit, with the 8 cells around them, become
    free whatever the global grid held; other evidence is added.
    """
    from scipy.ndimage import maximum_filter, minimum_filter

    p = global_grid.params
    # free "with high confidence": the cell and its whole neighbourhood are free, so pose noise
    # of a cell or two and grazing rays along walls never erase a wall
    neighbourhood_max = maximum_filter(local.logodds, size=2 * p.clear_margin_cells + 1)
    rows, cols = np.nonzero(local.logodds)
    if len(rows) == 0:
        return 0
    centres = local.origin + (np.stack([cols, rows], axis=1) + 0.5) * local.params.resolution
    xyz = np.zeros((len(centres), 3))
    xyz[:, :2] = centres
    r, c, inside = global_grid.cells(transform_points(T_global_local, xyz)[:, :2])
    values = local.logodds[rows, cols][inside]
    confident_free = neighbourhood_max[rows, cols][inside] < p.free_confidence
    r, c = r[inside], c[inside]
    at = global_grid.cell_index(r, c)
    g = global_grid.values()
    recent = np.zeros(len(r), dtype=bool)
    if local.free_run is not None and p.recent_free_observations:
        # the cell and its neighbours: a wall cell a grazing ray crossed after its last hit stays
        runs = minimum_filter(local.free_run, size=3)
        recent = runs[rows, cols][inside] >= p.recent_free_observations
    clear = (confident_free | recent) & (g[at] > p.occupied_threshold)
    g[at[clear]] = values[clear]
    if cleared_mask is not None:
        mark = clear if mark_where is None else clear & mark_where[r, c]
        cleared_mask[r[mark], c[mark]] = True
    rest = ~clear
    np.add.at(g, at[rest], values[rest])
    g[at[recent]] = np.minimum(g[at[recent]], p.free_confidence)  # free now, whatever the sum
    # only the cells this fuse touched can have left [l_min, l_max] (the rest were clipped before):
    # clipping the whole city-sized grid after every submap cost 1 s of a 3.7 km drive's fusion (13 M cells)
    g[at] = np.clip(g[at], p.l_min, p.l_max)
    return int(clear.sum())
