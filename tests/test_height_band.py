"""Obstacle slices of 3D scans for occupancy grids: ground estimate, height band, thinning."""

import numpy as np
import pytest

from submapslam.mapping.height_band import estimate_ground_z, obstacle_points


def _scene(sensor_height: float = 1.7, seed: int = 0) -> np.ndarray:
    """Sensor-frame points: rough ground, a wall at x = 5 m, a kerb 10 cm high, a canopy 4 m up."""
    rng = np.random.default_rng(seed)
    g = rng.uniform(-20, 20, size=(20000, 2))
    ground = np.c_[g, -sensor_height + rng.normal(0, 0.02, len(g))]
    wy, wz = rng.uniform(-3, 3, 3000), rng.uniform(-sensor_height, 0.8, 3000)
    wall = np.c_[np.full(3000, 5.0), wy, wz]
    kerb = np.c_[rng.uniform(-10, 10, 500), np.full(500, -4.0), np.full(500, -sensor_height + 0.1)]
    canopy = np.c_[rng.uniform(-2, 2, (500, 2)), np.full(500, 4.0 - sensor_height)]
    below = np.array([[1.0, 1.0, -sensor_height - 3.0]])  # one reflection below the ground
    return np.vstack([ground, wall, kerb, canopy, below])


def test_ground_is_estimated_from_the_nearby_heights():
    assert estimate_ground_z(_scene(1.7)) == pytest.approx(-1.7, abs=0.05)
    assert estimate_ground_z(_scene(0.5)) == pytest.approx(-0.5, abs=0.05)
    assert estimate_ground_z(np.array([[50.0, 0.0, -1.0]])) is None  # nothing near the sensor


def test_obstacle_points_keep_the_wall_and_drop_ground_kerb_and_canopy():
    pts = obstacle_points(_scene(1.7), cell=0.1)
    assert pts.dtype == np.float32 and len(pts) > 50
    assert np.allclose(pts[:, 0], 5.0)  # only the wall
    height = pts[:, 2] + 1.7
    assert height.min() >= 0.3 - 0.05 and height.max() <= 2.0 + 0.05
    cells = np.floor(pts[:, :2] / 0.1).astype(int)
    assert len(np.unique(cells, axis=0)) == len(pts)  # one point per grid cell
    # the band follows the sensor height: the same scene seen from 0.5 m up
    low = obstacle_points(_scene(0.5), cell=0.1)
    assert len(low) > 50 and np.allclose(low[:, 0], 5.0)


def test_band_limits_and_a_given_ground_height():
    scene = _scene(1.7)
    low = obstacle_points(scene, cell=0.1, min_above_ground=0.05, max_above_ground=0.2)
    assert np.any(np.isclose(low[:, 1], -4.0))  # the kerb, 10 cm above the ground
    # told the ground is 1 m below where it is, the real ground falls into the band: the given
    # height is used instead of the estimate
    wrong = obstacle_points(scene, cell=0.1, ground_z=-2.7, min_above_ground=0.3, max_above_ground=1.5)
    assert np.sum(np.abs(wrong[:, 0] - 5.0) > 1.0) > 1000
    assert obstacle_points(np.zeros((0, 3)), cell=0.1).shape == (0, 3)
