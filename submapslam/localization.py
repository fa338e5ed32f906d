"""Localization against a fixed map (Cartographer's "pure localization"): the map never changes.

A map built once (``map.ply`` of a ``submapslam run`` output folder, or any PLY/PCD cloud) is
loaded as a rigid target; every scan of a new log is registered against it, starting from a
prediction: the previous pose composed with the wheel-odometry increment when the log has
odometry (``Scan.odometry``), else with the last increment (constant velocity).

Registration reuses the package's matchers, nothing new:

* planar maps (2D laser, z = 0): point-to-line Gauss-Newton (:func:`.registration.point_to_line.point_to_line`)
  against the map's line-like points, once with a wide and once with a tight correspondence
  distance; directions the scene does not constrain (a corridor's axis) take the prediction.
  The global search is the correlative FFT search + ICP of :func:`.registration.planar.match_planar`.
* 3D maps: generalized ICP from the prediction (small_gicp); the global search is FPFH + RANSAC,
  then GICP (:func:`.registration.correspondence.check_correspondence`).

Frames: the map's frame is the world frame (for a ``submapslam run`` folder: the pose of that
run's first scan). Every pose is ``T_world_base``, a ``(4, 4)`` float64 array; scan points are
``(N, 3)`` in the base/sensor frame.

Without an initial pose the first scan is searched for in the whole map. That global search
can pick the wrong place where the map repeats itself (identical rooms, plain corridors); it
is only accepted when its fitness clears :attr:`LocalizationConfig.relocalize_min_fitness`
and (planar) the second-best place scores clearly lower (``max_ambiguity``).

Tracking never stops because the map does not explain a scan: a robot looking into rooms the
map never saw keeps registering locally (scan points with no map wall near them match the
last ``local_window`` tracked scans, as Cartographer's local SLAM would) and resumes full
map tracking as the map comes back into view. Two fitnesses are reported per scan: over all
scan points, and over the points *inside the mapped area* (2D: the map rendered from the pose
per bearing; a beam that ends in front of every mapped wall, or has none along it, is unmapped
space and does not count; one that passes a mapped wall contradicts the map). The robot is
declared lost only when the local fit is inconsistent for ``lost_after`` scans in a row: the
fitness over the mapped area below ``min_fitness``, or a correction larger than
``max_correction`` that does not explain the scan better than the prediction. Then poses are
dead-reckoned and the global search is retried (relocalisation) on the scans gathered since
the loss, fused by dead reckoning into one cloud; the lost span's poses are re-anchored on the
fix. Global searches never run while tracking, and while lost at most every
``relocalize_every`` scans and only while they took at most ``global_time_budget`` of the wall
time so far.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from .config import LocalizationConfig
from .errors import InputError, SubmapSlamError
from .geometry import inverse, matrix_to_se2, se2_to_matrix
from .registration.point_to_line import (
    CLEAN_WALL_NOISE_M,
    first_point_per_cell,
    line_normals,
    point_to_line,
)
from .registration.wall_noise import WallNoise
from .scan import Scan

log = logging.getLogger(__name__)

PLANAR_Z_TOL = 1e-6  # a map whose |z| never exceeds this is a 2D laser map


@dataclass
class LocalizationResult:
    """Per-scan outcome of :func:`localize_log` (``N`` scans, in log order).

    ``poses`` ``(N, 4, 4)`` are ``T_world_base`` in the map frame. While ``lost`` the pose is
    dead reckoning, re-anchored on the next fix (before the first fix there is none: the
    scans before it are lost too and take the fix's dead-reckoned past).
    """

    timestamps: np.ndarray          # (N,) [s], the log's own
    poses: np.ndarray               # (N, 4, 4) T_world_base
    fitness: np.ndarray             # (N,) inlier fraction against the map, [0, 1], over all scan points
    fitness_mapped: np.ndarray      # (N,) the same over the scan points inside the mapped area only
    inlier_rmse: np.ndarray         # (N,) [m], inf without inliers
    lost: np.ndarray                # (N,) bool
    relocalisations: int = 0        # fixes by the global search after the robot was lost
    global_searches: int = 0        # global searches tried (initialisation included)
    initialised_at: int = 0         # index of the scan of the first fix (-1: never found in the map)
    timings: dict[str, float] = field(default_factory=dict)  # seconds: total, tracking, global_search
    planar: bool = True
    min_fitness: float = 0.75         # the consistency gate the scans were held to (config's)
    min_consistent_fraction: float = 0.5  # share of consistent scans needed to call the log localised
    #: (N, 6, 6) covariance of each pose (GTSAM order rx, ry, rz, x, y, z [rad, m], the pose's own
    #: frame, right perturbation): :func:`~submapslam.uncertainty.pose_filter_covariances`
    covariances: np.ndarray | None = None

    @property
    def n_scans(self) -> int:
        return len(self.timestamps)

    @property
    def consistent_fraction(self) -> float:
        """Share of the scans tracked (not lost) with the mapped area explained (``fitness_mapped``
        at least ``min_fitness``), in [0, 1]."""
        if not self.n_scans:
            return 0.0
        return float(np.mean(~self.lost & (self.fitness_mapped >= self.min_fitness)))

    @property
    def localised(self) -> bool:
        """Whether the log was found in this map: a fix, and most scans consistent with it. A log
        from another building fails here even when a poor fit was accepted now and then."""
        return bool((~self.lost).any()) and self.consistent_fraction >= self.min_consistent_fraction

    def lost_spans(self) -> list[tuple[int, int]]:
        """``[(first, last), ...]`` scan index ranges (inclusive) during which the robot was lost."""
        spans, start = [], None
        for k, flag in enumerate(self.lost):
            if flag and start is None:
                start = k
            elif not flag and start is not None:
                spans.append((start, k - 1))
                start = None
        if start is not None:
            spans.append((start, len(self.lost) - 1))
        return spans

    def summary(self) -> dict:
        """JSON-ready summary: scans, lost scans and spans, relocalisations, wall time, scans/s."""
        total = self.timings.get("total", 0.0)
        return {
            "scans": self.n_scans,
            "localised": self.localised,
            "consistent_fraction": round(self.consistent_fraction, 4),
            "lost_scans": int(self.lost.sum()),
            "lost_spans": [{"first_scan": a, "last_scan": b, "t_start": float(self.timestamps[a]),
                            "t_end": float(self.timestamps[b])} for a, b in self.lost_spans()],
            "relocalisations": self.relocalisations,
            "global_searches": self.global_searches,
            "initialised_at_scan": self.initialised_at,
            "mean_fitness": float(np.mean(self.fitness)) if self.n_scans else 0.0,
            "mean_fitness_mapped": float(np.mean(self.fitness_mapped)) if self.n_scans else 0.0,
            "wall_time_s": round(total, 3),
            "scans_per_s": round(self.n_scans / total, 1) if total > 0 else None,
            "time_s": {k: round(v, 3) for k, v in self.timings.items()},
            "planar": self.planar,
            **self._sigma_summary(),
        }

    def _sigma_summary(self) -> dict:
        """Median and largest 1σ of position (the larger of x and y, and z in 3D) [m] and yaw [deg]."""
        if self.covariances is None or not self.n_scans:
            return {}
        s = np.sqrt(np.clip(np.diagonal(self.covariances, axis1=1, axis2=2), 0.0, None))
        pos = s[:, 3:5].max(axis=1) if self.planar else s[:, 3:6].max(axis=1)
        yaw = np.degrees(s[:, 2])
        return {"sigma_position_m": {"median": round(float(np.median(pos)), 4), "max": round(float(pos.max()), 4)},
                "sigma_yaw_deg": {"median": round(float(np.median(yaw)), 3), "max": round(float(yaw.max()), 3)}}


@dataclass
class Registration:
    """One scan registered against the map: the pose and how well the map explains the scan."""

    T: np.ndarray                  # (4, 4) T_world_base
    fitness: float                 # scan points with a map point within the inlier distance / all scan points
    fitness_mapped: float          # the same inliers / scan points inside the mapped area (a map point
    #                                within ``mapped_distance``); 1.0 when none is
    rmse: float                    # [m] over the inliers, inf without inliers
    mapped_fraction: float         # scan points inside the mapped area / all scan points


def load_map(path: str | Path) -> np.ndarray:
    """Map points ``(M, 3)`` (world frame) from a run folder (its ``map.ply``) or a PLY/PCD file.

    Raises :class:`InputError` naming the file when it is missing, not a point cloud or empty.
    """
    path = Path(path)
    if path.is_dir():
        if not (path / "map.ply").is_file():
            raise InputError(path, "no map.ply in this folder (expected a `submapslam run` output folder)")
        path = path / "map.ply"
    if not path.exists():
        raise InputError(path, "no such file or directory")
    suffix = path.suffix.lower()
    if suffix not in (".ply", ".pcd"):
        raise InputError(path, "not a point cloud: the map must be a run folder, a .ply or a .pcd file")
    with open(path, "rb") as fh:
        head = fh.read(512)
    if suffix == ".ply" and not head.startswith(b"ply"):
        raise InputError(path, "not a PLY point cloud (the file does not start with 'ply')")
    if suffix == ".pcd" and not any(key in head for key in (b"VERSION", b"FIELDS")):
        raise InputError(path, "not a PCD point cloud (no VERSION/FIELDS header)")
    from ._deps import open3d

    pcd = open3d().io.read_point_cloud(str(path))
    points = np.asarray(pcd.points, dtype=np.float64)
    if len(points) == 0:
        raise InputError(path, "the map holds no points (unreadable or empty point cloud)")
    if not np.isfinite(points).all():
        points = points[np.isfinite(points).all(axis=1)]
    if len(points) < 20:
        raise InputError(path, f"the map holds only {len(points)} finite points; at least 20 are needed")
    return points


class Localizer:
    """Registers scans against a fixed map ``(M, 3)`` (world frame); the map is never modified."""

    def __init__(self, map_points: np.ndarray, config: LocalizationConfig | None = None) -> None:
        pts = np.asarray(map_points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 20:
            raise SubmapSlamError(f"the map must be (M, 3) points with M >= 20, got shape {pts.shape}")
        self.config = config or LocalizationConfig()
        self.planar = bool(np.abs(pts[:, 2]).max() <= PLANAR_Z_TOL)
        c = self.config
        self.voxel = c.voxel_size or (0.05 if self.planar else 0.4)
        self.inlier = c.inlier_distance or (0.2 if self.planar else 2.0 * self.voxel)
        self.mapped = c.mapped_distance or 5.0 * self.inlier
        self._n_bins = max(8, int(round(2 * np.pi / c.beam_width)))
        self.map_points = pts
        if self.planar:
            xy = pts[first_point_per_cell(pts[:, :2], self.voxel), :2]
            self._xy = xy
            self._render_xy = xy[first_point_per_cell(xy, 2 * self.voxel)]  # enough for 0.5 deg bearings
            self._tree = cKDTree(xy)
            self.wall_noise_m = 0.0  # [m] the scanner's scatter across walls the line test allows for
            self._map_lines(0.0)
            self._map3d = np.column_stack([xy, np.zeros(len(xy))])
        else:
            from .registration.spatial import SpatialCloud

            self._cloud = SpatialCloud(pts, self.voxel)
            self._tree = cKDTree(self._cloud.points)

    def _map_lines(self, wall_noise_m: float) -> None:
        """Planar: the map's line-like points, their normals and k-d tree, with the line test allowing
        for ``wall_noise_m`` [m] (:func:`~submapslam.registration.point_to_line.line_normals`)."""
        normals = line_normals(self._xy, self._tree, noise_m=wall_noise_m)
        line = np.isfinite(normals[:, 0])
        if line.sum() < 10:
            raise SubmapSlamError("the planar map has fewer than 10 line-like points: nothing to localise against")
        self._line_pts, self._line_normals = self._xy[line], normals[line]
        self._line_tree = cKDTree(self._line_pts)
        self.wall_noise_m = wall_noise_m

    def allow_wall_noise(self, wall_noise_m: float) -> None:
        """Planar: let the map's and the local targets' line test allow for the scanner's measured
        scatter across walls (:class:`~submapslam.registration.wall_noise.WallNoise` of the log's
        scans; a noisy scanner's map and scans keep their walls). Up to the clean scanners' figure
        nothing changes."""
        if self.planar and max(wall_noise_m, CLEAN_WALL_NOISE_M) != max(self.wall_noise_m, CLEAN_WALL_NOISE_M):
            self._map_lines(wall_noise_m)

    # --- scans ---------------------------------------------------------------------------------
    def preprocess(self, points: np.ndarray) -> np.ndarray:
        """Range-filter and voxel-downsample scan points ``(N, 3)`` (base frame) -> ``(K, 3)``."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        r = np.linalg.norm(pts, axis=1)
        pts = pts[np.isfinite(r) & (r >= self.config.min_range) & (r <= self.config.max_range)]
        if self.planar:
            pts = pts[first_point_per_cell(pts[:, :2], self.voxel)]
            pts[:, 2] = 0.0
            return pts
        from .submaps import voxel_downsample

        return voxel_downsample(pts, self.voxel / 2) if len(pts) else pts

    def localize(self, scan: np.ndarray, odometry_prior: np.ndarray) -> tuple[np.ndarray, float, float]:
        """Register preprocessed scan points ``(N, 3)`` (base frame) starting from the predicted
        ``T_world_base`` ``odometry_prior`` ``(4, 4)``.

        Returns ``(T_world_base (4, 4), fitness, inlier_rmse)``: fitness is the fraction of scan
        points with a map point within the inlier distance, RMSE is over those inliers [m].
        :meth:`register` gives the fitness over the mapped area too.
        """
        reg = self.register(scan, odometry_prior)
        return reg.T, reg.fitness, reg.rmse

    def register(self, scan: np.ndarray, odometry_prior: np.ndarray,
                 local: _LocalTarget | None = None) -> Registration:
        """Like :meth:`localize`, returning a :class:`Registration`. ``local`` (planar): recent
        scans as a fallback target for the scan points with no map wall near them (unmapped
        space), so they steady the fit instead of being matched to a wrong wall."""
        prior = np.asarray(odometry_prior, dtype=np.float64)
        if len(scan) < 20:
            return Registration(prior, 0.0, 0.0, float("inf"), 0.0)
        if self.planar:
            xyt0 = matrix_to_se2(prior)
            xyt = xyt0
            tree, target, normals = ((self._line_tree, self._line_pts, self._line_normals) if local is None
                                     else (local, local.points, local.normals))
            for max_corr, kernel in ((3.0 * self.inlier, 2.0 * self.inlier / 4), (self.inlier, self.inlier / 4)):
                xyt, _ = point_to_line(scan[:, :2], xyt, tree, target, normals,
                                       max_correspondence=max_corr, kernel=kernel, prior_xyt=xyt0, iterations=8)
            T = se2_to_matrix(*xyt)
        else:
            T = self._gicp_pose(scan, prior)
        return self.score(scan, T)

    def score(self, scan: np.ndarray, T: np.ndarray) -> Registration:
        """How well the map explains scan points ``(N, 3)`` (base frame) at ``T_world_base``.

        Planar: the map is rendered from the pose as a range per bearing (``beam_width``); a scan
        point is *in the mapped area* when it is an inlier or its beam passes a mapped wall by
        more than ``see_through`` (the map says that space is blocked); a beam that ends in front
        of every mapped wall, or has none along it, looks into space the map does not explain
        (an unmapped room, furniture, people) and is no evidence either way. 3D: in the mapped
        area when a map point is within ``mapped_distance``.
        """
        n = len(scan)
        if n == 0:
            return Registration(T, 0.0, 0.0, float("inf"), 0.0)
        if self.planar:
            moved = scan[:, :2] @ T[:2, :2].T + T[:2, 3]
            d, _ = self._tree.query(moved, distance_upper_bound=self.inlier)
            inl = np.isfinite(d)
            expected = self._render(T)
            r = np.hypot(scan[:, 0], scan[:, 1])
            b = self._bearing_bins(scan[:, 0], scan[:, 1])
            through = ~inl & (r > expected[b] + self.config.see_through)
            n_map = int(inl.sum() + through.sum())
        else:
            moved = scan @ T[:3, :3].T + T[:3, 3]
            d, _ = self._tree.query(moved, distance_upper_bound=self.mapped)
            inl = d <= self.inlier
            n_map = int(np.isfinite(d).sum())
        n_inl = int(inl.sum())
        rmse = float(np.sqrt(np.mean(d[inl] ** 2))) if n_inl else float("inf")
        return Registration(T, n_inl / n, n_inl / n_map if n_map else 1.0, rmse, n_map / n)

    def information(self, scan: np.ndarray, T: np.ndarray) -> np.ndarray:
        """``(6, 6)`` information (GTSAM order, the scan's frame) that matching scan points ``(N, 3)``
        (base frame) against the map at ``T_world_base`` gives about the pose; only map points count
        (never the recent scans of unmapped space). Planar: point-to-line
        (:func:`~submapslam.uncertainty.planar_match_information`); 3D: the point-to-point
        information over the inlier RMSE squared, divided by the same inflation."""
        from .uncertainty import (
            REGISTRATION_INFLATION,
            limited_by_the_map,
            planar_match_information,
        )

        if len(scan) < 20:
            return np.zeros((6, 6))
        if self.planar:
            moved = scan[:, :2] @ T[:2, :2].T + T[:2, 3]
            d, i = self._line_tree.query(moved, distance_upper_bound=self.inlier)
            ok = np.isfinite(d)
            n = self._line_normals[i[ok]]
            r = np.einsum("ij,ij->i", moved[ok] - self._line_pts[i[ok]], n)
            w = 1.0 / (1.0 + (r / (self.inlier / 4)) ** 2)
            return limited_by_the_map(planar_match_information(scan[ok, :2], n @ T[:2, :2], r, w), True)
        from .registration.spatial import SpatialCloud, registration_fit, source_pose_information

        src = SpatialCloud(scan, self.voxel)
        fitness, rmse = registration_fit(src, self._cloud, T, self.inlier)
        if round(fitness * len(src.points)) < 20:
            return np.zeros((6, 6))
        body = source_pose_information(src, self._cloud, T, self.inlier)  # about the scan pose, its own frame
        var = max(rmse**2, (self.voxel / 4) ** 2)
        return limited_by_the_map(body / (var * REGISTRATION_INFLATION), False)

    def _bearing_bins(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        nb = self._n_bins
        return ((np.arctan2(y, x) + np.pi) * (nb / (2 * np.pi))).astype(np.int64) % nb

    def _render(self, T: np.ndarray) -> np.ndarray:
        """Planar: range to the nearest map point per bearing bin seen from ``T`` ``(n_bins,)``
        (inf where none within ``max_range``), widened by one bin to close gaps between points."""
        m = (self._render_xy - T[:2, 3]) @ T[:2, :2]
        r = np.hypot(m[:, 0], m[:, 1])
        near = r <= self.config.max_range
        m, r = m[near], r[near]
        b = self._bearing_bins(m[:, 0], m[:, 1])
        z = np.full(self._n_bins, np.inf)
        np.minimum.at(z, b, r)
        return np.minimum(z, np.minimum(np.roll(z, 1), np.roll(z, -1)))

    def local_target(self, recent_world_xy: list[np.ndarray]) -> _LocalTarget | None:
        """Planar: the map's walls plus recent scans ``(K_i, 2)`` (world frame) as one target."""
        pts = np.concatenate(recent_world_xy)
        pts = pts[first_point_per_cell(pts, self.voxel)]
        if len(pts) < 10:
            return None
        normals = line_normals(pts, cKDTree(pts), noise_m=self.wall_noise_m)
        line = np.isfinite(normals[:, 0])
        return _LocalTarget(self, pts[line], normals[line]) if line.sum() >= 10 else None

    def _gicp_pose(self, scan: np.ndarray, guess: np.ndarray) -> np.ndarray:
        from .registration.spatial import SpatialCloud, gicp

        src = SpatialCloud(scan, self.voxel)
        T = guess
        for dist in (3.0 * self.inlier, self.inlier):
            T = gicp(src, self._cloud, T, dist)
        return T

    def global_search(self, cloud: np.ndarray) -> tuple[np.ndarray, float, float, float]:
        """Find ``cloud`` ``(N, 3)`` (base frame) anywhere in the map, without a guess.

        Returns ``(T_world_base, fitness, inlier_rmse, ambiguity)`` (fitness over the cloud's
        points inside the mapped area); ambiguity is the score of
        the best clearly different place over the best (planar; 0 for 3D). Can fail where the
        map repeats itself: check fitness and ambiguity before trusting the pose.
        """
        if len(cloud) < 20:
            return np.eye(4), 0.0, float("inf"), 1.0
        if self.planar:
            from .registration.planar import match_planar

            m = match_planar(cloud, self._map3d, resolution=0.1, inlier_distance=self.inlier)
            reg = self.register(cloud, m.T)
            return reg.T, reg.fitness_mapped, reg.rmse, float(m.ambiguity)
        from .registration.correspondence import check_correspondence
        from .registration.spatial import SpatialCloud

        res = check_correspondence(SpatialCloud(cloud, self.voxel), self._cloud, planar=False,
                                   voxel_size=self.voxel)
        reg = self.register(cloud, res.T_target_source)
        return reg.T, reg.fitness_mapped, reg.rmse, 0.0


class _LocalTarget:
    """Point-to-line target (duck-types the ``cKDTree.query`` used by :func:`point_to_line`): a scan
    point takes the nearest map wall point; only a point with none within the bound takes the
    nearest point of the recent scans. Indices address ``points``/``normals`` (map first)."""

    def __init__(self, loc: Localizer, pts: np.ndarray, normals: np.ndarray) -> None:
        self._map_tree, self._n_map = loc._line_tree, len(loc._line_pts)
        self._tree = cKDTree(pts)
        self.points = np.vstack([loc._line_pts, pts])
        self.normals = np.vstack([loc._line_normals, normals])

    def query(self, x: np.ndarray, distance_upper_bound: float) -> tuple[np.ndarray, np.ndarray]:
        d, i = self._map_tree.query(x, distance_upper_bound=distance_upper_bound)
        miss = ~np.isfinite(d)
        if miss.any():
            d2, i2 = self._tree.query(x[miss], distance_upper_bound=distance_upper_bound)
            d[miss] = d2
            i[miss] = i2 + self._n_map
        return d, i


def parse_initial_pose(initial_pose: np.ndarray | tuple | str | None) -> np.ndarray | None:
    """``"x y yaw"`` (string or 3 numbers) or a ``(4, 4)`` matrix -> ``T_world_base``, or None."""
    if initial_pose is None:
        return None
    if isinstance(initial_pose, str):
        try:
            vals = [float(v) for v in initial_pose.replace(",", " ").split()]
        except ValueError:
            vals = []
        if len(vals) != 3:
            raise SubmapSlamError(f"initial pose {initial_pose!r}: expected three numbers \"x y yaw\" (yaw in rad)")
        return se2_to_matrix(*vals)
    arr = np.asarray(initial_pose, dtype=np.float64)
    if arr.shape == (3,):
        return se2_to_matrix(*arr)
    if arr.shape != (4, 4) or not np.isfinite(arr).all():
        raise SubmapSlamError(f"initial pose must be (x, y, yaw) or a finite (4, 4) matrix, got shape {arr.shape}")
    return arr


#: planar: the log's first scans, on which the scanner's wall noise is measured before the line
#: tests allow for it (:meth:`Localizer.allow_wall_noise`)
WALL_NOISE_SCANS = 20


def localize_log(
    log_reader: Iterable[Scan],
    map_dir_or_points: str | Path | np.ndarray,
    initial_pose: np.ndarray | tuple | str | None = None,
    *,
    config: LocalizationConfig | None = None,
    start: int = 0,
    max_scans: int | None = None,
    on_scan: Callable[[int], None] | None = None,
) -> LocalizationResult:
    """Localise every scan of ``log_reader`` (scans in log order) in a fixed map.

    ``map_dir_or_points``: a run folder, a PLY/PCD file, or ``(M, 3)`` points (world frame).
    ``initial_pose``: ``T_world_base`` of the first localised scan (``(4, 4)``, ``(x, y, yaw)``
    or ``"x y yaw"``); None: global search in the whole map. ``start`` skips that many scans
    of the log, ``max_scans`` stops after that many localised scans. ``on_scan(k)`` is called
    after each scan (progress). The map is not modified.
    """
    cfg = config or LocalizationConfig()
    t_total = time.perf_counter()
    points = map_dir_or_points if isinstance(map_dir_or_points, np.ndarray) else load_map(map_dir_or_points)
    loc = Localizer(points, cfg)
    T0 = parse_initial_pose(initial_pose)
    stamps, poses, regs, lost = [], [], [], []
    infos: list[np.ndarray | None] = []  # what each believed match says about its pose (None: not believed)
    t_track = t_global = 0.0
    tracking = T0 is not None   # False: searching (initialisation or lost)
    ever_fixed = tracking
    initialised_at = 0
    n_relocs = n_searches = 0
    bad_streak = 0
    pending: list[int] = []     # indices since tracking became doubtful (dead-reckoned, re-anchored on a fix)
    dr: list[np.ndarray] = []   # dead-reckoning chain T_dr_base of every scan (prediction increments only)
    clouds: list[np.ndarray] = []  # preprocessed points of the pending scans
    recent: deque[np.ndarray] = deque(maxlen=cfg.local_window)  # planar: recent tracked scans, world frame
    local: _LocalTarget | None = None
    since_local = 0
    last_wheel: np.ndarray | None = None
    last_delta = np.eye(4)
    since_search = 0
    wall_noise = WallNoise()  # planar: the scanner's scatter across walls, over the first scans
    k = -1
    for n, scan in enumerate(log_reader):
        if n < start:
            continue
        if max_scans is not None and k + 1 >= max_scans:
            break
        k += 1
        if scan.planar != loc.planar:
            raise InputError(scan.source or f"scan {scan.index}",
                             f"a {'2D' if scan.planar else '3D'} scan cannot be localised in a "
                             f"{'2D (planar)' if loc.planar else '3D'} map")
        wheel = scan.odometry if cfg.use_wheel_odometry else None
        delta = inverse(last_wheel) @ wheel if (wheel is not None and last_wheel is not None) else last_delta
        if loc.planar:
            delta = se2_to_matrix(*matrix_to_se2(delta))
        last_wheel = wheel
        dr.append(np.eye(4) if k == 0 else dr[-1] @ delta)
        if loc.planar and k < WALL_NOISE_SCANS:
            wall_noise.add(scan.points[:, :2])
            if k == WALL_NOISE_SCANS - 1:  # the scanner's noise known: the line tests allow for it from here on
                loc.allow_wall_noise(wall_noise.sigma_m)
        pts = loc.preprocess(scan.points)
        stamps.append(scan.timestamp)
        prev = poses[-1] if poses else (T0 if T0 is not None else np.eye(4))
        prior = prev if k == 0 else prev @ delta
        if tracking:
            t = time.perf_counter()
            reg = loc.register(pts, prior, local)
            why = _inconsistency(reg, pts, prior, loc, cfg)
            if why is None:
                bad_streak = 0
                pending.clear()
                clouds.clear()
                poses.append(reg.T)
                infos.append(loc.information(pts, reg.T))
                if loc.planar and len(pts):
                    recent.append(pts[:, :2] @ reg.T[:2, :2].T + reg.T[:2, 3])
                    since_local += 1
                    if local is None or since_local >= cfg.local_rebuild_every:
                        local, since_local = loc.local_target(list(recent)), 0
            else:
                bad_streak += 1
                pending.append(k)
                clouds.append(pts)
                poses.append(prior)  # the fit is not believed: dead reckoning until it is consistent again
                infos.append(None)
            regs.append(reg)
            lost.append(False)
            t_track += time.perf_counter() - t
            if why is not None and bad_streak >= cfg.lost_after:
                log.info("lost at scan %d (%s for %d scans)", k, why, bad_streak)
                tracking = False
                since_search = cfg.relocalize_every  # search right away (within the time budget)
                recent.clear()
                local = None
                for j in pending:
                    lost[j] = True
        else:
            poses.append(prior)
            infos.append(None)
            regs.append(loc.score(pts, prior))
            lost.append(True)
            pending.append(k)
            clouds.append(pts)
            since_search += 1
            elapsed = time.perf_counter() - t_total
            # before the first fix the first scans each get a search (the fused cloud grows), then
            # one every relocalize_every scans; once lost, the same within the time budget
            if (not ever_fixed and (k < cfg.global_scans or since_search >= cfg.relocalize_every)) or (
                    since_search >= cfg.relocalize_every and t_global <= cfg.global_time_budget * elapsed):
                since_search = 0
                del clouds[:-cfg.global_scans]
                t = time.perf_counter()
                recent_idx = pending[-len(clouds):]
                fused = _fuse(clouds, [inverse(dr[k]) @ dr[j] for j in recent_idx], loc)
                T, fit, _, amb = loc.global_search(fused)
                n_searches += 1
                if fit >= cfg.relocalize_min_fitness and amb <= cfg.max_ambiguity:
                    cur = loc.register(pts, T)
                    if cur.fitness_mapped >= fit - 0.05:
                        T = cur.T
                    log.info("fix at scan %d: fitness %.2f, ambiguity %.2f", k, fit, amb)
                    _reanchor(poses, dr, pending, k, T)
                    poses[k], regs[k], lost[k], infos[k] = T, loc.score(pts, T), False, loc.information(pts, T)
                    if ever_fixed:
                        n_relocs += 1
                    else:
                        initialised_at = k
                        ever_fixed = True
                        last_delta = np.eye(4)
                    tracking = True
                    bad_streak = 0
                    pending.clear()
                    clouds.clear()
                t_global += time.perf_counter() - t
        if k >= 1:
            last_delta = inverse(poses[-2]) @ poses[-1] if not lost[-1] else delta
        if on_scan is not None:
            on_scan(k)
    if k < 0:
        raise SubmapSlamError("the log holds no scans to localise")
    if not ever_fixed:
        log.warning("the robot was not found in the map in %d scans (%d global searches)", k + 1, n_searches)
    from .uncertainty import pose_filter_covariances

    covariances = pose_filter_covariances(np.stack(poses), infos, np.asarray(lost, dtype=bool), loc.planar)
    timings = {"total": time.perf_counter() - t_total, "tracking": t_track, "global_search": t_global}
    return LocalizationResult(
        timestamps=np.asarray(stamps, dtype=np.float64), poses=np.stack(poses),
        fitness=np.asarray([r.fitness for r in regs]), fitness_mapped=np.asarray([r.fitness_mapped for r in regs]),
        inlier_rmse=np.asarray([r.rmse for r in regs]), lost=np.asarray(lost, dtype=bool), relocalisations=n_relocs,
        global_searches=n_searches, initialised_at=initialised_at if ever_fixed else -1, timings=timings,
        planar=loc.planar, min_fitness=cfg.min_fitness, min_consistent_fraction=cfg.min_consistent_fraction,
        covariances=covariances)


def _inconsistency(reg: Registration, scan: np.ndarray, prior: np.ndarray, loc: Localizer,
                   cfg: LocalizationConfig) -> str | None:
    """Why the local fit ``reg`` of ``scan`` (started from ``prior``) cannot be believed, or None.

    Few scan points near the map (looking into space the map never saw) is no reason: the
    fit of the points that are near it, held to the prediction elsewhere, is still the best
    estimate. A correction far larger than a prediction error, or most of the *mapped* points
    missing the map's walls, is.
    """
    if reg.mapped_fraction >= cfg.min_mapped_fraction and reg.fitness_mapped < cfg.min_fitness:
        return f"fitness over the mapped area {reg.fitness_mapped:.2f}"
    corr = inverse(prior) @ reg.T
    if (np.linalg.norm(corr[:3, 3]) > cfg.max_correction
            or abs(np.arctan2(corr[1, 0], corr[0, 0])) > cfg.max_correction_yaw):
        # a large correction is believed only when it explains the scan clearly better than the
        # prediction (snapping back after drift); otherwise the fit ran off along some wall
        if reg.fitness < loc.score(scan, prior).fitness + 0.1:
            return "correction jump without a better fit"
    return None


def _fuse(clouds: list[np.ndarray], T_cur_j: list[np.ndarray], loc: Localizer) -> np.ndarray:
    """Scan clouds moved into the current base frame by ``T_cur_j`` and downsampled: ``(K, 3)``."""
    pts = np.vstack([c @ T[:3, :3].T + T[:3, 3] for c, T in zip(clouds, T_cur_j)])
    if loc.planar:
        return pts[first_point_per_cell(pts[:, :2], loc.voxel)]
    from .submaps import voxel_downsample

    return voxel_downsample(pts, loc.voxel / 2)


def _reanchor(poses: list[np.ndarray], dr: list[np.ndarray], pending: list[int], k: int, T_fix: np.ndarray) -> None:
    """Poses of the dead-reckoned scans ``pending`` re-expressed relative to the fix at scan ``k``."""
    T_world_dr = T_fix @ inverse(dr[k])
    for j in pending:
        poses[j] = T_world_dr @ dr[j]
