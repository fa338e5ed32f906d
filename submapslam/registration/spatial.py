"""3D registration tools: prepared clouds, structure agreement, deterministic feature RANSAC.

* :class:`SpatialCloud` — an open3d cloud voxel-downsampled with normals, its coarser levels
  and FPFH features, and its structure (non-ground) points, each built once;
* :class:`SubmapClouds` — the prepared clouds of recently used submaps (bounded LRU);
* :func:`structure_agreement` — overlap and point-to-plane RMSE of the walls, poles and cars;
* :func:`feature_ransac` — a global alignment from FPFH correspondences, repeatable run to run.

GICP itself is open3d's (:func:`~.correspondence.check_correspondence` drives it).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


class SpatialCloud:
    """A 3D cloud prepared once for every registration it takes part in.

    ``pcd``: open3d cloud voxel-downsampled at ``voxel`` with normals (GICP derives its
    covariances from them); ``level(4)``: the same at 4x the voxel (GICP's coarse stage);
    ``coarse()``: that level with FPFH features (global searches). Coarser levels are built on
    first use. :class:`SubmapClouds` keeps the prepared clouds of recently used submaps, so normals
    and features are computed once per submap, not once per test.
    """

    def __init__(self, points: np.ndarray, voxel: float) -> None:
        from .._deps import open3d

        o3d = open3d()
        self.voxel = float(voxel)
        self.n_input = len(points)
        self.pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
        self.pcd = self.pcd.voxel_down_sample(self.voxel)
        self.pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * self.voxel, max_nn=30))
        self._levels: dict = {}
        self._fpfh = None
        self._structure = None

    def __len__(self) -> int:
        return self.n_input

    def level(self, factor: float):
        """The cloud at ``factor`` x the voxel with normals (GICP's coarse stage), built once."""
        cloud = self._levels.get(factor)
        if cloud is None:
            from .._deps import open3d

            o3d = open3d()
            coarse = factor * self.voxel
            cloud = self.pcd.voxel_down_sample(coarse)
            cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * coarse, max_nn=30))
            self._levels[factor] = cloud
        return cloud

    def coarse(self):
        """``(cloud, fpfh)`` at 4x the voxel, for the feature-based global search."""
        if self._fpfh is None:
            from .._deps import open3d

            o3d = open3d()
            self._fpfh = o3d.pipelines.registration.compute_fpfh_feature(
                self.level(4), o3d.geometry.KDTreeSearchParamHybrid(radius=5 * 4 * self.voxel, max_nn=100))
        return self.level(4), self._fpfh


    def structure(self) -> tuple[np.ndarray, np.ndarray, cKDTree]:
        """``(points (S, 3), normals (S, 3), tree)`` of the non-ground points: those whose normal
        is more than 45 deg from vertical (walls, poles, cars, trees). Built once.

        The ground of a street matches the ground of any other street, so fitness over all
        points stays near 0.5 for wrong alignments; over the structure it does not.
        """
        if self._structure is None:
            pts, nrm = np.asarray(self.pcd.points), np.asarray(self.pcd.normals)
            keep = np.abs(nrm[:, 2]) < np.sqrt(0.5) if len(nrm) == len(pts) else np.ones(len(pts), bool)
            self._structure = (pts[keep], nrm[keep], cKDTree(pts[keep]))
        return self._structure


def structure_agreement(source: SpatialCloud, target: SpatialCloud, T_target_source: np.ndarray,
                        inlier: float) -> tuple[float, float]:
    """``(overlap, point-to-plane RMSE [m])`` of the two clouds' structure under ``T_target_source``.

    Overlap: the smaller of the two directed fractions of structure points with a structure
    point of the other cloud within ``inlier`` m; RMSE over the source's inliers, along the
    target's normals.
    """
    (sp, _, s_tree), (tp, tn, t_tree) = source.structure(), target.structure()
    if len(sp) < 10 or len(tp) < 10:
        return 0.0, float("inf")
    R, t = T_target_source[:3, :3], T_target_source[:3, 3]
    d, idx = t_tree.query(sp @ R.T + t, distance_upper_bound=inlier)
    hit = np.isfinite(d)
    forward = float(hit.mean())
    moved_back = (tp - t) @ R  # target points in the source frame
    d_back, _ = s_tree.query(moved_back, distance_upper_bound=inlier)
    backward = float(np.isfinite(d_back).mean())
    if not hit.any():
        return 0.0, float("inf")
    resid = np.einsum("ij,ij->i", (sp[hit] @ R.T + t) - tp[idx[hit]], tn[idx[hit]])
    return min(forward, backward), float(np.sqrt(np.mean(resid**2)))


class SubmapClouds:
    """The prepared :class:`SpatialCloud` of 3D submaps at one voxel, for every registration a
    submap takes part in (odometry edge, loop tests, adjacent checks).

    Only the ``capacity`` most recently used are kept (least recently used dropped first); a
    dropped one is rebuilt from the submap's points when it is needed again — the same points
    give the same cloud, normals and features, so results do not depend on the capacity.
    Memory stays bounded however long the drive (each prepared cloud is ~1 MB).
    """

    def __init__(self, voxel: float, capacity: int = 24) -> None:
        from collections import OrderedDict

        self.voxel = float(voxel)
        self.capacity = capacity
        self._clouds: OrderedDict[int, SpatialCloud] = OrderedDict()
        self.built = 0  # clouds prepared so far (rebuilds included)

    def __call__(self, submap) -> SpatialCloud:
        """The prepared cloud of ``submap`` (an object with ``id`` and ``points (N, 3)``)."""
        cloud = self._clouds.pop(submap.id, None)
        if cloud is None:
            cloud = SpatialCloud(submap.points, self.voxel)
            self.built += 1
        self._clouds[submap.id] = cloud
        while len(self._clouds) > self.capacity:
            self._clouds.popitem(last=False)
        return cloud

    def forget(self, submap_id: int) -> None:
        """Drop the prepared cloud of a submap whose points have changed (rebuilt when next needed)."""
        self._clouds.pop(submap_id, None)


def _kabsch_many(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Rigid ``(H, 4, 4)`` transforms mapping point triples ``P (H, k, 3)`` onto ``Q (H, k, 3)``."""
    mp, mq = P.mean(axis=1, keepdims=True), Q.mean(axis=1, keepdims=True)
    H = np.einsum("hki,hkj->hij", P - mp, Q - mq)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("hij,hjk->hik", U, Vt).transpose(0, 2, 1)))
    D = np.zeros_like(H)
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.einsum("hji,hjk,hlk->hil", Vt, D, U)  # V D U^T
    T = np.tile(np.eye(4), (len(P), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = mq[:, 0] - np.einsum("hij,hj->hi", R, mp[:, 0])
    return T


def feature_ransac(source: np.ndarray, source_features: np.ndarray, target: np.ndarray,
                   target_features: np.ndarray, *, inlier_distance: float, yaw_hint: float | None = None,
                   hypotheses: int = 4000, seed: int = 0) -> np.ndarray:
    """Deterministic RANSAC on feature correspondences: ``T_target_source`` ``(4, 4)``.

    ``source (N, 3)`` / ``target (M, 3)`` with descriptors ``(N, F)`` / ``(M, F)`` (FPFH).
    Correspondences are mutual nearest neighbours in feature space; triples are drawn by a
    seeded generator, pruned by edge-length agreement (within 10 %), solved in closed form
    and scored by the correspondences they bring within ``inlier_distance`` [m]; the best
    hypothesis (ties: the first drawn) is refitted on its inliers. The same inputs give the
    same transform on every run and every thread count (open3d's RANSAC runs threads that
    draw from shared random state). ``yaw_hint`` [rad] (place descriptor) keeps hypotheses
    within 30 deg of it.
    """
    if len(source) < 3 or len(target) < 3:
        return np.eye(4)
    fwd = cKDTree(target_features).query(source_features)[1]
    back = cKDTree(source_features).query(target_features)[1]
    mutual = back[fwd] == np.arange(len(source))
    src_idx = np.flatnonzero(mutual)
    if len(src_idx) < 3:
        return np.eye(4)
    P, Q = source[src_idx], target[fwd[src_idx]]
    rng = np.random.default_rng(seed)
    triples = rng.integers(0, len(P), size=(hypotheses, 3))
    triples = triples[(triples[:, 0] != triples[:, 1]) & (triples[:, 1] != triples[:, 2])
                      & (triples[:, 0] != triples[:, 2])]
    a, b = P[triples], Q[triples]
    ea = np.linalg.norm(a - np.roll(a, 1, axis=1), axis=2)
    eb = np.linalg.norm(b - np.roll(b, 1, axis=1), axis=2)
    ok = (np.minimum(ea, eb) >= 0.9 * np.maximum(ea, eb)).all(axis=1) & (ea.min(axis=1) > inlier_distance)
    if not ok.any():
        return np.eye(4)
    T = _kabsch_many(a[ok], b[ok])
    if yaw_hint is not None:
        yaw = np.arctan2(T[:, 1, 0], T[:, 0, 0])
        near = np.abs(np.angle(np.exp(1j * (yaw - yaw_hint)))) <= np.deg2rad(30.0)
        if near.any():
            T = T[near]
    best, best_count = None, -1
    for start in range(0, len(T), 256):  # bounded memory: 256 hypotheses x correspondences at a time
        chunk = T[start:start + 256]
        moved = np.einsum("hij,nj->hni", chunk[:, :3, :3], P) + chunk[:, None, :3, 3]
        counts = (np.sum((moved - Q) ** 2, axis=2) <= inlier_distance**2).sum(axis=1)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best, best_count = chunk[k], int(counts[k])
    inliers = np.sum((P @ best[:3, :3].T + best[:3, 3] - Q) ** 2, axis=1) <= inlier_distance**2
    if inliers.sum() >= 3:
        best = _kabsch_many(P[inliers][None], Q[inliers][None])[0]
    return best
