"""Correspondence test between two submaps: coarse alignment, fine registration, gates.

``check_correspondence(source, target, ...)`` estimates ``T_target_source`` without needing a
good initial guess and decides whether the two submaps really show the same place:

* planar submaps (2D laser, z = 0): correlative FFT search + ICP in SE(2)
  (:mod:`.planar_match`); the 3D point-to-plane / GICP systems are singular on planar data;
* 3D submaps: FPFH features + RANSAC (open3d) when there is no usable guess, then
  generalized ICP; information from open3d's ``get_information_matrix_from_point_clouds``.

Gates: fitness (source points with a target neighbour within the inlier distance), inlier
RMSE, overlap (the smaller of the two directed fitnesses) and, for global searches, the
ambiguity of the correlative peak. The reason string names the gate that failed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import matrix_to_se2
from .planar_match import match_planar

_PLANAR_PIN = 1e6  # information on z, roll, pitch of a planar result (not observable, pinned)


@dataclass
class CorrespondenceResult:
    """Outcome of a correspondence test.

    ``T_target_source`` maps source-submap points into the target submap's anchor frame;
    ``information`` is ``(6, 6)`` in GTSAM Pose3 tangent order ``(rx, ry, rz, tx, ty, tz)``.
    """

    accepted: bool
    T_target_source: np.ndarray
    information: np.ndarray
    fitness: float
    inlier_rmse: float
    overlap: float
    reason: str
    ambiguity: float = 0.0

    @property
    def information_gtsam(self) -> np.ndarray:
        return self.information


def _planar_information(info_xyt: np.ndarray) -> np.ndarray:
    """(3, 3) over (x, y, yaw) -> (6, 6) GTSAM order with z, roll, pitch pinned."""
    info = np.diag([_PLANAR_PIN, _PLANAR_PIN, 0.0, 0.0, 0.0, _PLANAR_PIN])
    idx = [3, 4, 2]  # x -> tx, y -> ty, yaw -> rz
    info[np.ix_(idx, idx)] = info_xyt + np.eye(3) * 1e-4  # a 100 m / 100 rad prior keeps it PD
    return info


def _gate(fitness: float, rmse: float, overlap: float, ambiguity: float, *, min_fitness: float,
          max_inlier_rmse: float, min_overlap: float, max_ambiguity: float) -> tuple[bool, str]:
    if fitness < min_fitness:
        return False, f"fitness {fitness:.2f} < {min_fitness:.2f}"
    if rmse > max_inlier_rmse:
        return False, f"inlier RMSE {rmse:.3f} m > {max_inlier_rmse:.3f} m"
    if overlap < min_overlap:
        return False, f"overlap {overlap:.2f} < {min_overlap:.2f}"
    if ambiguity > max_ambiguity:
        return False, f"ambiguous match (second peak {ambiguity:.2f} of the best > {max_ambiguity:.2f})"
    return True, "ok"


def check_correspondence(
    source: np.ndarray,
    target: np.ndarray,
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
    return _spatial(source, target, initial_guess, yaw_hint, voxel_size, inlier, refine_only,
                    dict(min_fitness=min_fitness, max_inlier_rmse=max_inlier_rmse,
                         min_overlap=min_overlap, max_ambiguity=max_ambiguity))


def _planar(source, target, initial_guess, yaw_hint, inlier, search_radius, yaw_window_deg, refine_only,
            gates, voxel_size) -> CorrespondenceResult:
    yaw_window = np.deg2rad(yaw_window_deg) if (initial_guess is not None or yaw_hint is not None) else np.pi
    m = match_planar(source, target, initial_guess=initial_guess, yaw_hint=yaw_hint,
                     window=search_radius or 10.0, yaw_window=yaw_window, resolution=max(voxel_size, 0.1),
                     inlier_distance=inlier, refine_only=refine_only)
    T = m.T
    reverse = _directed_fitness(target[:, :2], source[:, :2], np.linalg.inv(T), inlier)
    overlap = min(m.fitness, reverse)
    ok, reason = _gate(m.fitness, m.inlier_rmse, overlap, m.ambiguity, **gates)
    return CorrespondenceResult(ok, T, _planar_information(m.information), m.fitness, m.inlier_rmse,
                                overlap, reason, m.ambiguity)


def _directed_fitness(points_xy: np.ndarray, other_xy: np.ndarray, T: np.ndarray, inlier: float) -> float:
    """Fraction of ``points`` (moved by planar ``T``) with an ``other`` point within ``inlier``."""
    x, y, yaw = matrix_to_se2(T)
    c, s = np.cos(yaw), np.sin(yaw)
    moved = points_xy @ np.array([[c, s], [-s, c]]) + [x, y]
    d, _ = cKDTree(other_xy).query(moved, distance_upper_bound=inlier)
    return float(np.isfinite(d).mean())


def _spatial(source, target, initial_guess, yaw_hint, voxel, inlier, refine_only, gates) -> CorrespondenceResult:
    from .._deps import open3d

    o3d = open3d()
    reg = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source)).voxel_down_sample(voxel)
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target)).voxel_down_sample(voxel)
    for pc in (src, tgt):
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=30))
    ambiguity = 0.0
    if initial_guess is not None:
        guess = np.asarray(initial_guess, dtype=np.float64)
    else:
        coarse = 4 * voxel
        s_d, t_d = src.voxel_down_sample(coarse), tgt.voxel_down_sample(coarse)
        for pc in (s_d, t_d):
            pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * coarse, max_nn=30))
        feat = [reg.compute_fpfh_feature(pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * coarse, max_nn=100))
                for pc in (s_d, t_d)]
        o3d.utility.random.seed(0)
        ransac = reg.registration_ransac_based_on_feature_matching(
            s_d, t_d, feat[0], feat[1], True, 1.5 * coarse,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * coarse)],
            reg.RANSACConvergenceCriteria(100000, 0.999))
        guess = np.asarray(ransac.transformation)
        _ = yaw_hint
    result = guess
    for dist in ((3 * inlier, inlier) if not refine_only else (inlier,)):
        icp = reg.registration_generalized_icp(
            src, tgt, dist, result, reg.TransformationEstimationForGeneralizedICP(),
            reg.ICPConvergenceCriteria(max_iteration=30))
        result = np.asarray(icp.transformation)
    ev = reg.evaluate_registration(src, tgt, inlier, result)
    back = reg.evaluate_registration(tgt, src, inlier, np.linalg.inv(result))
    fitness, rmse = float(ev.fitness), float(ev.inlier_rmse) if ev.fitness > 0 else float("inf")
    overlap = min(fitness, float(back.fitness))
    info = np.asarray(reg.get_information_matrix_from_point_clouds(src, tgt, inlier, result))
    info = info / max(rmse, 0.02) ** 2 if np.isfinite(rmse) else np.eye(6) * 1e-6
    info = 0.5 * (info + info.T) + np.eye(6) * 1e-6
    ok, reason = _gate(fitness, rmse, overlap, ambiguity, **gates)
    return CorrespondenceResult(ok, result, info, fitness, rmse, overlap, reason, ambiguity)
