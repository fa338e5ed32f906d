"""Correspondence test between two submaps: coarse alignment, fine registration, gates.

``check_correspondence(source, target, ...)`` estimates ``T_target_source`` without needing a
good initial guess and decides whether the two submaps really show the same place:

* planar submaps (2D laser, z = 0): correlative FFT search + ICP in SE(2)
  (:mod:`.planar`); the 3D point-to-plane / GICP systems are singular on planar data;
* 3D submaps: FPFH features + a seeded RANSAC (:func:`.spatial.feature_ransac`) when there is no
  usable guess, then generalized ICP (small_gicp); information from the point-to-point
  correspondences (:func:`.spatial.source_pose_information`); for tests that are not a refinement, the
  agreement of the structure (non-ground points, :func:`.spatial.structure_agreement`).

Gates: fitness (source points with a target neighbour within the inlier distance), inlier
RMSE, overlap (the smaller of the two directed fitnesses) and, for global searches, the
ambiguity of the correlative peak. The reason string names the gate that failed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import matrix_to_se2
from .planar import match_planar, planar_cloud
from .spatial import (
    SpatialCloud,
    feature_ransac,
    gicp,
    registration_fit,
    source_pose_information,
    structure_agreement,
)

_PLANAR_PIN = 1e6  # information on z, roll, pitch of a planar result (not observable, pinned)


@dataclass
class CorrespondenceResult:
    """Outcome of a correspondence test.

    ``T_target_source`` maps source-submap points into the target submap's anchor frame;
    ``information`` is ``(6, 6)`` in GTSAM Pose3 tangent order ``(rx, ry, rz, tx, ty, tz)``, about
    ``T_target_source · Exp(xi)``: the source pose perturbed in its own frame, the tangent of a
    GTSAM between-factor's noise
    (3D results compute it on first access: most tested hypotheses are rejected and never
    need it).
    """

    accepted: bool
    T_target_source: np.ndarray
    _information: np.ndarray | Callable[[], np.ndarray]
    fitness: float
    inlier_rmse: float
    overlap: float
    reason: str
    ambiguity: float = 0.0
    structure_overlap: float = float("nan")  # 3D: overlap of the non-ground points (both ways)
    plane_rmse: float = float("nan")  # 3D: point-to-plane RMSE [m] of those inliers

    @property
    def information(self) -> np.ndarray:
        if callable(self._information):
            self._information = self._information()
        return self._information

    @property
    def information_gtsam(self) -> np.ndarray:
        return self.information



def below(name: str, value: float, bound: float) -> str:
    """``"fitness 0.449 < 0.45"``: as many decimals as it takes for the two to differ."""
    for digits in (2, 3, 4, 6):
        a, b = f"{value:.{digits}f}", f"{bound:.{digits}f}"
        if a != b:
            return f"{name} {a} < {b}"
    return f"{name} {value!r} < {bound!r}"

def match_voxel(submap_voxel: float, planar: bool) -> float:
    """Voxel [m] at which submaps are registered to each other (loop tests, odometry edges).

    Planar: the submap voxel (at least 5 cm). 3D submaps are dense: twice the submap voxel
    (4x fewer points; outdoor loop tests 125 -> 60 s at unchanged accuracy).
    """
    return max(submap_voxel, 0.05) if planar else 2.0 * submap_voxel


def _planar_information(info_xyt: np.ndarray) -> np.ndarray:
    """(3, 3) over (x, y, yaw) -> (6, 6) GTSAM order with z, roll, pitch pinned."""
    info = np.diag([_PLANAR_PIN, _PLANAR_PIN, 0.0, 0.0, 0.0, _PLANAR_PIN])
    idx = [3, 4, 2]  # x -> tx, y -> ty, yaw -> rz
    info[np.ix_(idx, idx)] = info_xyt + np.eye(3) * 1e-4  # a 100 m / 100 rad prior keeps it PD
    return info


def _gate(fitness: float, rmse: float, overlap: float, ambiguity: float, *, min_fitness: float,
          max_inlier_rmse: float, min_overlap: float, max_ambiguity: float) -> tuple[bool, str]:
    """The gates on scores rounded to 4 decimals (as loops.csv shows them): floating-point noise in
    the last digits must not flip a decision from one run to the next."""
    fitness, rmse, overlap, ambiguity = (round(v, 4) for v in (fitness, rmse, overlap, ambiguity))
    if fitness < min_fitness:
        return False, below("fitness", fitness, min_fitness)
    if rmse > max_inlier_rmse:
        return False, f"inlier RMSE {rmse:.3f} m > {max_inlier_rmse:.3f} m"
    if overlap < min_overlap:
        return False, below("overlap", overlap, min_overlap)
    if ambiguity > max_ambiguity:
        return False, f"ambiguous match (second peak {ambiguity:.2f} of the best > {max_ambiguity:.2f})"
    return True, "ok"


def check_correspondence(
    source: np.ndarray | SpatialCloud,
    target: np.ndarray | SpatialCloud,
    *,
    planar: bool,
    initial_guess: np.ndarray | None = None,
    yaw_hint: float | None = None,
    voxel_size: float = 0.1,
    min_fitness: float = 0.6,
    max_inlier_rmse: float = 0.15,
    min_overlap: float = 0.35,
    max_ambiguity: float = 0.9,
    search_radius: float | None = None,
    yaw_window_deg: float = 20.0,
    refine_only: bool = False,
) -> CorrespondenceResult:
    """Test whether ``source`` ``(N, 3)`` and ``target`` ``(M, 3)`` (anchor frames) show one place.

    ``initial_guess``: expected ``T_target_source`` (search centred on it within
    ``search_radius`` m and ``yaw_window_deg``); ``yaw_hint``: expected yaw only (descriptor);
    neither: global search. ``refine_only``: fine registration from ``initial_guess`` only.
    3D clouds may come prepared (:class:`SpatialCloud`, built once per submap at ``voxel_size``).
    """
    if len(source) < 20 or len(target) < 20:
        return CorrespondenceResult(False, np.eye(4), np.eye(6) * 1e-6, 0.0, float("inf"), 0.0,
                                    f"too few points ({len(source)} source, {len(target)} target)")
    inlier = max(2.0 * voxel_size, 0.1)
    max_inlier_rmse = max(max_inlier_rmse, 0.6 * inlier)  # coarse voxels: the gate scales with them
    if planar:
        return _planar(source, target, initial_guess, yaw_hint, inlier, search_radius, yaw_window_deg,
                       refine_only, dict(min_fitness=min_fitness, max_inlier_rmse=max_inlier_rmse,
                                         min_overlap=min_overlap, max_ambiguity=max_ambiguity), voxel_size)
    if not isinstance(source, SpatialCloud):
        source = SpatialCloud(source, voxel_size)
    if not isinstance(target, SpatialCloud):
        target = SpatialCloud(target, voxel_size)
    return _spatial(source, target, initial_guess, yaw_hint, voxel_size, inlier, refine_only,
                    dict(min_fitness=min_fitness, max_inlier_rmse=max_inlier_rmse,
                         min_overlap=min_overlap, max_ambiguity=max_ambiguity))


def _planar(source, target, initial_guess, yaw_hint, inlier, search_radius, yaw_window_deg, refine_only,
            gates, voxel_size) -> CorrespondenceResult:
    yaw_window = np.deg2rad(yaw_window_deg) if (initial_guess is not None or yaw_hint is not None) else np.pi
    m = match_planar(source, target, initial_guess=initial_guess, yaw_hint=yaw_hint,
                     window=search_radius or 10.0, yaw_window=yaw_window, resolution=max(voxel_size, 0.1),
                     inlier_distance=inlier, refine_only=refine_only,
                     resolve_ambiguity_above=gates["max_ambiguity"])
    T = m.T
    reverse = _directed_fitness(target[:, :2], planar_cloud(source).tree, np.linalg.inv(T), inlier)
    overlap = min(m.fitness, reverse)
    ok, reason = _gate(m.fitness, m.inlier_rmse, overlap, m.ambiguity, **gates)
    return CorrespondenceResult(ok, T, _planar_information(m.information), m.fitness, m.inlier_rmse,
                                overlap, reason, m.ambiguity)


def _directed_fitness(points_xy: np.ndarray, other: cKDTree, T: np.ndarray, inlier: float) -> float:
    """Fraction of ``points`` (moved by planar ``T``) with a point of the ``other`` tree within ``inlier``."""
    x, y, yaw = matrix_to_se2(T)
    c, s = np.cos(yaw), np.sin(yaw)
    moved = points_xy @ np.array([[c, s], [-s, c]]) + [x, y]
    d, _ = other.query(moved, distance_upper_bound=inlier)
    return float(np.isfinite(d).mean())


def _spatial(source: SpatialCloud, target: SpatialCloud, initial_guess, yaw_hint, voxel, inlier, refine_only,
             gates) -> CorrespondenceResult:
    ambiguity = 0.0
    if initial_guess is not None:
        guess = np.asarray(initial_guess, dtype=np.float64)
    else:
        (s_coarse, s_features), (t_coarse, t_features) = source.coarse(), target.coarse()
        guess = feature_ransac(s_coarse.points, s_features, t_coarse.points, t_features,
                               inlier_distance=1.5 * 4 * voxel, yaw_hint=yaw_hint)
    result = guess
    # Coarse to fine: the wide-basin stage (3x the inlier distance) runs on the 4x-voxel clouds,
    # the final stage on the match clouds.
    stages = ((source.level(4), target.level(4), 3 * inlier),) if not refine_only else ()
    for s_cloud, t_cloud, dist in (*stages, (source, target, inlier)):
        result = gicp(s_cloud, t_cloud, result, dist)
    fitness, rmse = registration_fit(source, target, result, inlier)
    back, _ = registration_fit(target, source, np.linalg.inv(result), inlier)
    overlap = min(fitness, back)

    def information() -> np.ndarray:
        info = source_pose_information(source, target, result, inlier)
        info = info / max(rmse, 0.02) ** 2 if np.isfinite(rmse) else np.eye(6) * 1e-6
        return 0.5 * (info + info.T) + np.eye(6) * 1e-6

    # the structure gates judge cycle hypotheses; refinements (odometry edges, adjacent checks) skip it
    structure_overlap, plane_rmse = (float("nan"), float("nan")) if refine_only else \
        structure_agreement(source, target, result, inlier)
    ok, reason = _gate(fitness, rmse, overlap, ambiguity, **gates)
    return CorrespondenceResult(ok, result, information, fitness, rmse, overlap, reason, ambiguity,
                                structure_overlap, plane_rmse)
