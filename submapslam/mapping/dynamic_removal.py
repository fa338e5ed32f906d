"""Dynamic-point removal given poses: voxels that a later (or earlier) beam passed through are not there.

Two passes over the scans (the DynamicMap benchmark's setting: scans plus one pose each):

1. **Voxel map.** Every scan point, moved into the world frame, falls into a ``voxel`` cell;
   each occupied voxel keeps its centroid, point count, first and last sighting, the scans that
   saw it and its per-scan ground points (:class:`VoxelAccumulator`).
2. **Free-space evidence by ray casting, through the range image.** Each scan (every
   ``stride``-th) becomes a fine range image in the sensor frame (``el_bin_deg`` x
   ``az_bin_deg`` pixels, each the nearest return in its direction). Every voxel centroid within
   ``max_range`` is projected into it: when the pixel holds a beam and that beam ended more than
   ``margin(r) = max(margin, margin_per_m * r)`` beyond the centroid, the beam passed through the
   voxel and the voxel gets a *free* vote for that scan. Looking a voxel up in the image is the
   ray traversal run backwards: the same test, but one lookup per voxel instead of one step per
   voxel along every ray, so a 600-scan 16-ring drive takes seconds of numpy.

A voxel with a free vote was seen through: something was there in one scan and another scan saw
through it (a car that drove on, a pedestrian who walked away, a parked car that left). The same
lookup counts the scans whose beam *ended* at the voxel (within the margin, either side): a
static surface whose points fell into the neighbouring voxel in that scan. A voxel is voted
when its free votes outnumber ``hit_weight`` times those hits: a wall's or a pole's edge voxel
that a grazing beam passes once but later beams see occupied again is not something that left
(what moved is seen through again and again and seldom hit; a hit weighs half a free vote
because the margin is wide: a beam ending on the surface beside the voxel counts as one). The
decision is per cluster of neighbours seen at overlapping times (``cluster_fraction`` of its
tested voxels voted, and at least ``min_free``: 1 lets a lone voxel, a far car hit by one ring,
go). A moved cluster is then cut between neighbours whose sighting durations differ by more than
``split_ratio`` times (a car seen for two scans as it drove past a parked car seen for forty): a
part with at least ``split_min_tested`` tested voxels stays when it is not voted itself (the
parked car, the pole a pedestrian walked by). The margin that grows with range keeps grazing
beams over rough ground and along walls from voting (a beam through a ground voxel at range r
ends within about ``r * roughness / sensor height`` of it).

The ground is never tested nor removed: the voxels within ``ground_band`` of the lowest voxel of
their ``ground_cell`` column, and (``scan_ground``) the voxels seen by ``scan_ground_seen`` scans
or more whose points were mostly ground in their own scan (:func:`scan_ground_points`: decided in
the scan's frame, so pose errors that smear the road over several voxels in the world do not
make its upper layer look like something a later beam passed through).

Frames: points ``(N, 3)`` in the base frame, ``T_world_base`` ``(4, 4)``, ``T_base_sensor``
``(4, 4)`` (the ray origin). Units: metres, degrees where named.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

_BITS = 21


_KEY_CHUNK = 1 << 16  # points keyed at once: the temporaries of a submap's 700k points stay a few MB


def voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """One int64 key ``(N,)`` per point ``(N, 3)``: its ``voxel`` cell's integer coordinates, 21 bits each."""
    points = np.asarray(points)
    keys = np.empty(len(points), dtype=np.int64)
    for lo in range(0, len(points), _KEY_CHUNK):
        ijk = np.floor(np.asarray(points[lo:lo + _KEY_CHUNK], dtype=np.float64) / voxel).astype(np.int64)
        ijk += 1 << (_BITS - 1)
        keys[lo:lo + _KEY_CHUNK] = (ijk[:, 0] << (2 * _BITS)) | (ijk[:, 1] << _BITS) | ijk[:, 2]
    return keys


class VoxelAccumulator:
    """Occupied voxels of a scan sequence: sorted keys, centroid sums, point counts, the first and
    last scan that had a point in each voxel and how many scans did.

    Scans are reduced one by one, gathered into batches of about ``merge_points`` points, and each
    batch is merged into the sorted table in place (new voxels inserted), so memory stays near the
    table's size.
    """

    def __init__(self, voxel: float, merge_points: int = 2_000_000) -> None:
        self.voxel = voxel
        self.merge_points = merge_points
        self._parts: list[tuple[np.ndarray, ...]] = []
        self._table: list[np.ndarray] | None = None
        self._pending = 0
        self.seen = np.zeros(0, dtype=np.int32)  # (V,) after result(): scans with a point in each voxel
        self.flagged = np.zeros(0, dtype=np.int32)  # (V,) after result(): flagged points in each voxel

    def add(self, points_world: np.ndarray, scan: int, flagged: np.ndarray | None = None) -> None:
        """Add the ``(N, 3)`` world points of scan number ``scan``; ``flagged`` ``(N,)`` bool: points
        counted in :attr:`flagged` per voxel (e.g. that scan's ground points)."""
        p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        if not len(p):
            return
        keys = voxel_keys(p, self.voxel)
        order = np.argsort(keys)
        keys = keys[order]
        idx, start = _groups(keys)
        m = len(start)
        sums = _column_sums(idx, p[order], m)
        one = np.ones(m, dtype=np.int32)
        flags = np.zeros(m, dtype=np.int32) if flagged is None else \
            np.bincount(idx, np.asarray(flagged)[order], m).astype(np.int32)
        self._parts.append((keys[start], sums, np.bincount(idx, minlength=m).astype(np.int64), one * scan,
                            one * scan, one, flags))
        self._pending += len(p)
        if self._pending >= self.merge_points:
            self._merge()

    def _merge(self) -> None:
        self._pending = 0
        if not self._parts:
            return
        batch = _reduce(*(np.concatenate(a) for a in zip(*self._parts))) if len(self._parts) > 1 else self._parts[0]
        self._parts = []
        if self._table is None:
            self._table = list(batch)
            return
        table = self._table
        pos = np.searchsorted(table[0], batch[0])
        found = table[0][np.minimum(pos, len(table[0]) - 1)] == batch[0]
        at = pos[found]
        for i in (1, 2, 5, 6):  # sums, counts, scans seen, flagged
            table[i][at] += batch[i][found]
        table[3][at] = np.minimum(table[3][at], batch[3][found])
        table[4][at] = np.maximum(table[4][at], batch[4][found])
        new = ~found
        if new.any():
            for i in range(len(table)):
                table[i] = np.insert(table[i], pos[new], batch[i][new], axis=0)

    def result(self) -> tuple[np.ndarray, ...]:
        """Sorted keys ``(V,)``, centroids ``(V, 3)``, point counts ``(V,)``, first and last scan ``(V,)``
        (and :attr:`seen`, :attr:`flagged`)."""
        self._merge()
        if self._table is None:
            z = np.zeros(0, dtype=np.int64)
            return z, np.zeros((0, 3)), z, z.astype(np.int32), z.astype(np.int32)
        keys, sums, counts, first, last, self.seen, self.flagged = self._table
        return keys, sums / counts[:, None], counts, first, last


def _groups(sorted_keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Group index ``(N,)`` of each sorted key and the first row ``(G,)`` of each group."""
    flag = np.empty(len(sorted_keys), dtype=bool)
    flag[:1] = True
    np.not_equal(sorted_keys[1:], sorted_keys[:-1], out=flag[1:])
    return np.cumsum(flag) - 1, np.flatnonzero(flag)


def _column_sums(idx: np.ndarray, values: np.ndarray, m: int) -> np.ndarray:
    """``(m, 3)`` sums of the rows of ``values`` ``(N, 3)`` by group index ``idx`` ``(N,)``."""
    return np.stack([np.bincount(idx, values[:, j], m) for j in range(3)], axis=1)


def _reduce(keys, sums, counts, first, last, seen, flags):
    """Group rows by key: sum ``sums`` ``(N, 3)``, ``counts``, ``seen`` and ``flags``, min of ``first``, max
    of ``last``."""
    order = np.argsort(keys, kind="stable")  # parts are sorted runs: a merge
    keys = keys[order]
    idx, start = _groups(keys)
    m = len(start)
    return (keys[start], _column_sums(idx, sums[order], m), np.bincount(idx, counts[order], m).astype(np.int64),
            np.minimum.reduceat(first[order], start), np.maximum.reduceat(last[order], start),
            np.bincount(idx, seen[order], m).astype(np.int32), np.bincount(idx, flags[order], m).astype(np.int32))


def transform(points: np.ndarray, T: np.ndarray, dtype=np.float64) -> np.ndarray:
    """``points (N, 3) @ R.T + t`` of the ``(4, 4)`` ``T``, elementwise (no BLAS threads: on a shared
    machine a threaded 3x3 product costs more than it saves)."""
    p = np.asarray(points)
    R, t = np.asarray(T[:3, :3], dtype=dtype), np.asarray(T[:3, 3], dtype=dtype)
    out = np.empty((len(p), 3), dtype=dtype)
    for i in range(3):
        out[:, i] = p[:, 0] * R[i, 0] + p[:, 1] * R[i, 1] + p[:, 2] * R[i, 2] + t[i]
    return out


@dataclass(frozen=True)
class RemovalParams:
    """Settings of :func:`remove_dynamic_points` (see the module docstring)."""

    voxel: float = 0.1  # [m] map voxel; also the output resolution
    max_range: float = 50.0  # [m] voxels farther from the sensor get no evidence from that scan
    margin: float = 0.3  # [m] a beam must end this far beyond a voxel to free it ...
    margin_per_m: float = 0.05  # ... or this fraction of the voxel's range, whichever is larger
    min_free: int = 1  # voxels with a free vote a cluster needs at least (1: a lone voxel seen once, far away, can go)
    hit_weight: float = 0.5  # a voxel is voted when its free votes > this x the scans whose beam ended at it (0: any vote)
    split_ratio: float = 4.0  # a moved cluster is cut between neighbours whose sighting durations differ more (0: off) ...
    split_min_tested: int = 20  # ... and each part with this many tested voxels must be voted itself
    stride: int = 1  # evidence from every stride-th scan
    window: int = 100  # scans after a voxel's last sighting (and before its first) that test it
    tolerance: float = 0.5  # a beam passes a voxel within this fraction of the voxel of its centre
    grow_slack: int = 2  # scans: neighbours seen within this of each other's sightings are one cluster
    cluster_fraction: float = 0.3  # a cluster with this fraction of free-voted voxels moved
    cluster_sample: int = 300  # voxels tested of a larger cluster (a sample, by key hash)
    protect: bool = True  # a vote beside a voxel seen long before or after the voted one does not count ...
    protect_slack: int = 20  # ... longer than this many scans
    protect_min_seen: int = 5  # scans between the first and last sighting of a protecting voxel
    planar_clusters: bool = False  # 2D logs: clusters too (else each voxel is decided by its own votes ...
    planar_min_free: int = 2  # ... and needs this many free votes)
    ground_cell: float = 1.0  # [m] columns whose lowest voxel is the ground ...
    ground_band: float = 0.15  # [m] ... and the voxels this far above it, never removed
    scan_ground: bool = True  # also the voxels whose points were mostly ground in their own scans (below)
    scan_ground_cell: float = 1.0  # [m] per scan (base frame): cells whose lowest point is the ground ...
    scan_ground_band: float = 0.1  # [m] ... and the points this far above it ...
    scan_ground_rise: float = 0.08  # [m] ... when the lowest point is no higher than the scan's ground plane
    scan_ground_seen: int = 2  # ... in voxels seen by this many scans at least (not a mover that passed once)
    scan_ground_slope: float = 0.004  # ... by this much plus this fraction of its range (not a car's side)
    el_bin_deg: float = 0.25  # range-image pixel: elevation ...
    az_bin_deg: float = 0.2  # ... and azimuth


@dataclass
class RemovalResult:
    """Voxels of all scans and which of them moved.

    ``centroids`` ``(V, 3)`` world frame; ``counts`` ``(V,)`` points per voxel; ``free_votes``
    ``(V,)`` scans that saw through the voxel (``hit_votes``: whose beam ended at it; both only
    for the tested voxels); ``dynamic`` ``(V,)`` bool; ``keys`` ``(V,)`` sorted
    voxel keys (:func:`voxel_keys` at ``params.voxel``); ``seconds`` per pass.
    """

    keys: np.ndarray
    centroids: np.ndarray
    counts: np.ndarray
    free_votes: np.ndarray
    dynamic: np.ndarray
    params: RemovalParams
    seconds: dict[str, float] = field(default_factory=dict)
    first: np.ndarray | None = None  # (V,) first scan with a point in the voxel
    last: np.ndarray | None = None  # (V,) last such scan
    cluster: np.ndarray | None = None  # (V,) cluster id (-1: ground, never removed)
    ground: np.ndarray | None = None  # (V,) bool: ground voxels
    hit_votes: np.ndarray | None = None  # (V,) scans whose beam ended at the voxel (within the margin)

    @property
    def points_kept(self) -> int:
        return int(self.counts[~self.dynamic].sum())

    @property
    def points_removed(self) -> int:
        return int(self.counts[self.dynamic].sum())

    def dynamic_mask(self, points_world: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: which world points ``(N, 3)`` fall into a dynamic voxel."""
        k = voxel_keys(points_world, self.params.voxel)
        pos = np.clip(np.searchsorted(self.keys, k), 0, max(len(self.keys) - 1, 0))
        found = len(self.keys) > 0
        return found & (self.keys[pos] == k) & self.dynamic[pos] if found else np.zeros(len(k), dtype=bool)


class _TileIndex:
    """Voxels sorted into square ``tile`` [m] columns, to fetch those near a sensor quickly."""

    def __init__(self, centroids: np.ndarray, tile: float) -> None:
        self.tile = tile
        ij = np.floor(centroids[:, :2] / tile).astype(np.int64)
        self.lo = ij.min(axis=0) if len(ij) else np.zeros(2, dtype=np.int64)
        ij -= self.lo
        self.shape = ij.max(axis=0) + 1 if len(ij) else np.ones(2, dtype=np.int64)
        flat = ij[:, 0] * self.shape[1] + ij[:, 1]
        self.order = np.argsort(flat, kind="stable")
        self.starts = np.searchsorted(flat[self.order], np.arange(self.shape[0] * self.shape[1] + 1))

    def near(self, xy: np.ndarray, radius: float) -> np.ndarray:
        """Indices of the voxels in the tiles within ``radius`` of ``xy`` (a superset of the disc)."""
        lo = np.floor((xy - radius) / self.tile).astype(np.int64) - self.lo
        hi = np.floor((xy + radius) / self.tile).astype(np.int64) - self.lo
        lo, hi = np.maximum(lo, 0), np.minimum(hi, self.shape - 1)
        if np.any(hi < lo):
            return np.zeros(0, dtype=np.int64)
        parts = [self.order[self.starts[i * self.shape[1] + lo[1]]:self.starts[i * self.shape[1] + hi[1] + 1]]
                 for i in range(lo[0], hi[0] + 1)]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)


class RangeImage:
    """The nearest return per (elevation, azimuth) pixel of one scan in its sensor frame, with the
    return's exact direction, so a lookup can tell whether that beam passed through a voxel.

    Stored compactly: a pixel grid of ``int32`` slots (0: no beam) into the returns kept, one
    per occupied pixel (a narrow-field scan fills a few % of the grid's pixels, a 16-ring scan
    a third), each with its range, elevation and azimuth (``float32``), and which azimuth
    columns hold any return (a lookup skips the points outside them: most, for a narrow field)."""

    def __init__(self, points_sensor: np.ndarray, el_bin_deg: float, az_bin_deg: float) -> None:
        r, el, az = _spherical(points_sensor)
        ok = r > 1e-6
        r, el, az = r[ok], el[ok], az[ok]
        self.del_ = np.deg2rad(el_bin_deg)
        self.daz = np.deg2rad(az_bin_deg)
        self.cols = int(np.ceil(2 * np.pi / self.daz))
        self.el_lo = float(el.min()) - 2 * self.del_ if len(el) else 0.0
        rows = np.floor((el - self.el_lo) / self.del_).astype(np.int64)
        self.rows = int(rows.max()) + 3 if len(rows) else 1
        flat = rows * self.cols + self._col(az)
        order = np.argsort(-r)  # nearest written last: duplicates keep the nearest return
        nearest = np.zeros(self.rows * self.cols, dtype=np.int64)  # 1 + index into r of each pixel's return
        nearest[flat[order]] = order + 1
        kept = np.flatnonzero(nearest)
        self._slot = np.zeros(self.rows * self.cols, dtype=np.int32)
        self._slot[kept] = np.arange(1, len(kept) + 1, dtype=np.int32)
        chosen = nearest[kept] - 1
        # slot 0: no beam (range 0)
        self._range = np.concatenate([[0.0], r[chosen]]).astype(np.float32)
        self._el = np.concatenate([[0.0], el[chosen]]).astype(np.float32)
        self._az = np.concatenate([[0.0], az[chosen]]).astype(np.float32)
        self._column_has_beam = np.zeros(self.cols, dtype=bool)
        self._column_has_beam[kept % self.cols] = True
        self._wedge_normals = self._wedge()

    def _col(self, az: np.ndarray) -> np.ndarray:
        return np.floor((az + np.pi) / self.daz).astype(np.int64) % self.cols

    def facing(self, T_sensor_world: np.ndarray, points_world: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: the world points ``(N, 3)`` (this scan at ``T_sensor_world``) within the
        azimuth wedge of its columns with a return, widened by a column each side: a superset of
        those a beam of this scan can pass (:meth:`passes`), found without moving them into the
        sensor frame (two half-space tests). All of them when the columns span more than 170 deg."""
        normals = self._wedge_normals
        if normals is None:
            return np.ones(len(points_world), dtype=bool)
        if not len(normals):  # no return at all
            return np.zeros(len(points_world), dtype=bool)
        R, t = T_sensor_world[:3, :3], T_sensor_world[:3, 3]
        # n . (R p + t) >= 0  <=>  (R^T n) . p >= -n . t; a micrometre of slack for the rounding
        side = np.asarray(points_world, dtype=np.float64) @ (normals @ R).T + normals @ t
        return (side[:, 0] >= -1e-6) & (side[:, 1] >= -1e-6)

    def _wedge(self) -> np.ndarray | None:
        """At construction: ``(2, 3)`` sensor-frame normals of the two vertical half-planes bounding the columns with
        a return (the complement of the widest run of empty columns) plus a column each side;
        ``(0, 3)`` when no column has one; None when that wedge is wider than 170 deg."""
        occupied = np.flatnonzero(self._column_has_beam)
        if not len(occupied):
            return np.zeros((0, 3))
        gaps = (np.roll(occupied, -1) - occupied) % self.cols  # to the next occupied column
        gaps[gaps == 0] = self.cols  # one occupied column: the gap is all the others
        k = int(np.argmax(gaps))
        first, last = int(occupied[(k + 1) % len(occupied)]), int(occupied[k])
        span = ((last - first) % self.cols + 1 + 2) * self.daz  # columns first..last, +1 each side
        if span > np.deg2rad(170.0):
            return None
        start = (first - 1) * self.daz - np.pi  # column c spans [c daz - pi, (c + 1) daz - pi)
        end = (last + 2) * self.daz - np.pi
        return np.array([[-np.sin(start), np.cos(start), 0.0],  # counter-clockwise of start
                         [np.sin(end), -np.cos(end), 0.0]])  # clockwise of end

    def passes(self, points_sensor: np.ndarray, tolerance: float, margin: Callable[[np.ndarray], np.ndarray],
               above: float = np.inf):
        """For sensor-frame voxel centres ``(M, 3)``: ``(r, free, hit)``, each ``(M,)``.

        A beam *passes* a centre when its direction comes within ``tolerance`` [m] of it (the
        beams of the centre's pixel and the pixels above and below) and passes it at most
        ``above`` [m] higher (elevation offset x range; inf: either side). ``free``: at least one beam
        passes and every passing beam ended more than ``margin(r)`` beyond the centre; ``hit``:
        a passing beam ended within ``margin(r)`` of it, before or beyond (a beam that ended
        well short of it, on something in front, is neither).
        """
        p = np.asarray(points_sensor, dtype=np.float64)
        r = np.sqrt(np.einsum("ij,ij->i", p, p))
        free = np.zeros(len(r), dtype=bool)
        hit = np.zeros(len(r), dtype=bool)
        az = np.arctan2(p[:, 1], p[:, 0])
        cols = self._col(az)
        # only a centre in a column with a return can have a beam pass it (the same result)
        live = np.flatnonzero(self._column_has_beam[cols])
        if not len(live):
            return r, free, hit
        ranges = r
        m = margin(r)[live]
        r, az, cols = r[live], az[live], cols[live]
        el = np.arcsin(np.clip(p[live, 2] / np.maximum(r, 1e-9), -1.0, 1.0))  # as _spherical
        rows = np.floor((el - self.el_lo) / self.del_).astype(np.int64)
        any_pass = np.zeros(len(r), dtype=bool)
        short = np.zeros(len(r), dtype=bool)
        ended = np.zeros(len(r), dtype=bool)
        cos_el = np.cos(el)
        for dr in (-1, 0, 1):
            rr = rows + dr
            inside = (rr >= 0) & (rr < self.rows)
            slot = self._slot[np.where(inside, rr, 0) * self.cols + cols]
            measured = self._range[slot]
            d_az = _wrap(self._az[slot] - az)
            rise = (self._el[slot] - el) * r  # [m] how far above the centre the beam passes
            passing = inside & (measured > 0) & (np.abs(rise) < tolerance) & (rise <= above) \
                & (d_az * cos_el * r < tolerance)
            any_pass |= passing
            short |= passing & (measured <= r + m)
            ended |= passing & (np.abs(measured - r) <= m)
        free[live] = any_pass & ~short
        hit[live] = ended
        return ranges, free, hit

    def returns_near(self, points_sensor: np.ndarray, radius: float, max_rows: int = 8,
                     max_cols: int = 12) -> np.ndarray:
        """``(M,)`` bool: this scan has a return within ``radius`` [m] (3D) of each sensor-frame
        centre ``(M, 3)`` (DUFOMap's hit extension: a beam that passes beside a surface, over a
        roof, under a canopy, beside a pole, is not evidence that the space *at* the surface is
        free). Searched in the pixels within ``radius`` of the centre's direction, at most
        ``max_rows`` x ``max_cols`` pixels either way (a centre very near the sensor sees less)."""
        p = np.asarray(points_sensor, dtype=np.float64)
        r, el, az = _spherical(p)
        out = np.zeros(len(r), dtype=bool)
        if not len(r):
            return out
        if not hasattr(self, "_xyz"):  # each return's point, computed as before in float32
            ce = np.cos(self._el)
            self._xyz = np.stack([ce * np.cos(self._az), ce * np.sin(self._az), np.sin(self._el)], 1) \
                * self._range[:, None]
        rows = np.floor((el - self.el_lo) / self.del_).astype(np.int64)
        cols = self._col(az)
        ang = radius / np.maximum(r, 1e-6)  # [rad] angular radius of the ball
        n_rows = np.minimum(np.ceil(ang / self.del_).astype(np.int64) + 1, max_rows)
        n_cols = np.minimum(np.ceil(ang / (self.daz * np.maximum(np.cos(el), 0.1))).astype(np.int64) + 1, max_cols)
        r2 = radius * radius
        p32 = p.astype(np.float32)
        for lo in range(0, len(r), _WINDOW_CHUNK):  # every (centre, pixel) pair of a chunk's windows at once
            centre, dr = _windows(n_rows[lo:lo + _WINDOW_CHUNK])
            centre += lo
            row = rows[centre] + dr
            inside = (row >= 0) & (row < self.rows)
            centre, row = centre[inside], row[inside]
            pair, dc = _windows(n_cols[centre])
            centre = centre[pair]
            slot = self._slot[row[pair] * self.cols + (cols[centre] + dc) % self.cols]
            beam = slot > 0
            centre, slot = centre[beam], slot[beam]
            d = (self._xyz[slot] - p32[centre])[:, None, :]
            out[centre[np.einsum("ijk,ijk->ij", d, d)[:, 0] <= r2]] = True
        return out


_WINDOW_CHUNK = 2048  # returns_near: centres searched at once (at most 17 x 25 pixels each)


def _windows(half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(owner, offset)``: for half-widths ``half`` ``(K,)`` (int, >= 0), every offset
    ``-half[k] .. half[k]`` of every ``k`` in turn, with ``k`` as its owner (each ``(sum(2 half + 1),)``)."""
    width = 2 * half + 1
    owner = np.repeat(np.arange(len(half)), width)
    start = np.cumsum(width) - width
    return owner, np.arange(len(owner)) - start[owner] - half[owner]


def _wrap(a: np.ndarray) -> np.ndarray:
    """|angle| wrapped into [0, pi]."""
    a = np.abs(a)
    return np.minimum(a, 2 * np.pi - a)


def _spherical(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range, elevation and azimuth ``(N,)`` of sensor-frame points ``(N, 3)``."""
    r = np.sqrt(np.einsum("ij,ij->i", p, p))
    el = np.arcsin(np.clip(p[:, 2] / np.maximum(r, 1e-9), -1.0, 1.0))
    return r, el, np.arctan2(p[:, 1], p[:, 0])


def remove_dynamic_points(scans: Callable[[], Iterable[np.ndarray]], T_world_base: np.ndarray,
                          T_base_sensor: np.ndarray | None = None, params: RemovalParams = RemovalParams(),
                          progress: Callable[[str, int], None] | None = None, planar: bool = False) -> RemovalResult:
    """Find the voxels of a posed scan sequence that something passed through.

    Args:
        scans: called twice, each time returns the scans in order, points ``(N, 3)`` in the base frame.
        T_world_base: ``(S, 4, 4)`` one pose per scan.
        T_base_sensor: ``(4, 4)`` the sensor's mounting (ray origin and range-image frame); identity if None.
        params: voxel, range, margin and vote settings.
        progress: called as ``progress(pass_name, scans_done)``.
        planar: 2D laser scans (z = 0): there is no ground to keep.
    """
    T_bs = np.eye(4) if T_base_sensor is None else np.asarray(T_base_sensor, dtype=np.float64)
    T_sb = np.linalg.inv(T_bs)
    t0 = time.perf_counter()
    acc = VoxelAccumulator(params.voxel)
    n = 0
    for k, pts in enumerate(scans()):
        if k >= len(T_world_base):
            break
        pts = np.asarray(pts)
        acc.add(transform(pts, T_world_base[k]), k, None if planar or not params.scan_ground else
                scan_ground_points(pts, params.scan_ground_cell, params.scan_ground_band, params.scan_ground_rise,
                                   params.scan_ground_slope))
        n += 1
        if progress is not None:
            progress("voxels", k + 1)
    keys, centroids, counts, first, last = acc.result()
    t1 = time.perf_counter()
    votes = np.zeros(len(keys), dtype=np.int32)
    hits = np.zeros(len(keys), dtype=np.int32)
    # the ground is never removed, so never tested; the rest is tested by the scans up to `window`
    # after the last one that saw a point in it and up to `window` before the first (a free vote
    # while points still arrive is an edge effect). The decision is per cluster, by the fraction
    # of voted voxels: of a large cluster a sample of about `cluster_sample` voxels is tested.
    ground = np.zeros(len(keys), dtype=bool) if planar else ground_voxels(centroids, params.ground_cell,
                                                                           params.ground_band)
    if not planar and params.scan_ground:
        ground |= (2 * acc.flagged >= counts) & (acc.seen >= params.scan_ground_seen)
    per_voxel = planar and not params.planar_clusters
    if per_voxel:  # a 2D wall is one long cluster: decide voxel by voxel
        cluster = np.where(ground, -1, np.arange(len(keys)))
    else:
        cluster = co_observed_clusters(keys, first, last, ~ground, params.grow_slack)
    tested = _sample_clusters(cluster, keys, params.cluster_sample)
    t_cluster = time.perf_counter() - t1
    by_last = tested[np.argsort(last[tested], kind="stable")]
    by_first = tested[np.argsort(first[tested], kind="stable")]
    last_sorted, first_sorted = last[by_last], first[by_first]
    centroids32 = centroids.astype(np.float32)
    tolerance = params.tolerance * params.voxel
    W = params.window

    def margin(r: np.ndarray) -> np.ndarray:
        return np.maximum(params.margin, params.margin_per_m * r)

    for k, pts in enumerate(scans()):
        if k >= n:
            break
        if k % params.stride:
            continue
        after = by_last[np.searchsorted(last_sorted, k - W):np.searchsorted(last_sorted, k)]
        before = by_first[np.searchsorted(first_sorted, k, side="right"):np.searchsorted(first_sorted, k + W, side="right")]
        cand = np.concatenate([after, before])
        if not len(cand):
            continue
        local = transform(centroids32[cand], np.linalg.inv(T_world_base[k] @ T_bs), np.float32)
        near = np.einsum("ij,ij->i", local, local) < params.max_range ** 2
        cand, local = cand[near], local[near]
        pts_sensor = transform(pts, T_sb)
        image = RangeImage(pts_sensor, params.el_bin_deg, params.az_bin_deg)
        _, free, ended = image.passes(local, tolerance, margin)
        votes[cand[free]] += 1
        hits[cand[ended]] += 1
        if progress is not None:
            progress("evidence", k + 1)
    t2 = time.perf_counter()
    hit = (votes >= (params.planar_min_free if per_voxel else 1)) & (votes > params.hit_weight * hits)
    if params.protect:
        hit &= ~protected_by_static(keys, first, last, hit, params.protect_slack, params.protect_min_seen)
    voted = np.zeros(len(keys), dtype=np.int8) - 1  # -1: not tested
    voted[tested] = hit[tested]
    dynamic = dynamic_clusters(cluster, voted, params.cluster_fraction, 1 if per_voxel else params.min_free) & ~ground
    if params.split_ratio > 0 and not per_voxel:
        dynamic = split_moved_clusters(keys, first, last, dynamic, voted, params.grow_slack, params.split_ratio,
                                       params.split_min_tested, params.cluster_fraction)
    t3 = time.perf_counter()
    return RemovalResult(keys, centroids, counts, votes, dynamic, params,
                         {"voxels": round(t1 - t0, 3), "clusters": round(t_cluster, 3),
                          "evidence": round(t2 - t1 - t_cluster, 3), "decision": round(t3 - t2, 3)},
                         first, last, cluster, ground, hits)


_NEIGHBOURS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)])


def ground_voxels(centroids: np.ndarray, cell: float, band: float) -> np.ndarray:
    """``(V,)`` bool: voxels within ``band`` [m] above the lowest voxel of their ``cell`` x ``cell`` column."""
    if not len(centroids):
        return np.zeros(0, dtype=bool)
    ij = np.floor(centroids[:, :2] / cell).astype(np.int64)
    col = (ij[:, 0] << 32) + (ij[:, 1] & 0xFFFFFFFF)
    uniq, idx = np.unique(col, return_inverse=True)
    lowest = np.full(len(uniq), np.inf)
    np.minimum.at(lowest, idx, centroids[:, 2])
    return centroids[:, 2] <= lowest[idx] + band


def scan_ground_points(points: np.ndarray, cell: float, band: float, rise: float, slope: float) -> np.ndarray:
    """``(N,)`` bool: the ground points of one scan ``(N, 3)`` (base frame, z up): within ``band`` [m] of
    the lowest point of their ``cell`` x ``cell`` column, where that lowest point is no more than
    ``rise + slope * range`` above the scan's ground level (the median lowest point of the columns
    within 20 m). Decided in the scan's own frame, so pose errors between scans cannot thicken it.
    """
    p = np.asarray(points)
    if not len(p):
        return np.zeros(0, dtype=bool)
    ij = np.floor(p[:, :2] / cell).astype(np.int64)
    col = (ij[:, 0] << 32) + (ij[:, 1] & 0xFFFFFFFF)
    order = np.argsort(col)
    idx, start = _groups(col[order])
    z = p[order, 2]
    lowest = np.minimum.reduceat(z, start)
    centre = (np.stack([np.minimum.reduceat(ij[order, 0], start), np.minimum.reduceat(ij[order, 1], start)], 1)
              + 0.5) * cell
    r = np.hypot(centre[:, 0], centre[:, 1])
    plausible = lowest - _ground_plane(centre, lowest, r) <= rise + slope * r
    out = np.empty(len(p), dtype=bool)
    out[order] = plausible[idx] & (z <= lowest[idx] + band)
    return out


def _ground_plane(xy: np.ndarray, z: np.ndarray, r: np.ndarray, rounds: int = 3) -> np.ndarray:
    """Height ``(C,)`` at ``xy`` ``(C, 2)`` of a plane fitted to the columns' lowest points ``z`` ``(C,)``:
    least squares over the columns within 30 m, then again over those within 0.2 m of it (cars,
    walls and kerbs drop out)."""
    A = np.column_stack([xy, np.ones(len(z))])
    use = r < 30.0
    if use.sum() < 3:
        use = np.ones(len(z), dtype=bool)
    coef = np.array([0.0, 0.0, float(np.median(z[use]))])
    for _ in range(rounds):
        use &= np.abs(z - A @ coef) < (1.0 if _ == 0 else 0.2)
        if use.sum() < 3:
            break
        coef = np.linalg.lstsq(A[use], z[use], rcond=None)[0]
    return A @ coef


def co_observed_clusters(keys: np.ndarray, first: np.ndarray, last: np.ndarray, members: np.ndarray,
                         slack: int, ratio: float = 0.0) -> np.ndarray:
    """Cluster id ``(V,)`` of every voxel (-1 for non-members): ``members`` joined with each
    26-neighbour member seen at overlapping times (sightings ``[first, last]`` +- ``slack`` scans).
    One object seen at one time is one cluster; so is the smear a car leaves along its lane.
    ``ratio`` > 0: only neighbours whose sighting durations (``last - first + 1 + slack`` scans)
    differ by at most this factor are joined."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    idx = np.flatnonzero(members)
    labels = np.full(len(keys), -1, dtype=np.int64)
    if not len(idx):
        return labels
    span = (last.astype(np.int64) - first + 1 + slack) if ratio > 0 else None

    def keep(src: np.ndarray, nb: np.ndarray) -> np.ndarray:
        ok = members[nb] & (first[nb] <= last[src] + slack) & (first[src] <= last[nb] + slack)
        if span is not None:
            a, b = span[src], span[nb]
            ok &= np.maximum(a, b) <= ratio * np.minimum(a, b)
        return ok

    src, nb = _neighbour_pairs(keys, idx, half=True, keep=keep)
    n = len(keys)
    graph = coo_matrix((np.ones(len(src), dtype=np.int8), (src, nb)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    labels[idx] = comp[idx]
    return labels


def _sample_clusters(cluster: np.ndarray, keys: np.ndarray, sample: int) -> np.ndarray:
    """Indices (ascending) of the voxels to test: all of a cluster up to ``sample`` voxels, about
    ``sample`` of a larger one (chosen by a hash of the voxel key: the same every run)."""
    member = np.flatnonzero(cluster >= 0)
    if not len(member):
        return member
    _, idx, size = np.unique(cluster[member], return_inverse=True, return_counts=True)
    p = np.minimum(1.0, sample / size[idx])
    return member[_unit_hash(keys[member]) < p]


def _unit_hash(keys: np.ndarray) -> np.ndarray:
    """A uniform number in [0, 1) per key (splitmix64's finaliser): deterministic sampling."""
    z = keys.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def dynamic_clusters(cluster: np.ndarray, voted: np.ndarray, fraction: float, min_voted: int) -> np.ndarray:
    """``(V,)`` bool: voxels of clusters where at least ``fraction`` of the tested voxels (and
    ``min_voted``) have a free vote (``voted``: 1 voted, 0 not, -1 not tested). A pole or a wall
    has a few voted voxels (range noise scatters points into the free space beside it); a car
    that drove on is voted nearly everywhere."""
    member = cluster >= 0
    if not member.any():
        return np.zeros(len(cluster), dtype=bool)
    uniq, idx = np.unique(cluster[member], return_inverse=True)
    tested = voted[member] >= 0
    size = np.bincount(idx, tested.astype(np.int64))
    n_voted = np.bincount(idx, (voted[member] == 1).astype(np.int64))
    good = (n_voted >= min_voted) & (n_voted >= fraction * size)
    out = np.zeros(len(cluster), dtype=bool)
    out[member] = good[idx]
    return out


def split_moved_clusters(keys: np.ndarray, first: np.ndarray, last: np.ndarray, dynamic: np.ndarray,
                         voted: np.ndarray, slack: int, ratio: float, min_tested: int, fraction: float) -> np.ndarray:
    """``(V,)`` bool: ``dynamic`` without the parts of moved clusters that were not voted themselves.

    The moved voxels are clustered again with :func:`co_observed_clusters` at ``ratio``: a car
    seen for two scans as it drove past a parked car or a pole seen for forty joined them in one
    cluster (their sightings overlap) that its votes carried; here they part. A part with at
    least ``min_tested`` tested voxels (``voted``: 1 voted, 0 not, -1 not tested) of which fewer
    than ``fraction`` were voted stays; a smaller part keeps its cluster's decision.
    """
    part = co_observed_clusters(keys, first, last, dynamic, slack, ratio)
    member = np.flatnonzero(part >= 0)
    if not len(member):
        return dynamic
    _, idx = np.unique(part[member], return_inverse=True)
    tested = np.bincount(idx, voted[member] >= 0)
    n_voted = np.bincount(idx, voted[member] == 1)
    stays = (tested >= min_tested) & (n_voted < fraction * tested)
    out = dynamic.copy()
    out[member[stays[idx]]] = False
    return out


_HALF = _NEIGHBOURS[:13]  # one of each +-offset pair: enough for an undirected graph


def _neighbour_pairs(keys: np.ndarray, of: np.ndarray, half: bool = False,
                     keep: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(src, nb)``: every occupied 26-neighbour ``nb`` of each voxel index in ``of`` (``of``
    ascending; ``half``: 13 of the 26 directions, each pair once); ``keep(src, nb)``: only the
    pairs it accepts (filtered direction by direction, so memory holds the kept pairs only). Indices
    are int32 when the voxels fit."""
    nbs = _HALF if half else _NEIGHBOURS
    offsets = (nbs[:, 0] << (2 * _BITS)) + (nbs[:, 1] << _BITS) + nbs[:, 2]
    srcs, found = [], []
    index = np.int32 if len(keys) < 2**31 else np.int64
    if len(of) and len(keys):
        base = keys[of]
        for off in offsets:
            q = base + off  # ascending like keys[of]: a cache-friendly search
            pos = np.minimum(np.searchsorted(keys, q), len(keys) - 1)
            hit = np.flatnonzero(keys[pos] == q)
            src, nb = of[hit], pos[hit]
            del q, pos, hit
            if keep is not None:
                ok = keep(src, nb)
                src, nb = src[ok], nb[ok]
            srcs.append(src.astype(index))
            found.append(nb.astype(index))
    if not srcs:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    return np.concatenate(srcs), np.concatenate(found)


def protected_by_static(keys: np.ndarray, first: np.ndarray, last: np.ndarray, dynamic: np.ndarray,
                        slack: int, min_seen: int = 0) -> np.ndarray:
    """Which voted (``dynamic``) voxels touch a static voxel that was seen before their first or after their last
    sighting (by more than ``slack`` scans): range noise scatters a pole's or a wall's points into
    the free space beside it, where later beams rightly pass; what moved has no such neighbour.
    Only neighbours seen over ``min_seen`` scans or more protect (not another car that drove the
    same lane later).
    """
    src, nb = _neighbour_pairs(keys, np.flatnonzero(dynamic))
    keep = ~dynamic[nb] & ((last[nb] > last[src] + slack) | (first[nb] < first[src] - slack)) \
        & (last[nb] - first[nb] >= min_seen)
    out = np.zeros(len(keys), dtype=bool)
    out[src[keep]] = True
    return out


def grow_dynamic(keys: np.ndarray, first: np.ndarray, last: np.ndarray, dynamic: np.ndarray, slack: int,
                 rounds: int) -> np.ndarray:
    """Spread the dynamic flag to the 26 neighbours of dynamic voxels that were seen only while
    their dynamic neighbour was (scans ``[first, last]`` inside the neighbour's, +- ``slack``):
    the rest of a car whose every voxel no beam happened to cross. A ground or wall voxel next
    to a mover is seen long before and after it, so it stays. ``rounds`` steps of one voxel.
    """
    dynamic = dynamic.copy()
    frontier = np.flatnonzero(dynamic)
    for _ in range(rounds):
        src, nb = _neighbour_pairs(keys, frontier)
        free = ~dynamic[nb]
        src, nb = src[free], nb[free]
        inside = (first[nb] >= first[src] - slack) & (last[nb] <= last[src] + slack)
        grown = np.unique(nb[inside])
        dynamic[grown] = True
        frontier = grown
    return dynamic
