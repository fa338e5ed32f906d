"""Points that moved, found while a run streams: space that recent scans saw through.

The evidence test is :class:`~submapslam.mapping.dynamic_removal.RangeImage`'s: a point lies in
free space for an earlier (or later) scan when that scan had a beam passing within
``tolerance`` of it that ended more than ``margin(r) = max(margin, margin_per_m * r)`` beyond
it. One such vote can be range noise at the edge of a wall; so the points are grouped into
clusters (26-connected non-ground voxels, :func:`~submapslam.mapping.dynamic_removal.
co_observed_clusters`) and a cluster moved when at least ``cluster_fraction`` of its tested
voxels (and ``min_votes``) were seen through. The ground is never tested.

Two users, both with bounded memory (a few recent range images, one submap's scans):

* :class:`MoverFilter` in the odometry: the scan being registered loses the clusters the last
  scans saw through (movers entering: a car driving into free space), and each scan goes into
  KISS-ICP's local map ``delay`` scans late, without the clusters the scans before *and after*
  it saw through (movers leaving: where a car was, later beams pass).
* :class:`SubmapMovers`: a closed submap's voxels that other scans of its window saw through
  go to its dynamic cloud (``map_dynamic.ply``); the rest is the submap cloud that the map,
  the place descriptors and loop registration use. A map keeps what several scans saw, so this
  side asks for more evidence (:data:`SPLIT_PARAMS`, DUFOMap's hit extension among them): a
  scan's beam that passed just over a roof, under a canopy or beside a pole, on a 16-ring
  sensor, does not count when that scan has a return within ``near_radius`` of the voxel, nor
  does any beam passing above the voxel (``pass_above``: far ground, a roof, a bonnet under a
  beam that lands beyond on the same surface); a voxel needs more scans that saw through it
  than ``hit_weight`` x the scans whose beam ended at it; an earlier submap's voxel that the new
  submap's scans hit again stays, and only its scans within ``later_max_range`` test it; and a beam
  that meets the surface at the voxel at a grazing angle (the ground far from the sensor: the
  surface's normal from the submap's points, :func:`~submapslam.mapping.local_normals.
  local_normals`) must end ``d x tan(angle to the normal)`` farther beyond it, since a beam
  passing the voxel at d (up to sqrt(2) ``tolerance`` + ``voxel`` / 4, the voxel's way off the
  surface) meets that surface up to so far on.

Frames: points ``(N, 3)`` in a scan's sensor frame (= base frame of the logs read here, or
moved by ``T_base_sensor`` first), poses ``T_world_sensor`` ``(4, 4)``. Units: metres.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..geometry import transform_points
from ..scan_intervals import ScanIntervals
from .dynamic_removal import (
    RangeImage,
    VoxelAccumulator,
    co_observed_clusters,
    dynamic_clusters,
    voxel_keys,
)
from .local_normals import VoxelSums, local_normals


@dataclass(frozen=True)
class MoverParams:
    """Settings of the streaming mover test (see the module docstring)."""

    voxel: float = 0.4  # [m] cluster / decision voxel
    margin: float = 0.5  # [m] a beam must end this far beyond a point to see through it ...
    margin_per_m: float = 0.05  # ... or this fraction of the point's range, whichever is larger
    tolerance: float = 0.25  # [m] a beam passes a point when its direction comes this close ...
    pass_above: float = float("inf")  # ... and passes at most this far above it (inf: either side)
    cluster_fraction: float = 0.3  # a cluster with this fraction of seen-through voxels moved ...
    min_votes: int = 2  # ... and at least this many
    ground_band: float = 0.3  # [m] points this close above the scan's ground are never tested
    max_range: float = 50.0  # [m] points farther from a scan get no evidence from it ...
    later_max_range: float = 50.0  # ... and in the test of earlier submaps by later scans, farther than this
    el_bin_deg: float = 0.5  # range-image pixel: elevation ...
    az_bin_deg: float = 0.4  # ... and azimuth
    near_radius: float = 0.0  # [m] a scan with a return this close to a point did not see through it (0: off)
    min_views: int = 1  # scans that must have seen a point through ...
    hit_weight: float = 0.0  # ... and more of them than this x the scans whose beam ended at it (0: off)
    protect_seen_again: bool = False  # submaps: an earlier submap's voxel the new one's scans hit again stays ...
    protect_min_scans: int = 1  # ... when this many of them hit it (or a neighbour)
    incidence: bool = False  # submaps: the margin grows by d x tan(angle of the beam to the surface normal) ...
    max_tan: float = 30.0  # ... that tangent capped here (a beam nearly along the surface) ...
    flatness: float = 0.2  # ... where the points around are a surface (local_normals: spread along / across)
    floor_cell: float = 0.0  # [m] submaps (0: off): a point at most floor_band [m] above the floor (column_floor ...
    floor_band: float = 0.4  # ... of floor_cell columns, floor_reach around, from the same cloud) casts no free ...
    floor_reach: int = 1  # ... vote: it stays a member of its cluster, never the reason it moves


SPLIT_PARAMS = MoverParams(tolerance=0.3, pass_above=0.0, near_radius=0.3, hit_weight=0.5, protect_seen_again=True,
                           protect_min_scans=10, incidence=True, later_max_range=30.0)
"""The submap split's settings (:class:`SubmapMovers`): the odometry's test (:class:`MoverFilter`) keeps
the plain ones. A map keeps what several scans saw: a voxel leaves it only when a scan saw through
it with no return of its own within ``near_radius`` (and beyond the incidence margin), more scans
saw through it than half those that ended their beam at it, and (earlier submaps) 10 of the new
submap's scans did not hit it again. Only beams at or below a voxel's height count (``pass_above``
0): a beam passing just over the ground, a roof or a bonnet lands beyond it on the same surface
(metres on at a grazing angle, farther still past a crest) and says nothing of the space at the
voxel, while a beam through or under it went where a mover stood; the window is 0.3 m instead of
0.25 since it is one-sided. An earlier submap's points are tested by the later scans within 30 m
only (``later_max_range``): farther, the odometry's drift between the two submaps (a few tenths of
a degree of tilt) moves a passing beam by a decimetre or more."""

NARROW_SPLIT_PARAMS = dataclasses.replace(SPLIT_PARAMS, tolerance=0.25, pass_above=float("inf"))
"""The split's settings for a narrow, forward-looking sensor (voxel-GICP odometry): beams on either
side of a voxel count. Such a sensor sees what it tests from ever nearer, so another scan's beam
passes a little above the earlier hits on an upright surface (a car's side) as often as not, and
a one-sided window drops that evidence (the Livox-like mover drive: DA 0.726 with both sides,
0.681 with one); its ground is dense enough for the incidence margin."""



class ViewStack:
    """The range images (:class:`~submapslam.mapping.dynamic_removal.RangeImage`) of up to
    ``capacity`` scans in a ring, each with its scan index and pose. Memory: ``capacity``
    images (16 rings at the default 0.5 x 0.4 deg pixels: 0.7 MB each)."""

    def __init__(self, capacity: int, params: MoverParams = MoverParams()) -> None:
        self.capacity = capacity
        self.params = params
        self.images: list[RangeImage | None] = [None] * capacity
        self.index = np.zeros(capacity, dtype=np.int64)
        self.valid = np.zeros(capacity, dtype=bool)
        self.T_sensor_world = np.tile(np.eye(4), (capacity, 1, 1))
        self._next = 0

    def add(self, index: int, T_world_sensor: np.ndarray, points_sensor: np.ndarray) -> None:
        """File scan ``index`` (``(N, 3)`` sensor-frame points at ``T_world_sensor``), replacing the oldest."""
        p = self.params
        k = self._next % self.capacity
        self._next += 1
        self.images[k] = RangeImage(np.asarray(points_sensor, dtype=np.float64), p.el_bin_deg, p.az_bin_deg)
        self.index[k], self.valid[k] = index, True
        self.T_sensor_world[k] = np.linalg.inv(np.asarray(T_world_sensor, dtype=np.float64))

    def subset(self, slots: np.ndarray, params: MoverParams | None = None) -> ViewStack:
        """A stack of only the scans in ``slots`` (the images shared, not copied: an image never
        changes), e.g. for work in another thread while this stack takes new scans; ``params``:
        its own settings (None: this stack's)."""
        out = ViewStack(max(1, len(slots)), self.params if params is None else params)
        for j, k in enumerate(slots):
            out.images[j], out.index[j], out.valid[j] = self.images[k], self.index[k], True
            out.T_sensor_world[j] = self.T_sensor_world[k]
        out._next = len(slots)
        return out

    def slots(self, lo: int, hi: int, most: int | None = None) -> np.ndarray:
        """Slots holding scans ``lo <= index <= hi`` in scan order; ``most``: at most that many,
        spread evenly over them (the newest always among them)."""
        found = np.flatnonzero(self.valid & (self.index >= lo) & (self.index <= hi))
        found = found[np.argsort(self.index[found], kind="stable")]
        if most is not None and len(found) > most:
            found = found[np.unique(np.round(np.linspace(len(found) - 1, 0, most)).astype(np.int64))]
        return found

    def seen_through(self, points_world: np.ndarray, slots: np.ndarray, allowed=None,
                     normals_of: Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(tested, free)``, each ``(N,)`` bool, for world points ``(N, 3)`` and the scans in ``slots``.

        ``free``: at least ``min_views`` of those scans saw through the point (:meth:`evidence`),
        more than ``hit_weight`` times as many as ended their beam at it. ``tested``: at least
        one was allowed to test it. ``allowed(slot, point_indices)`` -> bool per point (None: every point).
        ``normals_of(point_indices)`` -> ``(K, 3)`` world-frame surface normals of those points
        (zero: unknown) for the incidence margin. The incidence margin only widens the margin,
        which only turns free votes into hits, so only the points free without it are tested
        again with it (the same result as testing every point with it, for a fraction of the normals).
        """
        n_tested, n_free, n_hit = self.evidence(points_world, slots, allowed)
        free = self._decide(n_free, n_hit)
        if normals_of is not None and self.params.incidence and free.any():
            cand = np.flatnonzero(free)
            sub_allowed = None if allowed is None else (lambda k, idx: allowed(k, cand[idx]))
            _, n_free, n_hit = self.evidence(points_world[cand], slots, sub_allowed, normals_of(cand))
            free[cand] = self._decide(n_free, n_hit)
        return n_tested > 0, free

    def _within_reach(self, points_world: np.ndarray, slots: np.ndarray) -> np.ndarray:
        """Indices of the world points ``(N, 3)`` within ``max_range`` (and a millimetre) of the box
        around the sensor positions of the scans in ``slots``: every point that one of them can
        test, found in one pass instead of one per scan (most of a submap's points are beyond
        reach of most scans)."""
        if not len(slots) or not len(points_world):
            return np.zeros(0, dtype=np.int64)
        T = self.T_sensor_world[slots]
        origins = -np.einsum("kji,kj->ki", T[:, :3, :3], T[:, :3, 3])  # sensor positions (world frame)
        gap = np.maximum(np.maximum(origins.min(axis=0) - points_world, points_world - origins.max(axis=0)), 0.0)
        return np.flatnonzero(np.einsum("ij,ij->i", gap, gap) < (self.params.max_range + 1e-3) ** 2)

    def _decide(self, n_free: np.ndarray, n_hit: np.ndarray) -> np.ndarray:
        return (n_free >= self.params.min_views) & (n_free > self.params.hit_weight * n_hit)

    def evidence(self, points_world: np.ndarray, slots: np.ndarray,
                 allowed=None, normals: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(tested, free, hit)`` counts ``(N,)`` over the scans in ``slots`` for world points ``(N, 3)``:
        the scans allowed to test each point, those that saw through it (RangeImage's test: a
        beam within ``tolerance`` of it ended more than the margin beyond; within ``max_range``;
        with ``near_radius``: and no return of that scan within ``near_radius`` of it) and those
        whose beam ended at it (within the margin)."""
        p = self.params
        n = len(points_world)
        tested, free, hit = (np.zeros(n, dtype=np.int32) for _ in range(3))
        points_world = np.asarray(points_world, dtype=np.float64)

        def margin(r: np.ndarray) -> np.ndarray:
            return np.maximum(p.margin, p.margin_per_m * r)

        graze = normals is not None and p.incidence
        # d: how far a passing beam can be from the surface at the voxel: the passes() window's
        # corner (tolerance in elevation and in azimuth) and the voxel's own way off the plane
        reach = np.sqrt(2.0) * p.tolerance + p.voxel / 4

        every = np.arange(n)
        in_reach = self._within_reach(points_world, slots)  # a superset of the points any of the scans may test
        reach_mask = None
        if len(in_reach) < n:
            reach_mask = np.zeros(n, dtype=bool)
            reach_mask[in_reach] = True
        for k in slots:
            if allowed is None:  # every point (no copies of them)
                tested += 1
                cand = in_reach  # every point when all are within reach
            else:
                cand = np.flatnonzero(allowed(k, every))
                tested[cand] += 1
                if reach_mask is not None:
                    cand = cand[reach_mask[cand]]
            if not len(cand):
                continue
            candidates = points_world if len(cand) == n else points_world[cand]
            T = self.T_sensor_world[k]
            image = self.images[k]
            cand = cand[image.facing(T, candidates)]  # no beam of this scan passes the others
            local = transform_points(T, points_world[cand])
            near = np.einsum("ij,ij->i", local, local) < p.max_range ** 2
            if near.any():
                local, idx = local[near], cand[near]
                m = margin
                if graze:  # a beam passing the voxel grazes its surface: it ends on it up to d x tan(angle) on
                    extra = reach * grazing_tan(local, normals[idx] @ T[:3, :3].T, p.max_tan)
                    m = functools.partial(_plus, margin, extra)
                _, f, h = image.passes(local, p.tolerance, m, p.pass_above)
                if p.near_radius > 0 and f.any():
                    f[f] = ~image.returns_near(local[f], p.near_radius)
                free[idx[f]] += 1
                hit[idx[h]] += 1
        return tested, free, hit


def _plus(margin, extra: np.ndarray, r: np.ndarray) -> np.ndarray:
    return margin(r) + extra


def grazing_tan(points_sensor: np.ndarray, normals_sensor: np.ndarray, max_tan: float) -> np.ndarray:
    """``(N,)`` tan of the angle between each beam (sensor origin to point, ``(N, 3)``) and the surface
    normal there (``(N, 3)``, unit or zero), at most ``max_tan``; 0 where the normal is unknown (zero).

    A beam passing a surface point at distance d (perpendicular to the beam) meets the surface
    d x tan(angle) before or beyond it: a beam grazing a slope ends on the same slope metres on."""
    r = np.sqrt(np.einsum("ij,ij->i", points_sensor, points_sensor))
    cos = np.abs(np.einsum("ij,ij->i", points_sensor, normals_sensor)) / np.maximum(r, 1e-9)
    known = np.einsum("ij,ij->i", normals_sensor, normals_sensor) > 0.5
    tan = np.sqrt(np.maximum(1.0 - cos * cos, 0.0)) / np.maximum(cos, 1e-9)
    return np.where(known, np.minimum(tan, max_tan), 0.0)


def non_ground(points_sensor: np.ndarray, band: float, radius: float = 15.0, percentile: float = 2.0,
               cell: float | None = None, rise: float = 0.3, rise_per_m: float = 0.02) -> np.ndarray:
    """``(N,)`` bool: points more than ``band`` [m] above the scan's ground; all when no ground is near.

    The ground follows the terrain: a plane fitted (PCA) to the low points within ``radius`` [m]
    (those within 0.5 m of the ``percentile`` of the heights there), tilted with the road, at the
    height of that percentile (as the flat reference was). With ``cell`` (off by default: on the
    labelled mover drive it lowered the movers' DA 0.969 -> 0.940) it is bent beyond ``radius`` cell by cell: in each ``cell`` x ``cell`` [m] column the lowest point,
    when it lies within ``rise + rise_per_m * range`` [m] of the plane, is that column's ground (a
    crest, a dip, a change of grade far from the sensor); a column whose lowest point is higher (a
    canopy, a wall seen above the ground) keeps the plane. Within ``radius`` the plane alone
    decides, so the movers near the sensor are tested down to ``band`` over the road as before.
    Numpy only (the odometry's child process stays without scipy). Heights are measured along
    the plane's normal.
    """
    pts = np.asarray(points_sensor, dtype=np.float64)
    horizontal = np.hypot(pts[:, 0], pts[:, 1])
    near = pts[horizontal <= radius]
    if not len(near):
        return np.ones(len(pts), dtype=bool)
    z0 = float(np.percentile(near[:, 2], percentile))
    low = near[near[:, 2] <= z0 + 0.5]
    h = pts[:, 2] - z0
    if len(low) >= 30:
        centre = low.mean(axis=0)
        w, V = np.linalg.eigh((low - centre).T @ (low - centre) / len(low))
        normal = V[:, 0] if V[2, 0] > 0 else -V[:, 0]
        if w[1] > 1.0 and normal[2] > np.cos(np.deg2rad(20.0)):  # spread in two directions, not a wall
            h = (pts - centre) @ normal
            h -= float(np.percentile(h[horizontal <= radius], percentile))  # the low reference, as on flat ground
    if cell is None:
        return h > band
    _, inverse = np.unique(_column_keys(pts, cell), return_inverse=True)
    inverse = inverse.reshape(-1)
    lowest = np.full(int(inverse.max()) + 1 if len(inverse) else 0, np.inf)
    np.minimum.at(lowest, inverse, h)
    ground = lowest[inverse]
    allowed = rise + rise_per_m * horizontal
    ground = np.where((np.abs(ground) <= allowed) & (horizontal > radius), ground, 0.0)
    return h > ground + band


_HALF = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) > (0, 0, 0)])
# key differences to 13 of the 26 neighbours (the other 13 are their negatives), from voxel_keys itself
_HALF_OFFSETS = voxel_keys(_HALF + 0.5, 1.0) - voxel_keys(np.full((1, 3), 0.5), 1.0)


def spatial_clusters(keys: np.ndarray) -> np.ndarray:
    """Component id ``(V,)`` of sorted voxel keys (:func:`voxel_keys`) under 26-connectivity: the
    smallest index in each voxel's component. numpy only (no scipy in the odometry's child
    process): each round hooks the larger of two linked labels under the smaller, then follows
    the labels to their roots (every label is then a root), and drops the links inside one label."""
    n = len(keys)
    labels = np.arange(n)
    src, nb = [], []
    for off in _HALF_OFFSETS:
        q = keys + off
        pos = np.minimum(np.searchsorted(keys, q), max(n - 1, 0))
        hit = keys[pos] == q
        src.append(np.flatnonzero(hit))
        nb.append(pos[hit])
    src, nb = np.concatenate(src), np.concatenate(nb)
    while len(src):
        a, b = labels[src], labels[nb]
        apart = a != b  # a link inside one label stays inside one: its ends follow the same root
        if not apart.any():
            break
        src, nb, a, b = src[apart], nb[apart], a[apart], b[apart]
        np.minimum.at(labels, np.maximum(a, b), np.minimum(a, b))  # roots only ever fall
        while True:  # every voxel to its root
            jumped = labels[labels]
            if np.array_equal(jumped, labels):
                break
            labels = jumped
    return labels


def _column_keys(points: np.ndarray, cell: float) -> np.ndarray:
    """``(N,)`` int64: the ``cell`` x ``cell`` [m] column of each point ``(N, 3)``, as ``i << 32 + j``
    (|index| < 2^31), so that the column ``(di, dj)`` away is the key ``+ (di << 32) + dj``."""
    ij = np.floor(np.asarray(points)[:, :2] / cell).astype(np.int64)
    return (ij[:, 0] << 32) + ij[:, 1]


def column_floor(cloud_world: np.ndarray, query_world: np.ndarray, cell: float, reach: int = 1) -> np.ndarray:
    """``(Q,)`` [m] the floor under each query point ``(Q, 3)``: the lowest point of ``cloud_world``
    ``(N, 3)`` (same frame, z up) in the query's ``cell`` x ``cell`` [m] column and the columns up to
    ``reach`` cells away (a car's own columns see no road under it; those beside it do); -inf where
    the cloud has no point there. The ground as the cloud itself shows it, wherever the terrain
    bends (a scan's ground plane follows it only near the sensor)."""
    cloud = np.asarray(cloud_world, dtype=np.float64).reshape(-1, 3)
    query = np.asarray(query_world, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(query), np.inf)
    if not len(cloud) or not len(query):
        return np.full(len(query), -np.inf)

    keys, column = np.unique(_column_keys(cloud, cell), return_inverse=True)
    lowest = np.full(len(keys), np.inf)
    np.minimum.at(lowest, column.reshape(-1), cloud[:, 2])
    q = _column_keys(query, cell)
    for di in range(-reach, reach + 1):
        for dj in range(-reach, reach + 1):
            k = q + (di << 32) + dj
            pos = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
            found = keys[pos] == k
            out[found] = np.minimum(out[found], lowest[pos[found]])
    return np.where(np.isfinite(out), out, -np.inf)


@dataclass
class Placed:
    """A cloud placed in the world once for the mover tests of it: ``test`` ``(T,)`` the indices
    of its non-ground points (:func:`non_ground` in its own frame), ``cloud`` ``(N, 3)`` all its
    points in the world frame, ``world`` ``(T,)`` its tested points there (transformed on their
    own, as :func:`clusters_moved` always did); ``clusters``: ``(keys, inverse, labels)`` of those
    points' voxels (sorted unique :func:`voxel_keys`, each point's voxel, each voxel's
    26-connected cluster), built on first use by :func:`clusters_moved`; ``sums``: the
    :class:`~submapslam.mapping.local_normals.VoxelSums` of ``cloud`` the incidence margin's
    normals come from, built on first use by :func:`scan_votes`."""

    test: np.ndarray
    cloud: np.ndarray
    world: np.ndarray
    clusters: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    sums: VoxelSums | None = None


def place(points_sensor: np.ndarray, T_world_sensor: np.ndarray, params: MoverParams) -> Placed:
    """The :class:`Placed` cloud of ``points_sensor`` ``(N, 3)`` (its frame) at ``T_world_sensor``."""
    points_sensor = np.asarray(points_sensor, dtype=np.float64)
    test = np.flatnonzero(non_ground(points_sensor, params.ground_band))
    return Placed(test, transform_points(T_world_sensor, points_sensor),
                  transform_points(T_world_sensor, points_sensor[test]))


def above_floor(cloud_world: np.ndarray, query_world: np.ndarray, params: MoverParams) -> np.ndarray:
    """``(Q,)`` bool: the query points ``(Q, 3)`` more than ``params.floor_band`` [m] above the floor of
    ``cloud_world`` (:func:`column_floor` over ``floor_cell`` columns, ``floor_reach`` around): those that
    may cast a free vote under the floor rule (``floor_cell`` > 0)."""
    floor = column_floor(cloud_world, query_world, params.floor_cell, params.floor_reach)
    return np.asarray(query_world)[:, 2] > floor + params.floor_band


def scan_votes(points_sensor: np.ndarray, T_world_sensor: np.ndarray, views: ViewStack,
               slots: np.ndarray, params: MoverParams, placed: Placed | None = None) -> np.ndarray:
    """``(N,)`` bool: the non-ground points of one scan (sensor frame, at ``T_world_sensor``)
    that a scan in ``slots`` of ``views`` saw through (each point on its own; see :func:`clusters_moved`).
    ``placed``: the same points as :func:`place` gives them, when already at hand."""
    points_sensor = np.asarray(points_sensor, dtype=np.float64)
    out = np.zeros(len(points_sensor), dtype=bool)
    if not len(slots) or not len(points_sensor):
        return out
    if placed is None:
        test = np.flatnonzero(non_ground(points_sensor, params.ground_band))
        cloud = transform_points(T_world_sensor, points_sensor)  # all the points (the ground too)
    else:
        test, cloud = placed.test, placed.cloud
    world = cloud[test]

    def normals_of(idx: np.ndarray) -> np.ndarray:  # the surface each point lies on
        surfaces = cloud
        if placed is not None:  # tested again by the next submaps: its voxel sums are kept with it
            if placed.sums is None or placed.sums.voxel != params.voxel:
                placed.sums = VoxelSums(cloud, params.voxel)
            surfaces = placed.sums
        return local_normals(surfaces, world[idx], params.voxel, flatness=params.flatness)

    out[test] = views.seen_through(world, slots, normals_of=normals_of)[1]
    if params.floor_cell > 0 and out.any():  # near the floor: no vote (still a member of its cluster)
        voted = np.flatnonzero(out)
        out[voted] = above_floor(cloud, cloud[voted], params)
    return out


def clusters_moved(points_sensor: np.ndarray, T_world_sensor: np.ndarray, votes: np.ndarray,
                   params: MoverParams, placed: Placed | None = None) -> np.ndarray:
    """``(N,)`` bool: the points of the non-ground clusters (26-connected ``params.voxel`` voxels)
    of which at least ``cluster_fraction`` of the voxels (and ``min_votes``) hold a voted point
    (``votes`` ``(N,)``, e.g. from :func:`scan_votes`). ``placed``: the same points as
    :func:`place` gives them, when already at hand (their clusters are kept there)."""
    points_sensor = np.asarray(points_sensor, dtype=np.float64)
    out = np.zeros(len(points_sensor), dtype=bool)
    if int(votes.sum()) < params.min_votes:
        return out
    if placed is None:
        placed = place(points_sensor, T_world_sensor, params)
    if placed.clusters is None:
        keys, inverse = np.unique(voxel_keys(placed.world, params.voxel), return_inverse=True)
        placed.clusters = (keys, inverse, spatial_clusters(keys))
    keys, inverse, labels = placed.clusters
    test = placed.test
    voted = np.zeros(len(keys), dtype=np.int8)
    np.maximum.at(voted, inverse, votes[test].astype(np.int8))
    moved = dynamic_clusters(labels, voted, params.cluster_fraction, params.min_votes)
    out[test] = moved[inverse]
    return out


def moving_in_scan(points_sensor: np.ndarray, T_world_sensor: np.ndarray, views: ViewStack, slots: np.ndarray,
                   params: MoverParams) -> np.ndarray:
    """``(N,)`` bool: the points of one scan (or submap: sensor/anchor frame, at pose
    ``T_world_sensor``) in clusters that the scans in ``slots`` of ``views`` saw through."""
    votes = scan_votes(points_sensor, T_world_sensor, views, slots, params)
    return clusters_moved(points_sensor, T_world_sensor, votes, params)


class MoverFilter:
    """Keeps movers out of scan-to-map odometry (KISS-ICP's local map and each registration).

    The last ``history + delay + 1`` scans are kept as range images. :meth:`entering` marks the
    points of the scan being registered that the last ``history`` scans saw through; :meth:`add`
    files a registered scan and returns the scans now ready for the local map (``delay`` scans
    late, or sooner once ``delay_s`` seconds older than the newest scan), each without the
    clusters the scans before and after it saw through.
    """

    def __init__(self, params: MoverParams = MoverParams(), history: int = 6, delay: int = 3,
                 max_views: int = 6, test: bool = True, delay_s: float | None = None) -> None:
        """``test=False``: only the delay (nothing is tested, no range image is kept).
        ``delay_s`` [s]: a waiting scan also enters once the newest scan is this much later
        (None: ``delay`` scans alone)."""
        self.params = params
        self.test = test
        self.history = history
        self.delay = delay
        self.delay_s = delay_s
        self.max_views = max_views  # scans that test one scan, spread over those at hand
        self._views = ViewStack(history + delay + 1, params)
        self._waiting: list[tuple] = []  # (index, points, pose, votes before, time [s]) waiting for the map
        self._before: np.ndarray | None = None  # votes of the last entering() test
        self._count = 0
        self._intervals = ScanIntervals()  # between the timed scans so far
        self.dropped = 0  # points kept out of registration and the local map so far

    def entering(self, points_sensor: np.ndarray, T_world_sensor: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: points of the scan about to be registered (at its predicted pose) that the
        last ``history`` scans saw through. The votes are kept for the same points' map entry
        (:meth:`add` with the same ``points_down``)."""
        if not self.test:
            return np.zeros(len(points_sensor), dtype=bool)
        slots = self._views.slots(self._count - self.history, self._count - 1, self.max_views)
        self._before = scan_votes(points_sensor, T_world_sensor, self._views, slots, self.params)
        mask = clusters_moved(points_sensor, T_world_sensor, self._before, self.params)
        self.dropped += int(mask.sum())
        return mask

    def add(self, scan_points: np.ndarray, points_down: np.ndarray, T_world_sensor: np.ndarray,
            immediate: bool = False, timestamp: float | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
        """File a registered scan: ``scan_points`` ``(N, 3)`` (all of it, for its range image) and
        ``points_down`` ``(M, 3)`` (what goes into the map), sensor frame, at ``T_world_sensor``,
        taken at ``timestamp`` [s] (None: unknown, the count alone decides).

        Returns ``[(points, T_world_sensor)]`` to insert into the local map now: the scans that
        are ``delay`` scans old or ``delay_s`` older than this one, oldest first, without their
        moving clusters (``immediate``: this scan as it is, e.g. the first scan of an empty map,
        after the scans still waiting, as they are).
        """
        index = self._count
        self._count += 1
        if timestamp is not None:
            self._intervals.add(timestamp)
        T = np.asarray(T_world_sensor, dtype=np.float64)
        if len(scan_points) >= 10 and self.test:
            self._views.add(index, T, scan_points)
        before, self._before = self._before, None
        if immediate:
            ready = [(pts, pose) for _, pts, pose, _, _ in self._waiting] + [(points_down, T)]
            self._waiting = []
            return ready
        points_down = np.asarray(points_down, dtype=np.float64)
        if before is None or len(before) != len(points_down):
            before = np.zeros(len(points_down), dtype=bool)
        self._waiting.append((index, points_down, T, before, timestamp))
        ready = []
        while self._waiting and (len(self._waiting) > self.delay
                                  or self._old_enough(self._waiting[0][4], timestamp)):
            # the votes of the scans before it (taken at its predicted pose) and of those after it
            k, pts, pose, votes, _ = self._waiting.pop(0)
            if not self.test:
                ready.append((pts, pose))
                continue
            slots = self._views.slots(k + 1, index, self.max_views)
            votes = votes | scan_votes(pts, pose, self._views, slots, self.params)
            moved = clusters_moved(pts, pose, votes, self.params)
            self.dropped += int(moved.sum())
            ready.append((pts[~moved], pose))
        return ready

    @property
    def waiting(self) -> int:
        """Registered scans not yet in the local map."""
        return len(self._waiting)

    def flush(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """``[(points, T_world_sensor)]``: every scan still waiting, oldest first, as it is (no
        mover test: the scans after it have not been seen yet), for the local map now."""
        ready = [(pts, pose) for _, pts, pose, _, _ in self._waiting]
        self._waiting = []
        return ready

    def _old_enough(self, waiting_since: float | None, now: float | None) -> bool:
        """A scan taken at ``waiting_since`` [s] has waited ``delay_s`` by ``now`` [s], to within a
        millisecond of timestamp rounding. Never when either time or ``delay_s`` is unknown, nor
        while no two scans so far came within twice ``delay_s`` of each other: times not in
        seconds (milliseconds, nanoseconds) would let every scan in one scan late."""
        if self.delay_s is None or waiting_since is None or now is None:
            return False
        shortest = self._intervals.shortest
        if shortest is None or shortest > 2.0 * self.delay_s:
            return False
        return now - waiting_since >= self.delay_s - 1e-3


class SubmapMovers:
    """The submap side of a streaming run: each scan's thinned points while its submap grows,
    and the range images of the last ``max_views`` scans, so that a closed submap can be split
    into what stayed and what moved (:meth:`split`), and earlier submaps lose what the new one's
    scans saw through (:meth:`seen_through_later`). Memory: one submap's thinned scans,
    ``max_views`` range images, and each of the last ``placed_kept`` earlier submaps tested
    placed in the odometry frame with its voxel clusters (:class:`Placed`: tested again by each
    of the next submaps, a cloud's ground split and clusters are found once; ~1 MB a submap)."""

    def __init__(self, params: MoverParams = SPLIT_PARAMS, before: int = 10, max_views: int = 24,
                 slack: int = 1, split_views: int = 16, later_views: int = 8, view_stride: int = 2,
                 placed_kept: int = 5) -> None:
        self.params = params
        self.placed_kept = placed_kept  # earlier submaps whose placed clouds (and clusters) are kept
        self._kept: dict[bytes, Placed] = {}  # content digest of (points, pose) -> Placed, oldest first
        self.view_stride = view_stride  # a range image of every view_stride-th scan
        self.before = before
        self.slack = slack
        self.split_views = split_views  # scans (spread over the window) that test a closed submap ...
        self.later_views = later_views  # ... and of its scans, those that test each earlier submap
        self.views = ViewStack(max_views, params)
        self._occupied: tuple[int, np.ndarray] | None = None  # (first scan, voxel keys) of the newest submap
        self._scans: list[tuple[int, np.ndarray, np.ndarray]] = []  # (scan index, T_odom_sensor, thinned points)

    def add(self, index: int, T_odom_sensor: np.ndarray, points_down: np.ndarray, scan_points: np.ndarray) -> None:
        """File one registered scan (sensor frame; ``scan_points`` all of it, for its range image)."""
        if len(scan_points) >= 10 and index % self.view_stride == 0:
            self.views.add(index, T_odom_sensor, scan_points)
        self._scans.append((index, np.asarray(T_odom_sensor, dtype=np.float64), np.asarray(points_down, np.float32)))

    def take(self, scan_indices: list[int]) -> tuple:
        """The evidence for the submap of ``scan_indices``: its scans and the view slots of scans
        from ``before`` ahead of it to its end (for :meth:`split`, :meth:`seen_through_later`);
        the scans before its last are forgotten (the last one starts the next submap)."""
        first, last = scan_indices[0], scan_indices[-1]
        members = [s for s in self._scans if first <= s[0] <= last]
        self._scans = [s for s in self._scans if s[0] >= last]
        views = self.views.subset(self.views.slots(first - self.before, last))  # split runs in a worker
        return members, views, first

    def split(self, evidence: tuple, T_odom_anchor: np.ndarray, points: np.ndarray) -> np.ndarray:
        """``(M,)`` bool over a closed submap's fused ``points`` (anchor frame, anchor at
        ``T_odom_anchor``): the voxels (``params.voxel``) of its scans that other scans (outside
        each voxel's sightings, +- ``slack``) saw through, decided per cluster of voxels seen at
        overlapping times."""
        members, views, _ = evidence
        p = self.params
        if not len(points) or not members:
            return np.zeros(len(points), dtype=bool)
        acc = VoxelAccumulator(p.voxel)
        every = []
        for index, T, pts in members:
            pts = np.asarray(pts, dtype=np.float64)
            if len(pts):
                keep = non_ground(pts, p.ground_band)
                world = transform_points(T, pts)  # odometry frame
                acc.add(world[keep], index)
                every.append(world)
        keys, centroids, _, first, last = acc.result()
        if not len(keys):
            return np.zeros(len(points), dtype=bool)
        index = views.index

        def outside_sightings(k: int, vi: np.ndarray) -> np.ndarray:
            return (index[k] < first[vi] - self.slack) | (index[k] > last[vi] + self.slack)

        slots = views.slots(-(1 << 62), 1 << 62, self.split_views)

        cloud = np.concatenate(every)  # the submap's scans, ground too (odometry frame)
        del every  # (a submap's 16-ring scans: up to 700k points, 17 MB a copy)

        def normals_of(idx: np.ndarray) -> np.ndarray:
            return local_normals(cloud, centroids[idx], p.voxel, flatness=p.flatness)

        tested, free = views.seen_through(centroids, slots, outside_sightings, normals_of)
        if p.floor_cell > 0 and free.any():  # near the submap's own floor: no vote (still a cluster member)
            free &= above_floor(cloud, centroids, p)
        voted = np.where(tested, free.astype(np.int8), np.int8(-1))
        cluster = co_observed_clusters(keys, first, last, np.ones(len(keys), dtype=bool), self.slack + 1)
        moved = dynamic_clusters(cluster, voted, p.cluster_fraction, p.min_votes)
        T = np.asarray(T_odom_anchor, dtype=np.float64)
        k = voxel_keys(transform_points(T, points), p.voxel)
        pos = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
        return (keys[pos] == k) & moved[pos]

    def seen_through_later(self, evidence: tuple, T_odom_anchor: np.ndarray, points: np.ndarray) -> np.ndarray:
        """``(M,)`` bool over an *earlier* submap's ``points`` (its anchor frame, anchor at
        ``T_odom_anchor``): the clusters the new submap's scans (after its first, which the
        earlier submap shares, within ``later_max_range`` of a point) saw through: a parked car
        that left, a car seen at the edge of its own submap's window. ``evidence``: the new
        submap's, from :meth:`take`."""
        members, views, first = evidence
        later = views.slots(first + 1, 1 << 62, self.later_views)
        p = self.params
        near = views.subset(later, dataclasses.replace(p, max_range=min(p.max_range, p.later_max_range)))
        T = np.asarray(T_odom_anchor, dtype=np.float64)
        placed = self._placed(points, T)
        votes = scan_votes(points, T, near, np.arange(len(later)), p, placed)
        if self.params.protect_seen_again and votes.any():  # what the new submap's scans hit is still there
            votes[votes] = ~self._seen_again(members, first, transform_points(T, points[votes]))
        return clusters_moved(points, T, votes, self.params, placed)

    def _placed(self, points: np.ndarray, T_odom_anchor: np.ndarray) -> Placed:
        """:func:`place` of an earlier submap's ``points`` at ``T_odom_anchor``, kept for the next
        submaps' tests of the same cloud (the last ``placed_kept``; a cloud that lost points is new)."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        key = hashlib.blake2b(points.tobytes() + T_odom_anchor.tobytes(), digest_size=16).digest()
        placed = self._kept.pop(key, None)
        if placed is None:
            placed = place(points, T_odom_anchor, self.params)
        self._kept[key] = placed
        while len(self._kept) > self.placed_kept:
            self._kept.pop(next(iter(self._kept)))
        return placed

    def _seen_again(self, members: list, first: int, points_odom: np.ndarray) -> np.ndarray:
        """``(M,)`` bool: points ``(M, 3)`` (odometry frame) in or beside (26 neighbours) a voxel that
        ``protect_min_scans`` scans of the submap starting at scan ``first`` (``members``) had a point in."""
        if self._occupied is None or self._occupied[0] != first:
            keys = [np.unique(voxel_keys(transform_points(T, np.asarray(pts, dtype=np.float64)), self.params.voxel))
                    for index, T, pts in members if index > first and len(pts)]
            occupied = np.zeros(0, dtype=np.int64)
            if keys:  # hit by protect_min_scans of its scans: not a mover passing through
                occupied, scans = np.unique(np.concatenate(keys), return_counts=True)
                occupied = occupied[scans >= self.params.protect_min_scans]
            self._occupied = (first, occupied)
        occupied = self._occupied[1]
        out = np.zeros(len(points_odom), dtype=bool)
        if not len(occupied):
            return out
        k = voxel_keys(points_odom, self.params.voxel)
        for off in np.concatenate([[0], _HALF_OFFSETS, -_HALF_OFFSETS]):
            q = k + off
            pos = np.minimum(np.searchsorted(occupied, q), len(occupied) - 1)
            out |= occupied[pos] == q
        return out


def drop_from_slices(scan_points: list[np.ndarray], T_anchor_scans: np.ndarray, moved: np.ndarray,
                     voxel: float) -> list[np.ndarray]:
    """Each scan's points ``(n_k, 3)`` (sensor frame, at ``T_anchor_scans[k]``) without those in the
    ``voxel`` cells of the ``moved`` points ``(D, 3)`` (anchor frame); dtype kept."""
    gone = np.unique(voxel_keys(np.asarray(moved, dtype=np.float64), voxel))
    out = []
    for T, pts in zip(T_anchor_scans, scan_points):
        if not len(pts):
            out.append(pts)
            continue
        k = voxel_keys(transform_points(T, pts), voxel)
        pos = np.minimum(np.searchsorted(gone, k), len(gone) - 1)
        out.append(pts[gone[pos] != k])
    return out
