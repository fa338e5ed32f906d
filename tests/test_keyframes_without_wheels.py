"""A spinning LiDAR at irregular keyframes without wheel odometry: KISS-ICP's adaptive threshold,
grown by the keyframes' poor predictions to ~2.3 m (7 m long correspondences), let a scan half on
new ground be pulled off a good guess (a 64-ring drive ended 0.63 m off). Where the threshold is
wider than a map voxel the odometry also registers at a voxel and keeps that result unless it puts
less of the scan on the local map (``Odometry._tight_or_wide``; the drive: 0.075 m, BENCHMARKS.md).
The registration is stood in for here: the rule, not KISS-ICP, is under test."""

from __future__ import annotations

import numpy as np

from submapslam.config import OdometryConfig
from submapslam.odometry import Odometry


class _Registration:
    """KISS-ICP's registration stood in: the ``wide`` pose when the correspondences reach beyond
    ``reach`` [m], else ``tight``; counts its calls."""

    def __init__(self, wide: np.ndarray, tight: np.ndarray, reach: float) -> None:
        self.wide, self.tight, self.reach, self.calls = wide, tight, reach, 0

    def align_points_to_map(self, *, points, voxel_map, initial_guess, max_correspondance_distance, kernel):
        self.calls += 1
        return (self.wide if max_correspondance_distance > self.reach else self.tight).copy()


def _street_odometry(threshold_m: float) -> tuple[Odometry, np.ndarray]:
    """A 3D odometry whose local map holds a street (two facades and a wall across it) and
    whose adaptive threshold is ``threshold_m``; and a scan of that street ``(N, 3)`` at the origin."""
    rng = np.random.default_rng(0)
    x, z = np.meshgrid(np.arange(-20.0, 20.0, 0.3), np.arange(0.5, 6.0, 0.3))
    facades = [np.c_[x.ravel(), np.full(x.size, y), z.ravel() - 1.7] for y in (-6.0, 6.0)]
    y, z2 = np.meshgrid(np.arange(-6.0, 6.0, 0.3), np.arange(0.5, 6.0, 0.3))
    across = np.c_[np.full(y.size, 12.0), y.ravel(), z2.ravel() - 1.7]
    street = np.vstack(facades + [across]) + rng.normal(0.0, 0.02, (sum(len(f) for f in facades) + len(across), 3))
    odometry = Odometry(OdometryConfig(), planar=False)
    odometry._local_map.update(street, np.eye(4))
    odometry._scans_in_map = 100  # a grown map: no young-map registration
    odometry._threshold.get_threshold = lambda: threshold_m
    return odometry, street


def _shifted(x_m: float) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = x_m
    return pose


def test_a_wide_threshold_result_gives_way_to_a_tight_one_that_fits_the_map_better():
    """Wide: 1.5 m along the street (the scan's wall across lands off the map's); tight: in place."""
    odometry, street = _street_odometry(threshold_m=2.3)
    odometry._registration = _Registration(wide=_shifted(1.5), tight=np.eye(4), reach=3.0 * odometry.voxel_size)
    pose = odometry._align_3d(street, np.eye(4))
    assert np.allclose(pose, np.eye(4))
    assert (odometry.tight_tried, odometry.tight_won) == (1, 1)


def test_a_tight_result_that_fits_the_map_worse_gives_way_to_the_wide_one():
    """A guess far off: the tight registration stays 1.5 m away, the wide one reaches the map."""
    odometry, street = _street_odometry(threshold_m=2.3)
    odometry._registration = _Registration(wide=np.eye(4), tight=_shifted(1.5), reach=3.0 * odometry.voxel_size)
    assert np.allclose(odometry._align_3d(street, _shifted(2.0)), np.eye(4))
    assert (odometry.tight_tried, odometry.tight_won) == (1, 0)


def test_a_threshold_within_a_voxel_registers_once():
    """With wheels the threshold stays near 0.75 m, under the 0.8 m voxel: one registration, as before."""
    odometry, street = _street_odometry(threshold_m=0.75)
    odometry._registration = registration = _Registration(wide=np.eye(4), tight=_shifted(1.5), reach=0.0)
    odometry._align_3d(street, np.eye(4))
    assert registration.calls == 1 and odometry.tight_tried == 0
