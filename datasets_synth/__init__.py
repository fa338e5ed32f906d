"""Deterministic synthetic worlds, ray-cast 2D/3D LiDAR, drifting odometry, real log formats.

    from datasets_synth import generate, WORLDS
    generate("rectangle", "out/rect", seed=0, laps=2)
"""

from .worlds import WORLDS, World
from .writer import generate

__all__ = ["WORLDS", "World", "generate"]
