"""Local submaps: consecutive scans fused in the submap's own anchor frame (virtual sensors).

A submap's anchor is the pose of its first scan. Scans are stored as ``T_anchor_scan`` and
their points are fused into a voxel-downsampled cloud in the anchor frame. Once closed a
submap is a rigid unit; the global optimiser only moves its anchor.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .config import SubmapConfig
from .geometry import inverse, transform_points


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Keep one point (the centroid) per occupied voxel; ``(N, 3)`` -> ``(M, 3)``."""
    from kiss_icp.voxelization import voxel_down_sample

    if len(points) == 0:
        return points.reshape(0, 3)
    return np.asarray(voxel_down_sample(np.ascontiguousarray(points), voxel), dtype=np.float64)


def compact_points(points: np.ndarray, float16_reach: float = 256.0) -> np.ndarray:
    """``(M, 3)`` anchor-frame points in the smallest float type that keeps them to a few cm.

    float16 (6 bytes a point) while every coordinate is within ``float16_reach`` m of the
    anchor: at most 3 cm off below 128 m, 6 cm below 256 m — a tenth of the 0.4 m submap voxel
    or less; float32 beyond. numpy promotes them in any arithmetic with float64 poses.
    """
    if len(points) and np.abs(points).max() < float16_reach:
        return points.astype(np.float16)
    return points.astype(np.float32)


#: scans a 3D submap holds at least before its travel cuts it (``submaps.min_scans``)
MIN_SCANS_3D = 10


@dataclass
class Submap:
    """A closed (or growing) submap.

    Attributes:
        id: 0-based submap index (= its node key in the pose graph).
        scan_indices: indices of the scans fused into it, in order.
        T_odom_anchor: ``(4, 4)`` anchor pose in the odometry frame (before optimisation).
        T_anchor_scans: ``(K, 4, 4)`` scan poses in the anchor frame.
        points: ``(M, 3)`` fused, voxel-downsampled points in the anchor frame: float64 for planar
            submaps; for 3D ones compact (:func:`compact_points`: a long drive keeps hundreds),
            and once closed and out of the mover split's reach, read back from the run's spill
            file on each access (:meth:`keep_points_elsewhere`).
        distance: path length covered [m].
        planar: 2D laser submap (all z = 0).
        scan_points: each scan's ``(n, 3)`` points in its sensor frame, kept for the evidence
            grids, which need the rays: all points of a 2D laser scan; for 3D scans, the
            obstacle slice the builder's ``grid_points`` gives, in float16 (empty without one).
        dynamic_points: 3D with ``mapping.split_movers``: ``(D, 3)`` the fused points (anchor frame,
            compact) that other scans saw through, taken out of ``points``; None when not split.
        scan_no_returns: planar: each scan's ``(m, 3)`` float32 ends of its beams that returned
            nothing (:attr:`~submapslam.scan.Scan.no_returns`; free space for the grids, not
            points); empty when the log gives none.
    """

    id: int
    scan_indices: list[int]
    T_odom_anchor: np.ndarray
    T_anchor_scans: np.ndarray
    points: np.ndarray
    distance: float
    planar: bool
    scan_points: list[np.ndarray] = field(default_factory=list)
    descriptor: np.ndarray | None = None
    dynamic_points: np.ndarray | None = None
    scan_no_returns: list[np.ndarray] = field(default_factory=list)

    def keep_points_elsewhere(self, read: Callable[[], np.ndarray]) -> None:
        """From now on ``points`` is ``read()`` (the same array, e.g. read back from disk each
        time), until ``points`` is set again."""
        self.__dict__["_read_points"] = read
        self.__dict__["_points"] = None  # after the reader is set: a concurrent reader sees one of the two

    def __getstate__(self) -> dict:
        """Pickled with its points (a reader of a file need not survive the trip)."""
        state = dict(self.__dict__)
        state["_points"], state["_read_points"] = self.points, None
        return state


def _submap_points(submap: Submap) -> np.ndarray:
    """``Submap.points``: the array held, else what the reader given to ``keep_points_elsewhere`` reads."""
    points = submap.__dict__["_points"]
    return points if points is not None else submap.__dict__["_read_points"]()


def _set_submap_points(submap: Submap, points: np.ndarray) -> None:
    """``submap.points = points``: held in memory (a reader set before is forgotten)."""
    submap.__dict__["_points"] = points
    submap.__dict__["_read_points"] = None


# ``points`` behind a property: the dataclass's __init__ and replace() go through it, and
# :meth:`Submap.keep_points_elsewhere` can hand the array to a store
Submap.points = property(_submap_points, _set_submap_points)  # type: ignore[assignment]


class SubmapBuilder:
    """Accumulate registered scans; emit a :class:`Submap` when a cut criterion is met.

    Consecutive submaps share one scan: the last scan of submap k is the anchor of k + 1, so
    the odometry edge between anchors is exactly the last ``T_anchor_scan`` of submap k.
    """

    def __init__(self, config: SubmapConfig, voxel_size: float, planar: bool,
                 grid_points: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
        """``grid_points`` maps a 3D scan ``(N, 3)`` to the points an occupancy grid should trace
        rays to (e.g. :func:`~submapslam.mapping.height_band.obstacle_points`); planar scans
        are kept whole."""
        self.config = config
        self.voxel = voxel_size
        self.planar = planar
        self.grid_points = grid_points
        self.max_distance = config.max_distance or (5.0 if planar else 12.0)
        self.min_scans = config.min_scans or (1 if planar else MIN_SCANS_3D)
        self._next_id = 0
        self._reset(None)

    def _reset(self, seed: tuple | None) -> None:
        self._indices: list[int] = []
        self._poses: list[np.ndarray] = []
        self._chunks: list[np.ndarray] = []
        self._scan_points: list[np.ndarray] = []
        self._scan_no_returns: list[np.ndarray] = []
        self._buffered = 0
        self._fused = np.zeros((0, 3))
        self._distance = 0.0
        self._T_odom_anchor: np.ndarray | None = None
        if seed is not None:
            self.add(*seed)

    @property
    def current_anchor(self) -> np.ndarray | None:
        """``T_odom_anchor`` of the submap being built, or None before the first scan."""
        return self._T_odom_anchor

    def add(self, index: int, T_odom_scan: np.ndarray, points: np.ndarray,
            full_scan: np.ndarray | None = None, no_returns: np.ndarray | None = None) -> Submap | None:
        """Add one scan (points ``(N, 3)`` in its sensor frame); return a submap when one closes.

        ``full_scan``: the scan before thinning, when ``points`` is thinned; the occupancy grid's
        obstacle slice is taken from it (finer than the submap voxel). ``no_returns``: planar,
        ``(M, 3)`` ends of the scan's beams that returned nothing (free space for the grid).
        """
        if self._T_odom_anchor is None:
            self._T_odom_anchor = T_odom_scan.copy()
        T_anchor_scan = inverse(self._T_odom_anchor) @ T_odom_scan
        if self._poses:
            self._distance += float(np.linalg.norm(T_anchor_scan[:3, 3] - self._poses[-1][:3, 3]))
        self._indices.append(index)
        self._poses.append(T_anchor_scan)
        self._chunks.append(transform_points(T_anchor_scan, points))
        if self.planar:
            self._scan_points.append(points.astype(np.float32))
            self._scan_no_returns.append(np.zeros((0, 3), np.float32) if no_returns is None
                                         else no_returns.astype(np.float32))
        elif self.grid_points is not None:
            # float16: at most 3 cm off at 64-128 m range, a sixth of a 0.2 m grid cell, in half the
            # memory (a long drive keeps every scan's slice until the grid is built)
            self._scan_points.append(self.grid_points(points if full_scan is None else full_scan).astype(np.float16))
        self._buffered += len(points)
        if self._buffered > 50_000:
            self._compact()
        if (self._distance >= self.max_distance and len(self._indices) >= self.min_scans) \
                or len(self._indices) >= self.config.max_scans:
            submap = self._close()
            self._reset((index, T_odom_scan, points, full_scan, no_returns))
            return submap
        return None

    def _compact(self) -> None:
        if self._chunks:
            self._fused = voxel_downsample(np.vstack([self._fused, *self._chunks]), self.voxel)
            self._chunks = []
            self._buffered = 0

    def _close(self) -> Submap:
        self._compact()
        submap = Submap(
            id=self._next_id,
            scan_indices=list(self._indices),
            T_odom_anchor=self._T_odom_anchor.copy(),
            T_anchor_scans=np.array(self._poses),
            points=self._fused if self.planar else compact_points(self._fused),
            distance=self._distance,
            planar=self.planar,
            scan_points=list(self._scan_points),
            scan_no_returns=list(self._scan_no_returns) if any(len(r) for r in self._scan_no_returns) else [],
        )
        self._next_id += 1
        return submap

    def flush(self) -> Submap | None:
        """Close the submap being built (end of log); None when it holds only the shared scan."""
        if len(self._indices) <= 1 and self._next_id > 0:
            return None
        if not self._indices:
            return None
        submap = self._close()
        self._reset(None)
        return submap

    def current_points(self) -> np.ndarray:
        """Points of the growing submap, ``(M, 3)`` in its anchor frame."""
        self._compact()
        return self._fused
