"""Deterministic synthetic worlds, ray-cast 2D/3D LiDAR, drifting odometry, real log formats.

    from datasets_synth import generate, WORLDS
    generate("rectangle", "out/rect", seed=0, laps=2)
    generate_kitti_drive("kitti_gt/00.txt.xz", "out/kitti00_16", rings=16)  # a city along a real path
"""

from .city import generate_kitti_drive
from .worlds import WORLDS, World
from .writer import generate

__all__ = ["WORLDS", "World", "generate", "generate_kitti_drive"]
