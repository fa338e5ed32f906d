"""Planar scan-level pose graph on GTSAM (Pose2): one node per keyframe scan.

Used after the submap solve (:mod:`submapslam.scan_refine`): nodes are keyframe scans
``(x, y, yaw)`` in the world frame [m, rad]; between-factors come from the odometry between
consecutive keyframes and from scan-to-submap matches (a scan against another submap, whose
anchor is itself a keyframe node), the latter under a robust kernel. Poses go in and come out
as ``(K, 3)`` arrays; information matrices are ``(3, 3)`` over ``(x, y, yaw)`` in the frame of
the edge's second node (GTSAM Pose2's tangent order).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PlanarEdge:
    """Between-factor ``xyt_i_j`` ``(3,)`` (pose of node j in node i's frame) with its ``(3, 3)``
    information; ``robust``: under the Cauchy kernel (matches), else Gaussian (odometry)."""

    i: int
    j: int
    xyt_i_j: np.ndarray
    information: np.ndarray
    robust: bool


def solve_planar_graph(initial: np.ndarray, edges: list[PlanarEdge], *, fixed: int = 0,
                       kernel: float = 2.0, iterations: int = 10,
                       priors: list[tuple[int, np.ndarray]] = (), prior_kernel: float | None = None) -> np.ndarray:
    """Levenberg-Marquardt (at most ``iterations``) over ``initial`` ``(K, 3)`` node poses with ``edges``; node ``fixed``
    is held by a tight prior; ``priors``: ``(node, information (3, 3))`` holding a node at its
    initial pose (under a Cauchy kernel of width ``prior_kernel`` [whitened units] when given: a
    prior the matches contradict by many sigmas gives way). ``kernel``: Cauchy width [whitened units] of the robust edges.
    Returns the ``(K, 3)`` optimised poses (``initial`` when GTSAM fails)."""
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k, (x, y, t) in enumerate(np.asarray(initial, dtype=np.float64)):
        values.insert(k, gtsam.Pose2(float(x), float(y), float(t)))
    x, y, t = (float(v) for v in initial[fixed])
    graph.add(gtsam.PriorFactorPose2(fixed, gtsam.Pose2(x, y, t), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    cauchy = gtsam.noiseModel.mEstimator.Cauchy.Create(kernel)
    for k, info in priors:
        x, y, t = (float(v) for v in initial[k])
        noise = gtsam.noiseModel.Gaussian.Information(info)
        if prior_kernel is not None:
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(prior_kernel), noise)
        graph.add(gtsam.PriorFactorPose2(k, gtsam.Pose2(x, y, t), noise))
    for e in edges:
        info = 0.5 * (e.information + e.information.T)
        noise = gtsam.noiseModel.Gaussian.Information(info)
        if e.robust:
            noise = gtsam.noiseModel.Robust.Create(cauchy, noise)
        graph.add(gtsam.BetweenFactorPose2(e.i, e.j, gtsam.Pose2(*(float(v) for v in e.xyt_i_j)), noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    params.setRelativeErrorTol(1e-4)
    try:
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    except RuntimeError:
        return np.array(initial, dtype=np.float64)
    out = np.empty((len(initial), 3))
    for k in range(len(initial)):
        p = result.atPose2(k)
        out[k] = (p.x(), p.y(), p.theta())
    return out
