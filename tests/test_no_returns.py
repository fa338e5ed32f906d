"""Readings at the laser's maximum range are no-returns: free space up to the range, never walls.

An ACES-like log: the scanner writes 50.0 m for every beam that returned nothing (here those
through a doorway into an open hall). The reader finds that value in the data; the beams are not
registered and not in the map, and the grid marks free space along them.
"""

import numpy as np

from submapslam.api import run_log
from submapslam.geometry import transform_points
from submapslam.io.carmen import CarmenReader, detect_no_return_range
from submapslam.mapping.global_map import build_global_grid

from .planar_scenes import wall_ranges

NO_RETURN = 50.0
# a 10 x 8 m room, a 2 m doorway in its right wall (x = 5) and nothing beyond; a pillar and a
# recess so that the scans constrain every direction
WALLS = [(-5, -4, 5, -4), (5, -4, 5, -1), (5, 1, 5, 4), (5, 4, -5, 4), (-5, 4, -5, -4),
         (-1, 1, -0.5, 1), (-0.5, 1, -0.5, 1.5), (-0.5, 1.5, -1, 1.5), (-1, 1.5, -1, 1),
         (1, -4, 1, -3.2), (1, -3.2, 2, -3.2), (2, -3.2, 2, -4)]


def _ranges(x: float, y: float, th: float, beams: int = 181) -> np.ndarray:
    return np.round(wall_ranges(WALLS, (x, y, th), beams, no_return=NO_RETURN), 2)


def _write_log(path) -> None:
    lines = []
    for k in range(60):
        x, y, th = -3.0 + 0.08 * k, 0.2 * np.sin(k / 10), 0.1 * np.sin(k / 15)
        r = " ".join(f"{v:.2f}" for v in _ranges(x, y, th))
        t = 1000.0 + 0.2 * k
        lines.append(f"FLASER 181 {r} {x:.4f} {y:.4f} {th:.5f} {x:.4f} {y:.4f} {th:.5f} {t:.6f} host {t:.6f}")
    path.write_text("\n".join(lines) + "\n")


def test_the_no_return_value_is_found_in_the_data():
    rng = np.random.default_rng(0)
    real = rng.uniform(0.5, 30.0, 5000)
    assert detect_no_return_range(np.r_[real, np.full(300, 50.0)]) == 50.0
    assert detect_no_return_range(real) is None  # the largest reading once: a real distance
    assert detect_no_return_range(np.r_[real, np.full(3, 50.0)]) is None  # too rare to be the sensor's
    assert detect_no_return_range(np.full(180, 2.0)) is None  # one value only: nothing to tell by
    walls = np.r_[np.round(real, 2), np.full(200, 7.5)]  # a wall seen head-on 200 times, and 300 no-returns
    assert detect_no_return_range(np.r_[walls, np.full(300, 50.0)]) is None  # not 3x any real distance
    assert detect_no_return_range(np.r_[walls, np.full(700, 50.0)]) == 50.0


def test_max_range_beams_are_free_space_not_walls(tmp_path):
    log = tmp_path / "aces_like.clf"
    _write_log(log)
    reader = CarmenReader(log)
    scans = list(reader)
    assert reader.no_return_range == NO_RETURN
    assert all(np.linalg.norm(s.points, axis=1).max() < 20.0 for s in scans)  # no point at 50 m
    assert sum(len(s.no_returns) for s in scans) > 500  # the doorway's beams, kept as no-returns
    result, paths = run_log(log, tmp_path / "out")
    summary = (paths["summary.json"]).read_text()
    assert '"no_return_range_m": 50.0' in summary
    # the world frame is the first scan's (x = -3 in the log): the room spans x -2..8, y -4..4
    world = np.vstack([transform_points(T, p) for T, p in zip(result.submap_poses, result.submap_points)])
    assert world[:, 0].min() > -2.5 and world[:, 0].max() < 8.5 and np.abs(world[:, 1]).max() < 4.5  # the room only
    grid, _ = build_global_grid(result)
    logodds = grid.dense_logodds()
    height, width = logodds.shape
    assert width * grid.params.resolution < 25.0 and height * grid.params.resolution < 25.0  # the room's size
    # beyond the doorway (world x > 8): free where the grid reaches, never occupied
    r, c, inside = grid.cells(np.array([[8.6, 0.0], [9.0, 0.3]]))
    assert inside.all() and np.all(logodds[r, c] < 0)
    # the walls are still walls, and nothing occupied lies beyond the doorway
    occupied = np.argwhere(logodds > grid.params.occupied_threshold)
    xy = grid.origin + (occupied[:, ::-1] + 0.5) * grid.params.resolution
    assert len(xy) > 100 and xy[:, 0].max() < 8.6


def test_local_grids_made_from_jobs_carve_the_no_returns_as_the_grid_does(tmp_path):
    """A local grid made elsewhere (``batch``'s Ray actors take :func:`local_grid_jobs`) is the one
    :func:`build_global_grid` makes itself: the doorway's no-returns carved too."""
    from submapslam.mapping.global_map import grid_params, job_grid, local_grid, local_grid_jobs

    log = tmp_path / "aces_like.clf"
    _write_log(log)
    result, _ = run_log(log, None)
    params = grid_params(result)
    jobs = local_grid_jobs(result, range(result.n_submaps))
    assert any(job[3] for job in jobs)
    here, _ = build_global_grid(result, params)
    made, _ = build_global_grid(result, params, local_grids=[job_grid(job, params) for job in jobs])
    assert np.array_equal(made.dense_logodds(), here.dense_logodds())
    without, _ = build_global_grid(result, params, local_grids=[local_grid(p, s, params) for _, p, s, _ in jobs])
    assert not np.array_equal(without.dense_logodds(), here.dense_logodds())  # the no-returns' free space is there to lose


def test_a_saved_map_keeps_the_no_returns_and_gives_the_same_grid(tmp_path):
    """``OUT/map/`` (what ``run --map`` and ``batch`` extend) keeps each scan's no-returns: the
    loaded map's grid is the run's own, doorway included."""
    from submapslam.io.map_store import load_map, save_map

    log = tmp_path / "aces_like.clf"
    _write_log(log)
    result, _ = run_log(log, tmp_path / "out")
    loaded = load_map(tmp_path / "out" / "map").result
    assert [len(s) for s in loaded.submap_scan_no_returns] == [len(s) for s in result.submap_scan_no_returns]
    assert sum(len(e) for s in loaded.submap_scan_no_returns for e in s) > 500
    here, _ = build_global_grid(result)
    again, _ = build_global_grid(loaded)
    assert np.array_equal(again.dense_logodds(), here.dense_logodds())
    save_map(load_map(tmp_path / "out" / "map"), tmp_path / "copy")  # and saved again, the same bytes
    assert (tmp_path / "copy" / "submaps.npz").read_bytes() == (tmp_path / "out" / "map" / "submaps.npz").read_bytes()
