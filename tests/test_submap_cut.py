"""When a submap closes (``SubmapBuilder``): after ``max_distance`` of travel, and in 3D only once it
holds ``min_scans`` scans (a highway drive's 12 m were 5 scans, each submap's graph work for 5)."""

import numpy as np

from submapslam.config import SubmapConfig
from submapslam.submaps import MIN_SCANS_3D, SubmapBuilder


def _scans_per_submap(config: SubmapConfig, planar: bool, step_m: float, n: int = 120) -> list[int]:
    builder = SubmapBuilder(config, voxel_size=0.5, planar=planar)
    cloud = np.random.default_rng(0).uniform(-20, 20, (400, 3))
    if planar:
        cloud[:, 2] = 0.0
    sizes = []
    for k in range(n):
        T = np.eye(4)
        T[0, 3] = k * step_m
        submap = builder.add(k, T, cloud)
        if submap is not None:
            sizes.append(len(submap.scan_indices))
    return sizes


def test_a_fast_3d_drive_keeps_min_scans_in_a_submap_and_a_slow_one_cuts_by_travel():
    fast = _scans_per_submap(SubmapConfig(), planar=False, step_m=2.4)  # highway: 12 m in 5 scans
    assert fast and all(size == MIN_SCANS_3D for size in fast)  # its anchor (shared) and 9 steps: 21.6 m
    slow = _scans_per_submap(SubmapConfig(), planar=False, step_m=0.6)  # town: 12 m in 20 steps
    assert slow and all(size == 21 for size in slow)
    assert _scans_per_submap(SubmapConfig(min_scans=3), planar=False, step_m=2.4)[0] == 6  # 12 m first


def test_planar_submaps_cut_by_travel_alone():
    sizes = _scans_per_submap(SubmapConfig(), planar=True, step_m=2.4)
    assert sizes and all(size == 4 for size in sizes)  # 5 m: 3 steps of 2.4 m
