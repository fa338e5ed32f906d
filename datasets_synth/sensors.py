"""Ray-cast range sensors on open3d's ``RaycastingScene``: a 2D laser and a spinning 3D LiDAR.

Rays are cast in the world from the sensor pose; hits are returned in the SENSOR frame as
range x unit direction, with Gaussian range noise, random dropouts and a maximum range.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Laser2D:
    """A planar laser: ``beams`` over ``fov_deg`` starting at ``-fov/2`` (CARMEN: -90 deg)."""

    beams: int = 361
    fov_deg: float = 180.0
    max_range: float = 30.0
    range_noise: float = 0.01
    dropout: float = 0.01
    mount_height: float = 0.3  # height of the scan plane above the floor [m]

    def angles(self) -> np.ndarray:
        fov = np.deg2rad(self.fov_deg)
        if self.fov_deg >= 360.0:
            return -np.pi + np.arange(self.beams) * 2 * np.pi / self.beams
        return -fov / 2 + np.arange(self.beams) * fov / (self.beams - 1)

    def directions(self) -> np.ndarray:
        a = self.angles()
        return np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)


@dataclass
class Lidar3D:
    """A spinning LiDAR with ``rings`` between ``fov_down``..``fov_up`` degrees and ``columns`` azimuths."""

    rings: int = 32
    fov_up_deg: float = 15.0
    fov_down_deg: float = -25.0
    columns: int = 900
    max_range: float = 80.0
    range_noise: float = 0.02
    dropout: float = 0.02
    mount_height: float = 1.7

    def directions(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit ray directions ``(R*C, 3)`` and per-ray sweep times in [0, 1]."""
        elev = np.deg2rad(np.linspace(self.fov_down_deg, self.fov_up_deg, self.rings))
        az = -np.pi + np.arange(self.columns) * 2 * np.pi / self.columns
        E, A = np.meshgrid(elev, az, indexing="ij")
        d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)
        times = ((A + np.pi) / (2 * np.pi)).reshape(-1)
        return d, times

    @classmethod
    def preset(cls, rings: int, **overrides) -> Lidar3D:
        """A spinning sensor: ``rings`` 16 (VLP-16), 64 (HDL-64E) or 128 (OS1-128), at KITTI's 1.73 m
        mount height.

        VLP-16: -15..+15 deg, 1800 columns, 4 cm range noise, 100 m. HDL-64E: -24.8..+2 deg,
        1800 columns, 2 cm noise, 120 m. OS1-128 like: -22.5..+22.5 deg, 1024 columns, 3 cm
        noise, 120 m. Rings are evenly spaced in elevation (the real HDL-64E's are not quite).
        ``overrides`` replace any field.
        """
        if rings not in LIDAR_PRESETS:
            raise ValueError(f"no LiDAR preset with {rings} rings; use {' or '.join(map(str, LIDAR_PRESETS))}")
        return cls(**{**LIDAR_PRESETS[rings], **overrides})


LIDAR_PRESETS: dict[int, dict] = {
    16: {"rings": 16, "fov_up_deg": 15.0, "fov_down_deg": -15.0, "columns": 1800, "max_range": 100.0,
         "range_noise": 0.04, "dropout": 0.01, "mount_height": 1.73},
    64: {"rings": 64, "fov_up_deg": 2.0, "fov_down_deg": -24.8, "columns": 1800, "max_range": 120.0,
         "range_noise": 0.02, "dropout": 0.01, "mount_height": 1.73},
    128: {"rings": 128, "fov_up_deg": 22.5, "fov_down_deg": -22.5, "columns": 1024, "max_range": 120.0,
          "range_noise": 0.03, "dropout": 0.01, "mount_height": 1.73},
}


@dataclass
class LivoxLike:
    """A forward-looking solid-state LiDAR with a non-repetitive rosette pattern (Livox Avia like).

    ``points`` rays per scan over ``fov_h_deg`` x ``fov_v_deg`` (x forward, y left, z up): two
    incommensurate rotations (``f1_hz``, ``f2_hz``) trace a rosette that never repeats, so each
    scan samples different directions and the coverage fills in over time. The pattern runs on
    from scan to scan at ``rate_hz`` (scan ``k`` covers ``[k, k + 1) / rate_hz`` seconds).
    """

    fov_h_deg: float = 70.4
    fov_v_deg: float = 77.2
    points: int = 24000
    f1_hz: float = 733.0
    f2_hz: float = -467.3
    rate_hz: float = 10.0
    max_range: float = 120.0
    range_noise: float = 0.02
    dropout: float = 0.01
    mount_height: float = 1.73

    def directions_at(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Unit ray directions ``(points, 3)`` of scan ``k`` and their times in [0, 1) within it."""
        frac = np.arange(self.points) / self.points
        t = (k + frac) / self.rate_hz
        a, b = 2 * np.pi * self.f1_hz * t, 2 * np.pi * self.f2_hz * t
        u = 0.5 * (np.cos(a) + np.cos(b))  # rosette in the unit disc
        v = 0.5 * (np.sin(a) + np.sin(b))
        az = u * np.deg2rad(self.fov_h_deg) / 2
        el = v * np.deg2rad(self.fov_v_deg) / 2
        d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
        return d, frac


class RayCaster:
    """Wraps a ``RaycastingScene`` built from a legacy ``TriangleMesh``."""

    def __init__(self, mesh) -> None:
        from submapslam._deps import open3d

        o3d = open3d()
        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        self.triangles = len(mesh.triangles)

    def ranges(self, T_world_sensor: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Distances ``(N,)`` along sensor-frame unit ``directions`` (inf where nothing is hit)."""
        return self.cast(T_world_sensor, directions)[0]

    def cast(self, T_world_sensor: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances ``(N,)`` (inf where nothing is hit) and the index ``(N,)`` of the triangle hit."""
        d_world = directions @ T_world_sensor[:3, :3].T
        origins = np.broadcast_to(T_world_sensor[:3, 3], d_world.shape)
        rays = self._o3d.core.Tensor(np.hstack([origins, d_world]).astype(np.float32))
        hit = self.scene.cast_rays(rays)
        return hit["t_hit"].numpy().astype(np.float64), hit["primitive_ids"].numpy().astype(np.int64)


def measure(ranges: np.ndarray, max_range: float, noise: float, dropout: float,
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Apply noise, max range and dropouts; return noisy ranges and the valid mask."""
    valid = np.isfinite(ranges) & (ranges < max_range) & (rng.random(len(ranges)) >= dropout)
    noisy = ranges + rng.normal(0.0, noise, len(ranges)) if noise > 0 else ranges.copy()
    return noisy, valid & (noisy > 0)
