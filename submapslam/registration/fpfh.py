"""Fast Point Feature Histograms (Rusu et al. 2009), as open3d computes them, in numpy.

``fpfh_features(points, normals, radius, max_nn) -> (N, 33)``: for each point, the three angle
histograms (11 bins each, each summing to 100) of its pairs with its neighbours (SPFH), then the
neighbours' SPFH weighted by 1 / squared distance, renormalised, plus the point's own SPFH (the
paper's form, as open3d computes it; PCL leaves the own SPFH out). Neighbours: the ``max_nn``
nearest within ``radius`` (open3d's hybrid search). Given the same points and normals the result
matches ``open3d.pipelines.registration.compute_fpfh_feature`` (tests/test_spatial_toolbox.py), so
the 3D loop tests need neither open3d's import (a 3D run's imports take 130 MiB resident without
it, 188 with it) nor its threads.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

_BINS = 11
_CHUNK = 256  # points per vectorised block: (256, max_nn, 33) floats stay a few MB


def _pair_features(p1: np.ndarray, n1: np.ndarray, p2: np.ndarray, n2: np.ndarray) -> np.ndarray:
    """``(..., 3)`` angle features ``(alpha, phi, theta)`` of point pairs (Darboux frame at the
    point whose normal is more parallel to the line joining them); zeros for coincident points or
    a normal along that line, as open3d returns them."""
    dp = p2 - p1
    length = np.linalg.norm(dp, axis=-1)
    safe = np.where(length > 0, length, 1.0)
    angle1 = np.einsum("...i,...i->...", n1, dp) / safe
    angle2 = np.einsum("...i,...i->...", n2, dp) / safe
    swap = np.arccos(np.clip(np.abs(angle1), 0, 1)) > np.arccos(np.clip(np.abs(angle2), 0, 1))
    s = swap[..., None]
    a, b = np.where(s, n2, n1), np.where(s, n1, n2)
    dp = np.where(s, -dp, dp)
    theta = np.where(swap, -angle2, angle1)
    v = np.cross(dp, a)
    v_norm = np.linalg.norm(v, axis=-1)
    v = v / np.where(v_norm > 0, v_norm, 1.0)[..., None]
    w = np.cross(a, v)
    phi = np.einsum("...i,...i->...", v, b)
    alpha = np.arctan2(np.einsum("...i,...i->...", w, b), np.einsum("...i,...i->...", a, b))
    out = np.stack([alpha, phi, theta], axis=-1)
    out[(length == 0) | (v_norm == 0)] = 0.0
    return out


def _bins(features: np.ndarray) -> np.ndarray:
    """``(..., 3)`` pair features -> ``(..., 3)`` histogram columns in ``[0, 33)``."""
    alpha = np.floor(_BINS * (features[..., 0] + np.pi) / (2.0 * np.pi))
    rest = np.floor(_BINS * (features[..., 1:] + 1.0) * 0.5)
    cols = np.clip(np.concatenate([alpha[..., None], rest], axis=-1), 0, _BINS - 1).astype(np.int64)
    return cols + np.array([0, _BINS, 2 * _BINS])


def fpfh_features(points: np.ndarray, normals: np.ndarray, radius: float, max_nn: int = 100,
                  tree: cKDTree | None = None) -> np.ndarray:
    """FPFH descriptors ``(N, 33)`` of ``points (N, 3)`` with unit ``normals (N, 3)``; neighbours:
    the ``max_nn`` nearest (the point itself included) within ``radius`` [m]."""
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    n = len(points)
    if n < 2:
        return np.zeros((n, 3 * _BINS))
    tree = tree if tree is not None else cKDTree(points)
    dist, idx = tree.query(points, k=min(max_nn, n), distance_upper_bound=radius)
    dist, idx = dist[:, 1:], idx[:, 1:]  # column 0: the point itself
    found = np.isfinite(dist)
    idx = np.where(found, idx, 0)
    count = found.sum(axis=1)

    spfh = np.zeros((n, 3 * _BINS))
    for start in range(0, n, _CHUNK):
        rows = slice(start, min(start + _CHUNK, n))
        features = _pair_features(points[rows, None], normals[rows, None], points[idx[rows]], normals[idx[rows]])
        cols = _bins(features)  # (c, K, 3)
        weight = np.where(found[rows], 100.0 / np.maximum(count[rows], 1)[:, None], 0.0)
        flat = (np.arange(rows.stop - rows.start)[:, None, None] * 3 * _BINS + cols).ravel()
        spread = np.repeat(weight[..., None], 3, axis=2).ravel()
        spfh[rows] = np.bincount(flat, weights=spread, minlength=(rows.stop - rows.start) * 3 * _BINS
                                 ).reshape(-1, 3 * _BINS)

    squared = dist**2
    weight = np.where(found & (squared > 0), 1.0 / np.where(squared > 0, squared, 1.0), 0.0)
    out = np.zeros((n, 3 * _BINS))
    for start in range(0, n, _CHUNK):
        rows = slice(start, min(start + _CHUNK, n))
        out[rows] = np.einsum("ck,ckf->cf", weight[rows], spfh[idx[rows]])
    blocks = out.reshape(n, 3, _BINS)
    sums = blocks.sum(axis=2, keepdims=True)
    blocks *= np.where(sums != 0, 100.0 / np.where(sums != 0, sums, 1.0), 0.0)
    return out + spfh
