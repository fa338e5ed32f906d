"""A global log-odds grid stored in square tiles, only where a submap wrote a cell.

A drive's global grid spans the bounding box of its path, and most of that box no scan ever saw:
along the diagonal 1.4 km of KITTI 01's highway the box is 32 M cells (121 MB of float32), of which
648 tiles of 64 x 64 cells hold anything (10 MB). The dense box grows with the square of the
drive's extent; the tiles grow with the area the scans cover. Cells in no tile read 0 (log-odds
of "unknown"). Same cell convention as :class:`~submapslam.mapping.evidence_grid.EvidenceGrid`:
cell ``(r, c)`` covers ``x in [x0 + c*res, x0 + (c+1)*res)``, ``y in [y0 + r*res, ...)``.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from ..config import GridParams
from .evidence_grid import box_covering, cells_of, logistic_in_place

#: cells per side of a tile (64: 12.8 m at 0.2 m, 3.2 m at 0.05 m)
TILE_CELLS = 64


class TiledLogOdds:
    """Log-odds over ``shape`` ``(rows, cols)`` cells from ``origin_xy`` [m], in tiles of
    ``tile`` x ``tile`` cells allocated as cells are indexed for writing (:meth:`cell_index`).
    :meth:`cell_index` and :meth:`values` are :class:`EvidenceGrid`'s too, so
    :func:`~submapslam.mapping.evidence_grid.fuse_submap_grids` fuses into either."""

    def __init__(self, origin_xy: np.ndarray, shape: tuple[int, int], params: GridParams,
                 tile: int = TILE_CELLS) -> None:
        self.origin = np.asarray(origin_xy, dtype=np.float64)
        self.params = params
        self.shape = (int(shape[0]), int(shape[1]))
        self.tile = int(tile)
        tile_rows, tile_cols = -(-self.shape[0] // self.tile), -(-self.shape[1] // self.tile)
        self._slot = np.full((tile_rows, tile_cols), -1, dtype=np.int32)  # tile -> its index in _tiles
        self._tiles = np.zeros((0, self.tile, self.tile), dtype=np.float32)
        self._used = 0

    @classmethod
    def covering(cls, points_xy: np.ndarray, params: GridParams, margin: float = 1.0) -> TiledLogOdds:
        """An empty grid covering ``(N, 2)`` points [m] plus a margin [m] (as ``EvidenceGrid.covering``)."""
        origin, shape = box_covering(points_xy, params.resolution, margin)
        return cls(origin, shape, params)

    @property
    def tiles(self) -> int:
        """Tiles allocated so far."""
        return self._used

    def cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Row, column and inside-mask of ``(N, 2)`` points [m]."""
        return cells_of(xy, self.origin, self.params.resolution, self.shape)

    def cell_index(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Index of cells ``(rows, cols)`` (int64, inside the grid) into :meth:`values`, the tiles
        they lie in allocated first (the interface :class:`~submapslam.mapping.evidence_grid.EvidenceGrid`
        shares)."""
        t = self.tile
        tile_rows, tile_cols = rows // t, cols // t
        self._allocate(tile_rows * self._slot.shape[1] + tile_cols)
        slot = self._slot[tile_rows, tile_cols].astype(np.int64)
        return (slot * t + rows % t) * t + cols % t

    def _allocate(self, tile_keys: np.ndarray) -> None:
        """Allocate the tiles of flat tile indices ``tile_keys`` that have none yet."""
        t = self.tile
        wanted = np.zeros(self._slot.size, dtype=bool)
        wanted[tile_keys] = True
        missing = np.flatnonzero(wanted & (self._slot.ravel() < 0))
        if not len(missing):
            return
        needed = self._used + len(missing)
        if needed > len(self._tiles):  # grown by a quarter at least: few copies over a drive
            grown = np.zeros((max(needed, len(self._tiles) + len(self._tiles) // 4), t, t), dtype=np.float32)
            grown[:self._used] = self._tiles[:self._used]
            self._tiles = grown
        self._slot.ravel()[missing] = np.arange(self._used, needed, dtype=np.int32)
        self._used = needed

    def values(self) -> np.ndarray:
        """The tiles' log-odds as one flat float32 view, indexed by :meth:`cell_index` (valid
        until the next allocation)."""
        return self._tiles.reshape(-1)

    def read(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Log-odds (float32) of cells ``(rows, cols)``; 0 in cells no tile holds (nothing allocated)."""
        t = self.tile
        slot = self._slot[rows // t, cols // t]
        out = np.zeros(len(slot), dtype=np.float32)
        held = slot >= 0
        out[held] = self._tiles[slot[held], rows[held] % t, cols[held] % t]
        return out

    def logodds_rows(self, start: int, stop: int) -> np.ndarray:
        """Dense ``(stop - start, cols)`` float32 log-odds of rows ``start..stop-1``."""
        t = self.tile
        out = np.zeros((stop - start, self.shape[1]), dtype=np.float32)
        for tile_row in range(start // t, -(-stop // t)):
            r0, r1 = max(start, tile_row * t), min(stop, (tile_row + 1) * t)
            for tile_col in np.flatnonzero(self._slot[tile_row] >= 0):
                c0, c1 = tile_col * t, min(self.shape[1], (tile_col + 1) * t)
                block = self._tiles[self._slot[tile_row, tile_col]]
                out[r0 - start:r1 - start, c0:c1] = block[r0 - tile_row * t:r1 - tile_row * t, :c1 - c0]
        return out

    def dense_logodds(self) -> np.ndarray:
        """The whole ``(rows, cols)`` float32 log-odds, dense (a new array: as large as the box)."""
        return self.logodds_rows(0, self.shape[0])

    def probability_rows(self, start: int, stop: int) -> np.ndarray:
        """Occupancy probability (float32, the logistic of the log-odds, computed as
        ``EvidenceGrid.probabilities``) of rows ``start..stop-1``, ``(stop - start, cols)``."""
        return logistic_in_place(np.negative(self.logodds_rows(start, stop)))

    def probability_bands(self, band: int | None = None) -> Iterator[tuple[int, np.ndarray]]:
        """``(first row, probabilities)`` of consecutive bands of ``band`` rows (default: a tile's),
        from the last rows (highest y) down: an image's top first, one band in memory at a time."""
        band = band or self.tile
        for stop in range(self.shape[0], 0, -band):
            start = max(0, stop - band)
            yield start, self.probability_rows(start, stop)

    def probabilities(self) -> np.ndarray:
        """The whole grid's ``(rows, cols)`` float32 probabilities, dense (what the bands hold together)."""
        return self.probability_rows(0, self.shape[0])
