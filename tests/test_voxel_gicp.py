"""Voxelised GICP scan-to-map registration (narrow-field sensors) and the auto choice of registration."""

from __future__ import annotations

import numpy as np

from submapslam.config import OdometryConfig
from submapslam.geometry import inverse
from submapslam.odometry import odometry_voxels, resolve_registration
from submapslam.registration.voxel_gicp import VoxelGicpTracker, azimuth_coverage_deg
from submapslam.scan import Scan


def _rot_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def _room(rng: np.random.Generator, n: int = 6000) -> np.ndarray:
    """``(n, 3)`` points on the walls, floor and two boxes of a 16 x 10 x 3 m room [m]."""
    pts = []
    for _ in range(n):
        face = rng.integers(0, 7)
        u, v = rng.uniform(0, 1, 2)
        if face == 0:
            pts.append((8.0, -5 + 10 * u, 3 * v))
        elif face == 1:
            pts.append((-8.0, -5 + 10 * u, 3 * v))
        elif face == 2:
            pts.append((-8 + 16 * u, 5.0, 3 * v))
        elif face == 3:
            pts.append((-8 + 16 * u, -5.0, 3 * v))
        elif face == 4:
            pts.append((-8 + 16 * u, -5 + 10 * v, 0.0))
        elif face == 5:
            pts.append((3.0, 1 + 1.5 * u, 1.2 * v))
        else:
            pts.append((-2 + 1.0 * u, -3.0, 2.0 * v))
    return np.asarray(pts) + rng.normal(0, 0.01, (n, 3))


def _narrow_view(points_world: np.ndarray, T_world_sensor: np.ndarray, half_fov_deg: float = 35.0) -> np.ndarray:
    """The points a sensor at ``T_world_sensor`` sees within +-``half_fov_deg`` of its x axis, in its frame."""
    local = (points_world - T_world_sensor[:3, 3]) @ T_world_sensor[:3, :3]
    azimuth = np.degrees(np.arctan2(local[:, 1], local[:, 0]))
    return local[np.abs(azimuth) < half_fov_deg]


def test_azimuth_coverage_tells_a_narrow_field_from_a_spinning_sensor():
    rng = np.random.default_rng(0)
    room = _room(rng)
    spinning = room - np.array([0.0, 0.0, 1.5])
    narrow = _narrow_view(room, np.eye(4))
    assert azimuth_coverage_deg(spinning) >= 330.0
    assert 60.0 <= azimuth_coverage_deg(narrow) <= 90.0


def test_auto_registration_resolves_from_the_first_scan():
    rng = np.random.default_rng(1)
    room = _room(rng)
    auto = OdometryConfig()
    narrow = Scan(index=0, timestamp=0.0, points=_narrow_view(room, np.eye(4)))
    spinning = Scan(index=0, timestamp=0.0, points=room - np.array([0.0, 0.0, 1.5]))
    assert resolve_registration(auto, narrow).registration == "voxel_gicp"
    assert resolve_registration(auto, spinning).registration == "kiss_icp"
    # an explicit choice is kept, whatever the scan
    assert resolve_registration(OdometryConfig(registration="kiss_icp"), narrow).registration == "kiss_icp"
    # the map voxel follows the resolved registration
    resolved = resolve_registration(auto, narrow)
    assert odometry_voxels(resolved, planar=False) == (0.5, 0.25)
    assert odometry_voxels(resolve_registration(auto, spinning), planar=False) == (0.8, 0.4)


def test_a_turn_the_prediction_did_not_foresee_is_found_from_the_no_motion_guess():
    """The sensor turns 14 deg and moves 0.3 m while the prediction says it turned 14 deg the
    other way: the coarse-to-fine alignment from the no-motion guess finds the true pose."""
    rng = np.random.default_rng(2)
    room = _room(rng, 12000)
    tracker = VoxelGicpTracker()
    T0 = np.eye(4)
    T0[:3, 3] = (-4.0, 0.0, 1.5)
    first = tracker.prepare(_narrow_view(room, T0, half_fov_deg=60.0))
    tracker.insert(first, T0)
    truth = T0 @ _rot_z(14.0)
    truth[:3, 3] += (0.3, 0.1, 0.0)
    scan = tracker.prepare(_narrow_view(room, truth, half_fov_deg=60.0))
    wrong_prediction = T0 @ _rot_z(-14.0)
    pose, inliers = tracker.align(scan, [wrong_prediction, T0])
    error = inverse(truth) @ pose
    assert np.linalg.norm(error[:3, 3]) < 0.05
    assert np.degrees(np.arccos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1))) < 0.5
    assert inliers > 0.8 * scan.size()
