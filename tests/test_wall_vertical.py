"""The vertical a submap's walls give (mapping.vertical), against the ground plane's (issue 24)."""

from __future__ import annotations

import numpy as np

from submapslam.geometry import so3_exp
from submapslam.mapping.height_band import ground_normal
from submapslam.mapping.vertical import structure_vertical


def _street(rng: np.random.Generator, grade_deg: float, across: bool = True) -> np.ndarray:
    """A street in the world frame (z up): its road climbing at ``grade_deg`` along x, two plumb
    facades beside it (y = +-9 m) and, with ``across``, a building's side across the street ahead
    (x = 14 m) and a pole; 2 cm of noise on every point."""
    g = np.stack(np.meshgrid(np.arange(-15, 15, 0.2), np.arange(-9, 9, 0.2)), -1).reshape(-1, 2)
    road = np.c_[g, -1.7 + np.tan(np.deg2rad(grade_deg)) * g[:, 0]]
    u, h = np.meshgrid(np.arange(-15, 15, 0.2), np.arange(0.5, 8.0, 0.2))  # above the road throughout
    u, h = u.ravel(), h.ravel()
    parts = [road, np.c_[u, np.full_like(u, 9.0), h], np.c_[u, np.full_like(u, -9.0), h]]
    if across:
        parts.append(np.c_[np.full_like(u, 14.0), 0.3 * u, h])
        a, z = np.meshgrid(np.linspace(0, 2 * np.pi, 40), np.arange(0.5, 5.0, 0.1))
        parts.append(np.c_[5.0 + 0.3 * np.cos(a.ravel()), 6.0 + 0.3 * np.sin(a.ravel()), z.ravel()])
    pts = np.concatenate(parts)
    return pts + rng.normal(0.0, 0.02, pts.shape)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.rad2deg(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


def test_walls_give_the_true_vertical_where_the_ground_climbs():
    """Seen from a vehicle pitched 6 deg by the road and rolled 1 deg: the ground plane says up is
    the road's normal (6 deg off the truth), the walls say where gravity is (within 0.3 deg)."""
    rng = np.random.default_rng(1)
    R_world_anchor = so3_exp(np.deg2rad([1.0, -6.0, 0.0]))
    pts = _street(rng, 6.0) @ R_world_anchor  # row-wise R^T p: the points in the anchor's frame
    true_up = R_world_anchor.T @ np.array([0.0, 0.0, 1.0])
    ground = ground_normal(pts)
    vertical = structure_vertical(pts, ground, voxel=0.5, query_cell=1.0)
    assert ground is not None and _angle_deg(ground, true_up) > 5.0
    assert vertical is not None and _angle_deg(vertical, true_up) < 0.3
    assert vertical @ true_up > 0  # pointing up, like the guess


def test_no_vertical_from_a_street_canyon_or_an_open_field():
    """Facades that all face one way fix the roll but not the pitch: no vertical. A field has no walls."""
    rng = np.random.default_rng(2)
    canyon = _street(rng, 3.0, across=False)
    assert structure_vertical(canyon, np.array([0.0, 0.0, 1.0])) is None
    field = canyon[np.abs(canyon[:, 1]) < 8.5]  # the road alone
    assert structure_vertical(field, np.array([0.0, 0.0, 1.0])) is None
