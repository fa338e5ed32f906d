"""A closed 3D submap's cloud handed to the spill file: the same array back on every read, set
again in memory, pickled with its points."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np

from submapslam.mapping.scan_spill import ScanSpill
from submapslam.submaps import Submap, compact_points


def _submap(points: np.ndarray) -> Submap:
    return Submap(id=3, scan_indices=[7, 8], T_odom_anchor=np.eye(4), T_anchor_scans=np.tile(np.eye(4), (2, 1, 1)),
                  points=points, distance=12.0, planar=False)


def test_points_read_back_from_the_spill_are_the_same_array():
    points = compact_points(np.random.default_rng(0).uniform(-50, 50, (500, 3)))
    submap = _submap(points.copy())
    cloud = ScanSpill().put([submap.points])
    submap.keep_points_elsewhere(lambda: cloud[0])
    assert submap.__dict__["_points"] is None  # no longer held in memory
    back = submap.points
    assert back.dtype == points.dtype and np.array_equal(back, points)
    assert dataclasses.replace(submap, id=4).points.tobytes() == points.tobytes()
    restored = pickle.loads(pickle.dumps(submap))
    assert np.array_equal(restored.points, points) and restored.id == 3


def test_setting_points_again_keeps_them_in_memory():
    submap = _submap(np.zeros((4, 3)))
    submap.keep_points_elsewhere(lambda: np.ones((4, 3)))
    assert submap.points.sum() == 12
    submap.points = np.full((2, 3), 5.0)
    assert submap.__dict__["_read_points"] is None and submap.points.shape == (2, 3)
