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
* :func:`split_submap`: a closed submap's voxels that other scans of its window saw through
  go to its dynamic cloud (``map_dynamic.ply``); the rest is the submap cloud that the map,
  the place descriptors and loop registration use.

Frames: points ``(N, 3)`` in a scan's sensor frame (= base frame of the logs read here, or
moved by ``T_base_sensor`` first), poses ``T_world_sensor`` ``(4, 4)``. Units: metres.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from .dynamic_removal import (
    RangeImage,
    VoxelAccumulator,
    co_observed_clusters,
    dynamic_clusters,
    voxel_keys,
)
from .height_band import estimate_ground_z


@dataclass(frozen=True)
class MoverParams:
    """Settings of the streaming mover test (see the module docstring)."""

    voxel: float = 0.4  # [m] cluster / decision voxel
    margin: float = 0.5  # [m] a beam must end this far beyond a point to see through it ...
    margin_per_m: float = 0.05  # ... or this fraction of the point's range, whichever is larger
    tolerance: float = 0.25  # [m] a beam passes a point when its direction comes this close
    cluster_fraction: float = 0.3  # a cluster with this fraction of seen-through voxels moved ...
    min_votes: int = 2  # ... and at least this many
    ground_band: float = 0.3  # [m] points this close above the scan's ground are never tested
    max_range: float = 50.0  # [m] points farther from a scan get no evidence from it
    el_bin_deg: float = 0.5  # range-image pixel: elevation ...
    az_bin_deg: float = 0.4  # ... and azimuth


def _margin(params: MoverParams):
    def margin(r: np.ndarray) -> np.ndarray:
        return np.maximum(params.margin, params.margin_per_m * r)
    return margin


@dataclass
class _View:
    """One scan as evidence: its range image and ``T_world_sensor`` (inverse kept)."""

    index: int
    T_world_sensor: np.ndarray
    image: RangeImage

    def seen_through(self, points_world: np.ndarray, params: MoverParams) -> np.ndarray:
        """``(N,)`` bool: this scan's beams passed the world points ``(N, 3)`` and ended beyond."""
        R, t = self.T_world_sensor[:3, :3], self.T_world_sensor[:3, 3]
        local = (points_world - t) @ R
        near = np.einsum("ij,ij->i", local, local) < params.max_range ** 2
        out = np.zeros(len(points_world), dtype=bool)
        if near.any():
            _, free, _ = self.image.passes(local[near], params.tolerance, _margin(params))
            out[near] = free
        return out


def view_of(index: int, T_world_sensor: np.ndarray, points_sensor: np.ndarray, params: MoverParams) -> _View:
    """A scan's evidence view: its range image built from ``(N, 3)`` sensor-frame points."""
    return _View(index, np.asarray(T_world_sensor, dtype=np.float64),
                 RangeImage(np.asarray(points_sensor, dtype=np.float64), params.el_bin_deg, params.az_bin_deg))


def non_ground(points_sensor: np.ndarray, band: float) -> np.ndarray:
    """``(N,)`` bool: points more than ``band`` [m] above the scan's ground (estimated per scan,
    :func:`~submapslam.mapping.height_band.estimate_ground_z`); all of them when no ground is seen."""
    ground = estimate_ground_z(points_sensor)
    if ground is None:
        return np.ones(len(points_sensor), dtype=bool)
    return points_sensor[:, 2] > ground + band


def moving_in_scan(points_sensor: np.ndarray, T_world_sensor: np.ndarray, views: list[_View],
                   params: MoverParams) -> np.ndarray:
    """``(N,)`` bool: the points of one scan (sensor frame, at pose ``T_world_sensor``) in clusters
    that the other ``views`` saw through."""
    n = len(points_sensor)
    out = np.zeros(n, dtype=bool)
    if not views or not n:
        return out
    test = np.flatnonzero(non_ground(points_sensor, params.ground_band))
    if not len(test):
        return out
    world = points_sensor[test] @ T_world_sensor[:3, :3].T + T_world_sensor[:3, 3]
    keys, inverse = np.unique(voxel_keys(world, params.voxel), return_inverse=True)
    voted_point = np.zeros(len(test), dtype=bool)
    for view in views:
        voted_point |= view.seen_through(world, params)
    voted = np.zeros(len(keys), dtype=np.int8)
    np.maximum.at(voted, inverse, voted_point.astype(np.int8))
    zero = np.zeros(len(keys), dtype=np.int32)
    cluster = co_observed_clusters(keys, zero, zero, np.ones(len(keys), dtype=bool), 0)
    moved = dynamic_clusters(cluster, voted, params.cluster_fraction, params.min_votes)
    out[test] = moved[inverse]
    return out


class MoverFilter:
    """Keeps movers out of scan-to-map odometry (KISS-ICP's local map and each registration).

    ``history`` recent scans are kept as range images. :meth:`entering` marks the points of the
    scan being registered that those scans saw through; :meth:`add` files a registered scan and
    returns the scans now ready for the local map (``delay`` scans late), each without the
    clusters the scans around it saw through. Memory: ``history`` range images and ``delay``
    thinned scans.
    """

    def __init__(self, params: MoverParams = MoverParams(), history: int = 6, delay: int = 3) -> None:
        self.params = params
        self.history = history
        self.delay = delay
        self._views: deque[_View] = deque(maxlen=history + delay + 1)
        self._waiting: deque[tuple[int, np.ndarray, np.ndarray]] = deque()  # (index, points, pose) for the map
        self._count = 0
        self.dropped = 0  # points kept out of registration and the local map so far

    def entering(self, points_sensor: np.ndarray, T_world_sensor: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: points of the scan about to be registered (at its predicted pose) that the
        last ``history`` scans saw through."""
        views = list(self._views)[-self.history:]
        mask = moving_in_scan(np.asarray(points_sensor, dtype=np.float64), T_world_sensor, views, self.params)
        self.dropped += int(mask.sum())
        return mask

    def add(self, scan_points: np.ndarray, points_down: np.ndarray, T_world_sensor: np.ndarray,
            immediate: bool = False) -> list[tuple[np.ndarray, np.ndarray]]:
        """File a registered scan: ``scan_points`` ``(N, 3)`` (all of it, for its range image) and
        ``points_down`` ``(M, 3)`` (what goes into the map), sensor frame, at ``T_world_sensor``.

        Returns ``[(points, T_world_sensor)]`` to insert into the local map now: the scan that
        is ``delay`` scans old, without its moving clusters (``immediate``: this scan, as it is,
        e.g. the first scan of an empty map; the scans waiting are released too).
        """
        index = self._count
        self._count += 1
        T = np.asarray(T_world_sensor, dtype=np.float64)
        if len(scan_points) >= 10:
            self._views.append(view_of(index, T, scan_points, self.params))
        ready: list[tuple[np.ndarray, np.ndarray]] = []
        if immediate:
            ready = [(p, pose) for _, p, pose in self._waiting] + [(points_down, T)]
            self._waiting.clear()
            return ready
        self._waiting.append((index, np.asarray(points_down, dtype=np.float64), T))
        while len(self._waiting) > self.delay:
            k, pts, pose = self._waiting.popleft()
            others = [v for v in self._views if v.index != k]
            moved = moving_in_scan(pts, pose, others, self.params)
            self.dropped += int(moved.sum())
            ready.append((pts[~moved], pose))
        return ready


def split_submap(T_anchor_scans: np.ndarray, scans_down: list[np.ndarray], views: list[_View],
                 points: np.ndarray, params: MoverParams, slack: int = 1) -> np.ndarray:
    """``(M,)`` bool: which of a submap's fused ``points`` ``(M, 3)`` (anchor frame) moved.

    ``scans_down``: the submap's scans (thinned, sensor frame) at ``T_anchor_scans`` ``(K, 4, 4)``;
    their points are voxelised at ``params.voxel`` with the first and last scan that saw each
    voxel. ``views``: range images with ``T_anchor_sensor`` poses (the submap's scans and a few
    before it), ``view.index`` counting in the same numbering as ``scans_down`` (negative:
    before the submap). A voxel is tested by the views outside its sightings (+- ``slack``
    scans); clusters of voxels seen at overlapping times are decided together.
    """
    if not len(points) or not scans_down:
        return np.zeros(len(points), dtype=bool)
    acc = VoxelAccumulator(params.voxel)
    for k, (T, pts) in enumerate(zip(T_anchor_scans, scans_down)):
        pts = np.asarray(pts, dtype=np.float64)
        if not len(pts):
            continue
        keep = non_ground(pts, params.ground_band)
        acc.add(pts[keep] @ T[:3, :3].T + T[:3, 3], k)
    keys, centroids, _, first, last = acc.result()
    if not len(keys):
        return np.zeros(len(points), dtype=bool)
    voted = np.zeros(len(keys), dtype=np.int8) - 1  # -1: no view could test it
    for view in views:
        cand = np.flatnonzero((view.index < first - slack) | (view.index > last + slack))
        if not len(cand):
            continue
        voted[cand] = np.maximum(voted[cand], 0)
        free = view.seen_through(centroids[cand], params)
        voted[cand[free]] = 1
    cluster = co_observed_clusters(keys, first, last, np.ones(len(keys), dtype=bool), slack + 1)
    moved = dynamic_clusters(cluster, voted, params.cluster_fraction, params.min_votes)
    k = voxel_keys(np.asarray(points, dtype=np.float64), params.voxel)
    pos = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
    return (keys[pos] == k) & moved[pos]


class SubmapMovers:
    """The submap side in a streaming run: each scan's thinned points and range image while its
    submap grows (and the last ``before`` scans of the previous one), so that a closed submap can
    be split into what stayed and what moved (:func:`split_submap`). Memory: one submap's scans."""

    def __init__(self, params: MoverParams = MoverParams(), before: int = 10) -> None:
        self.params = params
        self.before = before
        self._scans: list[tuple[int, np.ndarray, np.ndarray, _View | None]] = []  # (scan index, T_odom, down, view)

    def add(self, index: int, T_odom_sensor: np.ndarray, points_down: np.ndarray, scan_points: np.ndarray) -> None:
        """File one registered scan (sensor frame; ``scan_points`` all of it, for the image)."""
        view = view_of(index, T_odom_sensor, scan_points, self.params) if len(scan_points) >= 10 else None
        self._scans.append((index, np.asarray(T_odom_sensor, dtype=np.float64),
                            np.asarray(points_down, dtype=np.float32), view))

    def take(self, scan_indices: list[int], T_odom_anchor: np.ndarray) -> tuple:
        """The evidence for the submap of ``scan_indices`` (anchor ``T_odom_anchor``) as arguments
        for :meth:`split`; forgets the scans no later submap needs."""
        first = scan_indices[0]
        members = [s for s in self._scans if s[0] in set(scan_indices)]
        inv = np.linalg.inv(T_odom_anchor)
        views = []
        for idx, _, _, view in self._scans:
            if view is not None and first - self.before <= idx <= scan_indices[-1]:
                views.append(_View(idx - first, inv @ view.T_world_sensor, view.image))
        T_anchor_scans = np.array([inv @ T for _, T, _, _ in members]).reshape(-1, 4, 4)
        downs = [d for _, _, d, _ in members]
        last = scan_indices[-1]
        self._scans = [s for s in self._scans if s[0] >= last - self.before]
        return T_anchor_scans, downs, views

    def split(self, evidence: tuple, points: np.ndarray) -> np.ndarray:
        """``(M,)`` bool over a submap's ``points`` (anchor frame): what moved."""
        T_anchor_scans, downs, views = evidence
        return split_submap(T_anchor_scans, downs, views, points, self.params)
