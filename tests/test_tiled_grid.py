"""The tiled global grid: the dense grid's log-odds in tiles only where submaps wrote."""

import numpy as np

from submapslam.geometry import se2_to_matrix
from submapslam.io.grid import read_pgm, write_pgm_yaml
from submapslam.mapping.evidence_grid import EvidenceGrid, GridParams, fuse_submap_grids
from submapslam.mapping.tiled_grid import TiledLogOdds

from .test_evidence_grid import local


def _fused(grid, params):
    """Two rooms far apart fused into ``grid``, the second rotated (its cells land on repeated
    and tile-straddling global cells), a person leaving the first between two passes."""
    person = (2.0, 0.0, 0.25)
    scans = [(-2.0, 0.0), (-2.0, 0.3), (-2.0, -0.3)] * 2
    before, after = local(scans, person, params), local(scans, None, params)
    moved = se2_to_matrix(40.0, 25.0, 0.7)
    cleared = 0
    for submap, T in ((before, np.eye(4)), (after, np.eye(4)), (before, moved), (after, moved)):
        cleared += fuse_submap_grids(grid, submap, T)
    return cleared


def test_tiled_grid_fuses_to_the_dense_grids_numbers_and_holds_only_the_tiles_written():
    params = GridParams(resolution=0.05, free_scan_stride=1)
    corners = np.array([[-8.0, -8.0], [52.0, 37.0]])
    dense = EvidenceGrid.covering(corners, params, track_free_runs=False)
    tiled = TiledLogOdds.covering(corners, params)
    assert tiled.shape == dense.shape and np.array_equal(tiled.origin, dense.origin)
    cleared_dense, cleared_tiled = _fused(dense, params), _fused(tiled, params)
    assert cleared_tiled == cleared_dense > 0  # the person left: the same cells cleared
    np.testing.assert_array_equal(tiled.dense_logodds(), dense.logodds)
    np.testing.assert_array_equal(tiled.probabilities(), dense.probabilities())
    total_tiles = -(-dense.shape[0] // tiled.tile) * -(-dense.shape[1] // tiled.tile)
    assert 0 < tiled.tiles < total_tiles / 3  # two rooms in a 60 x 45 m box
    r, c, _ = tiled.cells(np.array([[20.0, -6.0]]))  # between the rooms: never written
    assert tiled.read(r, c)[0] == 0.0 and tiled._slot[r[0] // tiled.tile, c[0] // tiled.tile] == -1


def test_tiled_grid_bands_write_the_dense_grids_pgm(tmp_path):
    params = GridParams(resolution=0.05, free_scan_stride=1)
    corners = np.array([[-8.0, -8.0], [52.0, 37.0]])
    dense = EvidenceGrid.covering(corners, params, track_free_runs=False)
    tiled = TiledLogOdds.covering(corners, params)
    _fused(dense, params), _fused(tiled, params)
    bands = list(tiled.probability_bands(band=50))
    assert [start for start, _ in bands][:2] == [tiled.shape[0] - 50, tiled.shape[0] - 100]  # top of the image first
    pgm_dense, yaml_dense = write_pgm_yaml(tmp_path / "dense", dense.probabilities(), dense.origin, 0.05)
    pgm_tiled, yaml_tiled = write_pgm_yaml(tmp_path / "tiled", tiled, tiled.origin, 0.05)
    assert pgm_tiled.read_bytes() == pgm_dense.read_bytes()
    assert yaml_tiled.read_text().replace("tiled", "dense") == yaml_dense.read_text()
    assert read_pgm(pgm_tiled).shape == dense.shape


def test_tiles_grow_as_cells_are_indexed_and_keep_what_they_held():
    params = GridParams(resolution=0.1)
    grid = TiledLogOdds(np.zeros(2), (1000, 1000), params, tile=16)
    rows, cols = np.array([0, 15, 16, 999]), np.array([0, 15, 16, 999])
    at = grid.cell_index(rows, cols)  # allocates: values() after it
    np.add.at(grid.values(), at, np.array([1.0, 2.0, 3.0, 4.0], dtype=np.float32))
    assert grid.tiles == 3  # (0, 0) and (15, 15) share a tile
    for k in range(200):  # many more tiles: the store grows, earlier values stay
        at = grid.cell_index(np.array([k * 5]), np.array([500]))
        grid.values()[at] = 0.5
    np.testing.assert_array_equal(grid.read(rows, cols), [1.0, 2.0, 3.0, 4.0])
    assert grid.read(np.array([995]), np.array([500]))[0] == 0.5
    assert grid.read(np.array([3]), np.array([900]))[0] == 0.0 and grid.tiles == 3 + 63  # rows 0-995 of column 500
