"""Scores of a cleaned map against labelled scans: the DynamicMap benchmark (Zhang et al., ITSC 2023).

The ground-truth map is every labelled scan placed at its ground-truth pose, voxelised
(:class:`LabelledVoxels`). A voxel is *static* when every point in it has a static class,
*dynamic* when every point has a moving class (SemanticKITTI 252-259), and *mixed* otherwise
(not scored, counted). A voxel counts as kept when the scored map has a point within
``radius`` of the voxel's centroid. Static accuracy SA = kept static voxels / static voxels,
dynamic accuracy DA = removed dynamic voxels / dynamic voxels, AA = sqrt(SA * DA).

For 2D logs the voxels are grid cells (z dropped) and the map is the occupied cells' centres.
Pure numpy/scipy: no file is read here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..mapping.dynamic_removal import voxel_keys

DYNAMIC_LOW, DYNAMIC_HIGH = 252, 259  # SemanticKITTI moving classes (lower 16 bits)


def is_dynamic(labels: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: which SemanticKITTI labels (uint32, class in the lower 16 bits) are moving classes."""
    cls = np.asarray(labels, dtype=np.uint32) & 0xFFFF
    return (cls >= DYNAMIC_LOW) & (cls <= DYNAMIC_HIGH)


class LabelledVoxels:
    """Accumulates labelled world points ``(N, 3)`` into voxels: centroid, static and dynamic counts.

    Scans are added one at a time (:meth:`add`); memory is one row per occupied voxel, merged
    every ``merge_every`` scans. ``planar``: z is dropped (2D cells of side ``voxel``).
    """

    def __init__(self, voxel: float = 0.1, planar: bool = False, merge_every: int = 40) -> None:
        if voxel <= 0:
            raise ValueError(f"voxel must be > 0, not {voxel}")
        self.voxel = voxel
        self.planar = planar
        self.merge_every = merge_every
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self._pending = 0
        self.points = 0

    def add(self, points_world: np.ndarray, labels: np.ndarray) -> None:
        """Add one scan: world points ``(N, 3)`` [m] and their labels ``(N,)``."""
        p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        if self.planar:
            p = np.column_stack([p[:, :2], np.zeros(len(p))])
        if len(p) != len(labels):
            raise ValueError(f"{len(labels)} labels for {len(p)} points")
        dyn = is_dynamic(labels)
        self._parts.append(_reduce(voxel_keys(p, self.voxel), p, (~dyn).astype(np.int64), dyn.astype(np.int64)))
        self.points += len(p)
        self._pending += 1
        if self._pending >= self.merge_every:
            self._merge()

    def _merge(self) -> None:
        if len(self._parts) > 1:
            keys, sums, n_static, n_dyn = (np.concatenate(a) for a in zip(*self._parts))
            order = np.argsort(keys, kind="stable")
            keys, sums, n_static, n_dyn = keys[order], sums[order], n_static[order], n_dyn[order]
            first = np.concatenate([[True], keys[1:] != keys[:-1]])
            idx = np.cumsum(first) - 1
            m = int(idx[-1]) + 1
            out_sums = np.zeros((m, 3))
            np.add.at(out_sums, idx, sums)
            self._parts = [(keys[first], out_sums, np.bincount(idx, n_static, m).astype(np.int64),
                            np.bincount(idx, n_dyn, m).astype(np.int64))]
        self._pending = 0

    def voxels(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centroids ``(V, 3)``, static point counts ``(V,)`` and dynamic point counts ``(V,)``."""
        self._merge()
        if not self._parts:
            return np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        _, sums, n_static, n_dyn = self._parts[0]
        return sums / (n_static + n_dyn)[:, None], n_static, n_dyn


def _reduce(keys: np.ndarray, points: np.ndarray, n_static: np.ndarray, n_dyn: np.ndarray):
    uniq, idx = np.unique(keys, return_inverse=True)
    m = len(uniq)
    sums = np.stack([np.bincount(idx, points[:, k], m) for k in range(3)], axis=1)
    return uniq, sums, np.bincount(idx, n_static, m).astype(np.int64), np.bincount(idx, n_dyn, m).astype(np.int64)


@dataclass(frozen=True)
class MapScores:
    """SA, DA, AA and the voxel counts behind them."""

    static_accuracy: float
    dynamic_accuracy: float
    associated_accuracy: float
    static_voxels: int
    static_kept: int
    dynamic_voxels: int
    dynamic_removed: int
    mixed_voxels: int
    map_points: int

    def as_dict(self) -> dict:
        return {"SA": round(self.static_accuracy, 6), "DA": round(self.dynamic_accuracy, 6),
                "AA": round(self.associated_accuracy, 6), "static_voxels": self.static_voxels,
                "static_kept": self.static_kept, "dynamic_voxels": self.dynamic_voxels,
                "dynamic_removed": self.dynamic_removed, "mixed_voxels_not_scored": self.mixed_voxels,
                "map_points": self.map_points}


def score_map(truth: LabelledVoxels, map_points: np.ndarray, radius: float = 0.15) -> MapScores:
    """Score the map ``(M, 3)`` (world frame, the truth's frame) against the labelled voxels.

    A voxel is kept when a map point lies within ``radius`` [m] of its centroid (for planar
    truth the map's z is dropped). SA over pure-static voxels, DA over pure-dynamic voxels;
    an empty class scores 1.0 (nothing to keep or to remove).
    """
    from scipy.spatial import cKDTree

    if radius <= 0:
        raise ValueError(f"radius must be > 0, not {radius}")
    centroids, n_static, n_dyn = truth.voxels()
    pts = np.asarray(map_points, dtype=np.float64).reshape(-1, 3)
    if truth.planar:
        pts = np.column_stack([pts[:, :2], np.zeros(len(pts))])
    static = (n_static > 0) & (n_dyn == 0)
    dynamic = (n_dyn > 0) & (n_static == 0)
    scored = static | dynamic
    kept = np.zeros(len(centroids), dtype=bool)
    if len(pts) and scored.any():
        tree = cKDTree(pts)
        d, _ = tree.query(centroids[scored], distance_upper_bound=radius)
        kept[scored] = np.isfinite(d)
    s_kept, d_kept = int((kept & static).sum()), int((kept & dynamic).sum())
    n_s, n_d = int(static.sum()), int(dynamic.sum())
    sa = s_kept / n_s if n_s else 1.0
    da = (n_d - d_kept) / n_d if n_d else 1.0
    return MapScores(sa, da, float(np.sqrt(sa * da)), n_s, s_kept, n_d, n_d - d_kept,
                     int((~scored).sum()), len(pts))
