"""Place descriptors for submaps: Scan Context (Kim & Kim, IROS 2018) adapted to planar data.

A polar grid (``rings x sectors``) around the submap anchor. 3D cell value: the highest point
above the submap's lowest point; planar cell value (no height in a 2D scan): the log point
count, which encodes where walls are and how much of them. Matching is rotation-invariant by a
circular column shift, which also estimates the yaw between the two anchors. A ring key (mean
per ring) is rotation-invariant and pre-selects candidates.
"""

from __future__ import annotations

import numpy as np

RINGS = 20
SECTORS = 60


def compute_descriptor(points: np.ndarray, *, planar: bool, max_range: float, rings: int = RINGS,
                       sectors: int = SECTORS) -> np.ndarray:
    """``(N, 3)`` points in the anchor frame -> ``(rings, sectors)`` descriptor, max-normalised."""
    desc = np.zeros((rings, sectors))
    if len(points) == 0:
        return desc
    points = np.asarray(points, dtype=np.float64)
    xy = points[:, :2]
    r = np.hypot(xy[:, 0], xy[:, 1])
    keep = r < max_range
    r, pts = r[keep], points[keep]
    theta = np.arctan2(pts[:, 1], pts[:, 0])
    ri = np.minimum((r / max_range * rings).astype(int), rings - 1)
    si = np.minimum(((theta + np.pi) / (2 * np.pi) * sectors).astype(int), sectors - 1)
    if planar:
        np.add.at(desc, (ri, si), 1.0)
        desc = np.log1p(desc)
    else:
        height = pts[:, 2] - pts[:, 2].min()
        np.maximum.at(desc, (ri, si), height)
    peak = desc.max()
    return desc / peak if peak > 0 else desc


def ring_key(desc: np.ndarray) -> np.ndarray:
    """Rotation-invariant ``(rings,)`` summary: occupancy of each ring."""
    return (desc > 0).mean(axis=1)


def descriptor_distance(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Scan Context distance in [0, 1] and the yaw [rad] that rotates ``b``'s frame onto ``a``'s.

    The distance is 1 - mean column cosine similarity at the best circular shift; all shifts
    are scored at once with an FFT along the sector axis.
    """
    sectors = a.shape[1]
    na = np.linalg.norm(a, axis=0)
    nb = np.linalg.norm(b, axis=0)
    an = np.divide(a, na, out=np.zeros_like(a), where=na > 0)
    bn = np.divide(b, nb, out=np.zeros_like(b), where=nb > 0)
    # corr[k] = sum_s <an[:, s], bn[:, s - k]>  (b shifted by k sectors)
    corr = np.fft.irfft(np.fft.rfft(an, axis=1) * np.conj(np.fft.rfft(bn, axis=1)), n=sectors, axis=1).sum(axis=0)
    valid = max(int(((na > 0) | (nb > 0)).sum()), 1)
    k = int(np.argmax(corr))
    similarity = float(corr[k]) / valid
    yaw = (k if k <= sectors // 2 else k - sectors) * 2 * np.pi / sectors
    return float(np.clip(1.0 - similarity, 0.0, 1.0)), float(yaw)


class DescriptorIndex:
    """All submap descriptors so far; ``query`` finds the most similar ones."""

    def __init__(self, prefilter: int = 20) -> None:
        self.ids: list[int] = []
        self.descs: list[np.ndarray] = []
        self.keys: list[np.ndarray] = []
        self.prefilter = prefilter

    def add(self, id_: int, desc: np.ndarray) -> None:
        self.ids.append(id_)
        self.descs.append(desc)
        self.keys.append(ring_key(desc))

    def query(self, desc: np.ndarray, top_k: int, exclude_ids: set[int] | None = None) -> list[tuple[int, float, float]]:
        """Best ``top_k`` ``(id, distance, yaw)`` by Scan Context distance, ring-key prefiltered."""
        if not self.ids or top_k <= 0:
            return []
        exclude = exclude_ids or set()
        keys = np.array(self.keys)
        d_key = np.linalg.norm(keys - ring_key(desc), axis=1)
        order = [i for i in np.argsort(d_key) if self.ids[i] not in exclude][: self.prefilter]
        scored = []
        for i in order:
            dist, yaw = descriptor_distance(self.descs[i], desc)
            scored.append((self.ids[i], dist, yaw))
        scored.sort(key=lambda t: t[1])
        return scored[:top_k]
