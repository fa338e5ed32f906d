"""Submap pose graph on GTSAM: Pose3 between-factors, robust loop edges, iSAM2 and batch LM.

This is the only module (with ``landmark_graph``) that touches gtsam. Poses go in and come out
as ``(4, 4)`` numpy arrays ``T_world_submap``; information matrices are ``(6, 6)`` in GTSAM's
Pose3 tangent order ``(rx, ry, rz, tx, ty, tz)``.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from ..config import BackendConfig
from ..errors import OptimisationError
from ..geometry import adjoint, rotation_between

log = logging.getLogger(__name__)


GROUND_ATTITUDE_PRIOR = "ground attitude prior"  # the kind of a level prior from a ground plane


@dataclass
class GraphEdge:
    """One between-factor ``T_i_j`` with its information (GTSAM order) and kind."""

    i: int
    j: int
    T_i_j: np.ndarray
    information: np.ndarray
    kind: str  # "odometry" | "loop"


def floor_information(information: np.ndarray, sigma_m: float, sigma_rad: float) -> np.ndarray:
    """Cap an information matrix so no direction is more certain than the given floor sigmas.

    Keeps the registration's shape while refusing over-confident edges; ``(6, 6)`` GTSAM order.
    """
    info = 0.5 * (information + information.T)
    cov = np.linalg.pinv(info)
    floor = np.diag([sigma_rad**2] * 3 + [sigma_m**2] * 3)
    w, V = np.linalg.eigh(cov + floor)
    w = np.maximum(w, 1e-12)
    return (V / w) @ V.T


# The least information an edge carries in any direction (GTSAM order): sigma 100 m / 100 rad. A
# direction the measurement does not see at all (a zero eigenvalue, a registration that failed)
# otherwise leaves a node under-determined and GTSAM's solve fails on it.
MIN_INFORMATION = 1e-4


def regularised_information(information: np.ndarray) -> np.ndarray:
    """``(6, 6)`` information made symmetric positive definite: eigenvalues floored at
    :data:`MIN_INFORMATION`; a non-finite matrix carries that floor only (no information)."""
    info = np.asarray(information, dtype=np.float64)
    if not np.isfinite(info).all():
        log.warning("an edge's information is not finite: the edge is kept with none (sigma 100 m / 100 rad)")
        return np.eye(len(info)) * MIN_INFORMATION
    info = 0.5 * (info + info.T)
    w, V = np.linalg.eigh(info)
    if w.min() >= MIN_INFORMATION:
        return info
    return (V * np.maximum(w, MIN_INFORMATION)) @ V.T


def cap_covariance(cov: np.ndarray, sigma_m: float, sigma_rad: float) -> np.ndarray:
    """Clip a ``(6, 6)`` covariance (GTSAM order) so no direction is less certain than the caps.

    Directions are compared after whitening by the caps, so a corridor's long axis is cut to
    ``sigma_m`` while well-constrained directions keep their own, smaller variance.
    """
    scale = np.array([1.0 / sigma_rad] * 3 + [1.0 / sigma_m] * 3)
    w, V = np.linalg.eigh(cov * np.outer(scale, scale))
    return ((V * np.minimum(w, 1.0)) @ V.T) / np.outer(scale, scale)


class PoseGraph:
    """Incremental submap pose graph (iSAM2) with an optional final batch LM pass."""

    def __init__(self, config: BackendConfig) -> None:
        import gtsam

        self._gtsam = gtsam
        self.config = config
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(0.01)
        params.relinearizeSkip = 1
        self._isam_params = params
        self._isam = gtsam.ISAM2(params)
        self.recoveries: list[str] = []  # GTSAM failures recovered by regularising the graph
        self._graph = gtsam.NonlinearFactorGraph()  # everything, for batch and export
        self._pending_graph = gtsam.NonlinearFactorGraph()
        self._pending_values = gtsam.Values()
        self._estimate = gtsam.Values()
        self._initial: dict[int, np.ndarray] = {}
        self.edges: list[GraphEdge] = []
        self._factor_edges: dict[int, int] = {}  # factor index in _graph -> index in edges
        self._excluded: set[int] = set()  # factor indices of rejected loop edges and of priors that gave way
        self._relaxed: dict[int, object] = {}  # factor index of an odometry edge that gave way -> its weak stand-in
        self._priors: dict[int, tuple] = {}  # factor index -> (kind, i, j, information) of a ground prior
        self.gave_way: list[dict] = []  # what the final check blamed instead of loops (odometry edges, priors)
        self.odometry_steps: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # i -> (T_i_i+1, Sigma)
        self.n_updates = 0

    # ------------------------------------------------------------------ building
    def _noise(self, information: np.ndarray, robust: bool):
        gtsam = self._gtsam
        info = 0.5 * (information + information.T)
        base = gtsam.noiseModel.Gaussian.Information(info)
        kernel = self.config.robust_kernel
        if not robust or kernel in ("none", "gnc"):
            return base
        k = self.config.robust_scale
        est = {
            "huber": gtsam.noiseModel.mEstimator.Huber,
            "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
            "gm": gtsam.noiseModel.mEstimator.GemanMcClure,
        }[kernel].Create(k)
        return gtsam.noiseModel.Robust.Create(est, base)

    def _prior_noise(self, base):
        """A ground prior's noise: ``base`` under the Cauchy kernel of ``ground_prior_kernel``
        whitened units when set (a prior the data contradicts by many sigmas, a change of grade,
        loses its pull instead of bending the graph), else ``base``."""
        k = self.config.ground_prior_kernel
        if k is None:
            return base
        gtsam = self._gtsam
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(k), base)

    def add_node(self, key: int, T_world_node: np.ndarray, prior_information: np.ndarray | None = None) -> None:
        """Add a node with its initial estimate; anchor it with a prior when given."""
        gtsam = self._gtsam
        self._initial[key] = np.array(T_world_node, dtype=np.float64)
        self._pending_values.insert(key, gtsam.Pose3(self._initial[key]))
        if prior_information is not None:
            f = gtsam.PriorFactorPose3(key, gtsam.Pose3(self._initial[key]), self._noise(prior_information, False))
            self._pending_graph.add(f)
            self._graph.add(f)

    def add_attitude(self, key: int, up_in_node: np.ndarray, up_in_world: np.ndarray, sigma_rad: float,
                     kind: str = GROUND_ATTITUDE_PRIOR) -> None:
        """Soft prior that the node's ``up_in_node`` ``(3,)`` direction points along the world's
        ``up_in_world`` ``(3,)``: constrains roll and pitch, never yaw or position (2 DOF). ``kind``
        names it in the final check's and the ground-prior test's accounts."""
        gtsam = self._gtsam
        f = gtsam.AttitudeFactorPose3(key, gtsam.Unit3(np.asarray(up_in_world, dtype=np.float64)),
                                      self._prior_noise(gtsam.noiseModel.Isotropic.Sigma(2, float(sigma_rad))),
                                      gtsam.Unit3(np.asarray(up_in_node, dtype=np.float64)))
        self._pending_graph.add(f)
        self._priors[self._graph.size()] = (kind, key, key, np.eye(2) / float(sigma_rad) ** 2)
        self._graph.add(f)

    def add_relative_attitude(self, i: int, j: int, up_i: np.ndarray, up_j: np.ndarray, T_i_j: np.ndarray,
                              sigma_rad: float) -> None:
        """Soft constraint that node j's ``up_j`` ``(3,)`` and node i's ``up_i`` ``(3,)`` are one
        direction: node j's roll and pitch relative to node i (2 DOF; never the yaw between them
        or their positions). ``T_i_j`` ``(4, 4)``: the current guess of the relative pose, whose
        yaw and translation the factor leaves free (information 1e-9)."""
        gtsam = self._gtsam
        measured = np.array(T_i_j, dtype=np.float64)
        R = measured[:3, :3]
        measured[:3, :3] = rotation_between(R @ up_j, up_i) @ R  # tilted so that R up_j = up_i
        info = np.eye(6) * 1e-9  # GTSAM order (rx, ry, rz, tx, ty, tz), in node j's frame
        info[:3, :3] += (np.eye(3) - np.outer(up_j, up_j)) / sigma_rad**2
        f = gtsam.BetweenFactorPose3(i, j, gtsam.Pose3(measured),
                                     self._prior_noise(gtsam.noiseModel.Gaussian.Information(info)))
        self._pending_graph.add(f)
        self._priors[self._graph.size()] = ("ground tilt-change prior", i, j, info)
        self._graph.add(f)

    def add_between(self, i: int, j: int, T_i_j: np.ndarray, information: np.ndarray, kind: str) -> None:
        """Add ``T_i_j`` (pose of node j in node i's frame); loop edges get the robust kernel."""
        edge = GraphEdge(i, j, np.array(T_i_j), np.array(regularised_information(information)), kind)
        f = self._between_factor(edge)
        self._pending_graph.add(f)
        self._factor_edges[self._graph.size()] = len(self.edges)
        self._graph.add(f)
        self.edges.append(edge)

    def _between_factor(self, edge: GraphEdge):
        """``edge``'s GTSAM between-factor (loop edges under the robust kernel); an odometry edge
        between consecutive nodes is also kept in :attr:`odometry_steps` with its covariance."""
        gtsam = self._gtsam
        T = np.asarray(edge.T_i_j, dtype=np.float64)
        if edge.kind == "odometry" and edge.j == edge.i + 1:
            self.odometry_steps[edge.i] = (T.copy(), np.linalg.inv(0.5 * (edge.information + edge.information.T)))
        return gtsam.BetweenFactorPose3(edge.i, edge.j, gtsam.Pose3(T),
                                        self._noise(edge.information, robust=(edge.kind == "loop")))

    # ------------------------------------------------------------------ solving
    def update(self, extra_iterations: int = 0) -> None:
        """One iSAM2 step with everything added since the last call.

        When GTSAM finds the system indeterminate, the node it names is held where it is by a
        weak prior and iSAM2 restarted on the whole graph (:attr:`recoveries` says so);
        :class:`OptimisationError` if that does not help.
        """
        try:
            self._isam.update(self._pending_graph, self._pending_values)
            for _ in range(extra_iterations):
                self._isam.update()
        except RuntimeError as exc:
            self._recover(exc)
        self._pending_graph = self._gtsam.NonlinearFactorGraph()
        self._pending_values = self._gtsam.Values()
        self._estimate = self._isam.calculateEstimate()
        self.n_updates += 1

    def _recover(self, exc: RuntimeError, attempts: int = 8) -> None:
        """Find the under-constrained node GTSAM names ("near variable K"), hold it where it is
        with a prior (sigma 1 m / 1 rad), restart iSAM2 on the whole active graph; repeat for the
        next node it names, at most ``attempts`` times."""
        gtsam = self._gtsam
        values = gtsam.Values()
        for key, T in self._initial.items():
            values.insert(key, self._estimate.atPose3(key) if self._estimate.exists(key) else gtsam.Pose3(T))
        hold = gtsam.noiseModel.Isotropic.Sigma(6, 1.0)
        for _ in range(attempts):
            why = _one_line(exc)
            match = re.search(r"near variable\s+(\d+)", str(exc))
            if match is None or int(match.group(1)) not in self._initial:
                break
            key = int(match.group(1))
            log.warning("GTSAM could not solve the graph (%s); holding node %d where it is and solving again",
                        why, key)
            self._graph.add(gtsam.PriorFactorPose3(key, values.atPose3(key), hold))
            self.recoveries.append(f"{why}: node {key} held by a weak prior (1 m, 1 rad), solved again")
            self._isam = gtsam.ISAM2(self._isam_params)
            try:
                self._isam.update(self._active_graph(), values)
                return
            except RuntimeError as again:
                exc = again
        raise OptimisationError(f"the pose graph cannot be solved, even regularised: {_one_line(exc)}") from exc

    def _active_factors(self, leave_out: frozenset[int] | set[int] = frozenset()) -> list[int]:
        """Indices (ascending) of the factors in the graph that are not in ``self._excluded``
        (rejected loops, priors that gave way) nor in ``leave_out``."""
        return [idx for idx in range(self._graph.size()) if idx not in self._excluded and idx not in leave_out]

    def _active_graph(self, also_without: int | None = None, leave_out: frozenset[int] | set[int] = frozenset()):
        """The graph of :meth:`_active_factors` (``leave_out`` left out too), odometry edges that
        gave way as their weak stand-ins and, when given, without the factor at index
        ``also_without`` (an odometry edge: its weak stand-in)."""
        if not self._excluded and not self._relaxed and also_without is None and not leave_out:
            return self._graph
        graph = self._gtsam.NonlinearFactorGraph()
        for idx in self._active_factors(leave_out):
            if idx == also_without:
                if idx in self._factor_edges and self.edges[self._factor_edges[idx]].kind == "odometry":
                    graph.add(self._weak(idx))  # the chain stays connected
                continue
            graph.add(self._relaxed.get(idx, self._graph.at(idx)))
        return graph

    def _weak(self, idx: int):
        """A stand-in for the odometry edge at factor ``idx`` that has given way: the same
        measurement, its information scaled by 1e-6 (a switched-off edge that keeps the chain connected)."""
        e = self.edges[self._factor_edges[idx]]
        info = 0.5 * (e.information + e.information.T) * 1e-6
        return self._gtsam.BetweenFactorPose3(e.i, e.j, self._gtsam.Pose3(np.asarray(e.T_i_j, dtype=np.float64)),
                                              self._gtsam.noiseModel.Gaussian.Information(info))

    def _flush_pending(self) -> None:
        """An iSAM2 step with whatever was added since the last one, if anything was."""
        if self._pending_graph.size() or self._pending_values.size():
            self.update()

    def _lm_params(self, max_iterations: int):
        lm = self._gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(max_iterations)
        lm.setVerbosityLM("SILENT")
        return lm

    def optimize_batch(self, max_iterations: int = 100) -> dict[tuple[int, int], float]:
        """Batch pass on the whole graph from the current estimate.

        With ``robust_kernel="gnc"``: graduated non-convexity (truncated least squares) over LM,
        odometry edges and priors known inliers; returns the final weight of each loop edge
        ``{(i, j): w}`` (0 = rejected as an outlier; such edges leave the graph). Otherwise plain
        LM; weights are all 1.
        """
        self._flush_pending()
        lm = self._lm_params(max_iterations)
        loop_factors = {idx: key for idx, key in self._factor_edges.items() if self.edges[key].kind == "loop"}
        weights = {(e.i, e.j): 1.0 for e in self.edges if e.kind == "loop"}
        try:
            return self._batch(lm, loop_factors, weights)
        except RuntimeError as exc:  # keep iSAM2's estimate
            log.warning("the batch pass failed (%s); keeping the incremental estimate", _one_line(exc))
            self.recoveries.append(f"batch pass: {_one_line(exc)}; kept the incremental estimate")
            return weights

    def _batch(self, lm, loop_factors: dict[int, int], weights: dict[tuple[int, int], float]
               ) -> dict[tuple[int, int], float]:
        gtsam = self._gtsam
        graph = self._active_graph()
        active = self._active_factors()  # factor position in `graph` -> index in `self._graph`
        loops_active = [pos for pos, idx in enumerate(active) if idx in loop_factors]
        if self.config.robust_kernel == "gnc" and loops_active:
            params = gtsam.GncLMParams(lm)
            params.setLossType(gtsam.GncLossType.TLS)
            params.setKnownInliers([pos for pos in range(graph.size()) if active[pos] not in loop_factors])
            opt = gtsam.GncLMOptimizer(graph, self._estimate, params)
            opt.setInlierCostThresholdsAtProbability(self.config.gnc_inlier_probability)
            self._estimate = opt.optimize()
            w = np.asarray(opt.getWeights())
            for pos in loops_active:
                e = self.edges[loop_factors[active[pos]]]
                weights[(e.i, e.j)] = float(w[pos])
            self._excluded |= {active[pos] for pos in loops_active if w[pos] < 0.5}
        else:
            self._estimate = gtsam.LevenbergMarquardtOptimizer(graph, self._estimate, lm).optimize()
        return weights

    def drop_ground_priors_unless_loops_favour(self, allowance: float = 0.0, limit: float = 22.46,
                                               max_iterations: int = 100,
                                               keep_kinds: frozenset[str] | set[str] = frozenset()) -> dict:
        """Keep the ground priors only where the loop closures fit them, within ``allowance``, as
        well as they fit without them.

        For a world the run found not level, or could not test (:class:`~submapslam.uncertainty.LevelGroundTest`):
        the priors' flat-world bet then has evidence against it, and the closures, the one
        measurement of the heights besides the odometry, must speak for it. The active graph is
        solved with and without every ground prior (LM from the current estimate); each loop
        edge's whitened residual, capped at ``limit`` (a wrong closure counts once), is summed
        for both. The priors stay when they raise that sum by less than ``allowance`` (chi-square;
        0: they must lower it); else, and with no closure at all, they leave, and the solution
        without them becomes the estimate. Priors of ``keep_kinds`` (not a bet on level ground: the
        walls' vertical) are neither tested nor dropped. Returns ``{"kept", "priors", "loops",
        "loop_chi2_with", "loop_chi2_without", "allowance"}``.
        """
        gtsam = self._gtsam
        priors = {idx for idx, p in self._priors.items() if idx not in self._excluded and p[0] not in keep_kinds}
        loops = [idx for idx, key in self._factor_edges.items()
                 if self.edges[key].kind == "loop" and idx not in self._excluded]
        out = {"kept": True, "priors": len(priors), "loops": len(loops),
               "loop_chi2_with": None, "loop_chi2_without": None, "allowance": round(allowance, 4)}
        if not priors:
            return out
        self._flush_pending()

        def solve(leave_out: set[int]):
            return gtsam.LevenbergMarquardtOptimizer(self._active_graph(leave_out=leave_out), self._estimate,
                                                     self._lm_params(max_iterations)).optimize()

        def loop_chi2(estimate) -> float:
            return float(sum(min(2.0 * float(self._graph.at(idx).error(estimate)), limit) for idx in loops))

        try:
            without = solve(priors)
            if loops:
                c_with, c_without = loop_chi2(solve(set())), loop_chi2(without)
                out.update(loop_chi2_with=round(c_with, 2), loop_chi2_without=round(c_without, 2))
                if c_with - c_without < allowance:
                    return out
        except RuntimeError as exc:
            log.warning("the ground-prior test failed (%s); the priors stay", _one_line(exc))
            return out
        out["kept"] = False
        self._excluded |= priors
        self._estimate = without
        return out

    def reweigh_edges(self, kind: str, information_of: Callable[[np.ndarray], np.ndarray]) -> int:
        """Weigh every active edge of ``kind`` anew: the same measurement with information
        ``information_of(information) -> (6, 6)`` (GTSAM order). The old factors leave the graph
        that the batch pass, the final check and the marginals solve (iSAM2 keeps them: call this
        once the incremental updates are over, as at the end of a run); the edges, and the g2o
        export, carry the new information. Returns how many edges were reweighed."""
        self._flush_pending()
        count = 0
        for idx, key in list(self._factor_edges.items()):
            e = self.edges[key]
            if e.kind != kind or idx in self._excluded or idx in self._relaxed:
                continue
            e.information = regularised_information(information_of(e.information))
            del self._factor_edges[idx]
            self._excluded.add(idx)
            self._factor_edges[self._graph.size()] = key
            self._graph.add(self._between_factor(e))
            count += 1
        return count

    def has_active_priors(self, ignore_kinds: frozenset[str] | set[str] = frozenset()) -> bool:
        """Whether any ground or level prior of a kind not in ``ignore_kinds`` is still in the
        graph the solution uses."""
        return any(idx not in self._excluded and p[0] not in ignore_kinds for idx, p in self._priors.items())

    def edge_chi2(self) -> dict[int, float]:
        """Whitened squared residual of every active between-edge at the current estimate.

        ``{index in edges: chi2}``; for Gaussian noise ``2 * factor.error`` is ``e^T I e`` (6 DOF).
        """
        out = {}
        for idx, key in self._factor_edges.items():
            if idx not in self._excluded and idx not in self._relaxed:
                out[key] = 2.0 * float(self._graph.at(idx).error(self._estimate))
        return out

    def prior_chi2(self) -> dict[int, float]:
        """``{factor index: chi2}`` of the active ground priors (2 DOF each) at the current estimate;
        for a robust prior the whitened squared residual before the kernel."""
        out = {}
        for idx in self._priors:
            if idx in self._excluded:
                continue
            e = np.asarray(self._graph.at(idx).unwhitenedError(self._estimate))
            out[idx] = float(e @ self._priors[idx][3] @ e)
        return out

    def final_check(self, limit: float = 22.46, max_drops: int | None = None, max_suspects: int = 12,
                    prior_limit: float = 13.82) -> list[tuple[int, int, str]]:
        """Drop loop edges the solution cannot reconcile; return ``(i, j, why)`` of those dropped.

        After the batch pass every kept edge should be explained within its noise: whitened
        residual at most ``limit`` (chi-square, 6 DOF, 99.9 %), every ground prior at most
        ``prior_limit`` (2 DOF, 99.9 %; Gaussian priors only: under ``ground_prior_kernel`` a
        prior far out has lost its pull already). While one is exceeded, one constraint gives way. The
        candidates: the ``max_suspects`` loops with the largest residuals, the most stretched
        odometry edge and the most stretched ground prior (and the priors on that edge's two
        nodes). Each is taken out in turn (an odometry edge keeps a 1e-6 stand-in: the chain stays
        connected) and the graph re-solved; the one whose removal lowers the cost the most goes.
        An odometry edge or a prior can be that one only when at least
        ``config.final_check_consensus`` loops remain and all of them fit without it (many loops
        agree and contradict it); otherwise the best loop is dropped (a residual alone can point
        at a right loop that the wrong one bent). Then the check repeats. At most ``max_drops``
        loops are dropped (default: half the loops, at least one): the check never empties the
        graph of mutually consistent closures. What gave way besides loops is in :attr:`gave_way`.
        """
        gtsam = self._gtsam
        dropped: list[tuple[int, int, str]] = []
        index_of = {key: idx for idx, key in self._factor_edges.items()}
        n_loops = sum(1 for k in self.edge_chi2() if self.edges[k].kind == "loop")
        max_drops = max_drops if max_drops is not None else max(1, n_loops // 2)
        consensus = self.config.final_check_consensus
        for _ in range(len(self.edges) + len(self._priors)):
            chi2 = self.edge_chi2()
            loops = {k: v for k, v in chi2.items() if self.edges[k].kind == "loop"}
            odo = {k: v for k, v in chi2.items() if self.edges[k].kind == "odometry"}
            # robust priors far out have given way already (their kernel): only Gaussian ones are a symptom
            priors = self.prior_chi2() if self.config.ground_prior_kernel is None else {}
            worst_odo = max(odo, key=lambda k: (odo[k], -k)) if odo else None
            worst_prior = max(priors, key=lambda k: (priors[k], -k)) if priors else None
            if worst_odo is not None and odo[worst_odo] > limit:
                m = self.edges[worst_odo].i
                symptom = f"odometry edge {m}-{self.edges[worst_odo].j} stretched to chi2 {odo[worst_odo]:.1f} > {limit:.1f}"
            elif worst_prior is not None and priors[worst_prior] > prior_limit:
                kind, i, j, _ = self._priors[worst_prior]
                symptom = (f"{kind} {i}" + (f"-{j}" if j != i else "")
                           + f" stretched to chi2 {priors[worst_prior]:.1f} > {prior_limit:.1f}")
            elif loops and max(loops.values()) > limit:
                symptom = "loop residual above the chi2 bound"
            else:
                break
            if not loops:
                break
            suspects = [("loop", index_of[k]) for k in sorted(loops, key=lambda k: (-loops[k], k))[:max_suspects]]
            others: list[int] = []
            if worst_odo is not None and odo[worst_odo] > limit:
                others.append(index_of[worst_odo])
                ei, ej = self.edges[worst_odo].i, self.edges[worst_odo].j
                others += [idx for idx, p in self._priors.items() if idx not in self._excluded
                           and ((p[1] == p[2] and p[1] in (ei, ej)) or (p[1], p[2]) == (ei, ej))]
            if worst_prior is not None and priors[worst_prior] > prior_limit and worst_prior not in others:
                others.append(worst_prior)
            if len(loops) >= consensus:
                suspects += [("other", idx) for idx in others]
            best = None
            for what, idx in suspects:
                trial = self._active_graph(also_without=idx)
                estimate = gtsam.LevenbergMarquardtOptimizer(trial, self._estimate, self._lm_params(30)).optimize()
                cost = trial.error(estimate)
                if what == "other" and not self._loops_fit(estimate, loops, index_of, limit):
                    continue
                if best is None or cost < best[2] - 1e-9:
                    best = (what, idx, cost, estimate)
            if best is None:
                break
            what, idx, _, estimate = best
            if what == "loop" and len(dropped) >= max_drops:
                log.warning("final check: stops after dropping %d of %d loop closures (%s); the rest stay",
                            len(dropped), n_loops, symptom)
                break
            previous, self._estimate = self._estimate, estimate
            if what == "loop":
                self._excluded.add(idx)
                e = self.edges[self._factor_edges[idx]]
                dropped.append((e.i, e.j, f"dropped by the final check: {symptom}; its residual chi2 was "
                                          f"{loops[self._factor_edges[idx]]:.1f}, the graph agrees best without it"))
                continue
            if idx in self._factor_edges:  # an odometry edge: a weak stand-in keeps the chain connected
                self._relaxed[idx] = self._weak(idx)
                e = self.edges[self._factor_edges[idx]]
                kind, i, j, before = "odometry edge", e.i, e.j, odo[self._factor_edges[idx]]
            else:
                self._excluded.add(idx)
                kind, i, j, info = self._priors[idx]
                residual = np.asarray(self._graph.at(idx).unwhitenedError(previous))
                before = float(residual @ info @ residual)  # before it gave way
            entry = {"constraint": kind, "i": int(i), "j": int(j), "chi2": round(float(before), 2),
                     "loops_agreeing": len(loops), "symptom": symptom}
            self.gave_way.append(entry)
            log.info("final check: %s %d-%d gave way (chi2 %.1f; %d loop closures agree without it)",
                     kind, i, j, before, len(loops))
        return dropped

    def _loops_fit(self, estimate, loops: dict[int, float], index_of: dict[int, int], limit: float) -> bool:
        """Whether every loop edge in ``loops`` has a whitened residual within ``limit`` at ``estimate``."""
        return all(2.0 * float(self._graph.at(index_of[k]).error(estimate)) <= limit for k in loops)

    def odometry_chain(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        """Odometry-only ``(T_i_j, Sigma_i_j)`` between nodes ``i < j`` (loop edges ignored)."""
        return chain_covariance([self.odometry_steps[k] for k in range(i, j)])

    def pose(self, key: int) -> np.ndarray:
        """Current ``T_world_node`` of one node (initial guess if not yet optimised)."""
        if self._estimate.exists(key):
            return self._estimate.atPose3(key).matrix()
        return self._initial[key].copy()

    def active_edges(self) -> list[GraphEdge]:
        """The edges the solution keeps (loops rejected by GNC or the final check left out)."""
        excluded = {self._factor_edges[idx] for idx in self._excluded if idx in self._factor_edges}  # not priors
        return [e for k, e in enumerate(self.edges) if k not in excluded]

    def marginal_covariance(self, key: int) -> np.ndarray:
        """``(6, 6)`` marginal covariance of a node (GTSAM order), from iSAM2."""
        return np.asarray(self._isam.marginalCovariance(key))

    def all_marginal_covariances(self, keys: Iterable[int] | None = None) -> dict[int, np.ndarray]:
        """Marginal covariances ``(6, 6)`` of the nodes ``keys`` (default: every node) at the
        current estimate (batch Marginals)."""
        gtsam = self._gtsam
        wanted = list(self._initial if keys is None else keys)
        try:
            marg = gtsam.Marginals(self._active_graph(), self._estimate)
            return {k: np.asarray(marg.marginalCovariance(k)) for k in wanted}
        except RuntimeError as exc:  # indeterminant system; fall back to iSAM2's
            log.warning("batch marginals failed (%s); using iSAM2 marginals", exc)
            return {k: self.marginal_covariance(k) for k in wanted}


    def factor_kind(self, idx: int) -> tuple[str, int, int]:
        """``(kind, i, j)`` of the factor at index ``idx``: an edge's kind ("odometry", "loop", with
        " (gave way)" when it did), a ground prior's, or "prior" (the start, a node held after a
        GTSAM failure) with ``i = j`` its node."""
        if idx in self._factor_edges:
            e = self.edges[self._factor_edges[idx]]
            return (e.kind + (" (gave way)" if idx in self._relaxed else ""), e.i, e.j)
        if idx in self._priors:
            kind, i, j, _ = self._priors[idx]
            return kind, i, j
        key = int(self._graph.at(idx).keys()[0])
        return "prior", key, key

    def attitude_residuals(self) -> dict[str, np.ndarray]:
        """Per kind of attitude prior (:meth:`add_attitude`), ``(n, 2)`` [rad]: how far each active
        one's node is from it at the estimate, in the prior's own 2-D error space."""
        gtsam = self._gtsam
        out: dict[str, list[np.ndarray]] = {}
        for idx in self._active_factors():
            factor = self._graph.at(idx)
            if isinstance(factor, gtsam.AttitudeFactorPose3):
                out.setdefault(self.factor_kind(idx)[0], []).append(np.asarray(factor.unwhitenedError(self._estimate)))
        return {kind: np.array(r) for kind, r in out.items()}

    def estimator_covariances(self, true_covariance: Callable[[str, int, int, np.ndarray], np.ndarray],
                              keys: Iterable[int] | None = None, batch: int = 128,
                              up_covariance: np.ndarray | None = None,
                              first_cloud: tuple[int, np.ndarray] | None = None) -> dict[int, np.ndarray]:
        """``(6, 6)`` covariances (GTSAM order, node frame) of the current estimate of nodes ``keys``
        (default: all) when each factor's measurement error has the covariance
        ``true_covariance(kind, i, j, stated)`` (:meth:`factor_kind`; ``stated``: the covariance
        the factor is weighed with, ``(d, d)`` in its own error space) instead of the stated one.

        The estimate minimises the factors' weighted errors, so its linearised error is ``H^-1 J^T W
        e`` (``H = J^T W J``, ``W`` the stated informations, robust kernels' weights at the estimate
        included); its covariance is the sandwich ``H^-1 J^T W S W J H^-1`` with ``S`` the true
        covariances. With ``S`` the stated ones and no kernel this is the graph's marginal covariance.
        Sparse: ``H`` is factorised once and solved for ``batch`` nodes at a time.

        ``up_covariance`` ``(3, 3)`` [rad^2]: the error the attitude priors (:meth:`add_attitude`)
        share, a small rotation (world frame) of the one world up they all hold the nodes to. It
        tilts the whole estimate alike: ``G Sigma_up G^T`` is added, ``G = H^-1 J^T W (de/du)``.

        ``first_cloud`` ``(node, (6, 6))``: the error (node frame, GTSAM order) of the cloud that
        ``node``'s edges register against, relative to the node's pose
        (:func:`~submapslam.uncertainty.first_cloud_covariance`). Every odometry and loop edge of
        the node shares it as if the node had moved; added the same way, ``G = H^-1 J^T W A_node``.
        """
        from scipy.sparse import coo_matrix
        from scipy.sparse.linalg import splu

        gtsam = self._gtsam
        nodes = sorted(self._initial)
        col = {k: 6 * n for n, k in enumerate(nodes)}
        rows_h, cols_h, vals_h, rows_m, cols_m, vals_m = [], [], [], [], [], []
        shared_rows, shared_vals = [], []  # J^T W de/du of the attitude priors, (6, 3) per factor
        cloud_rows, cloud_vals = [], []  # J^T W de/dc of the edges into first_cloud's node, (6, 6) per factor
        for idx in self._active_factors():
            factor = self._relaxed.get(idx, self._graph.at(idx))
            kind, i, j = self.factor_kind(idx)
            noise = factor.noiseModel()
            weight = 1.0
            if isinstance(noise, gtsam.noiseModel.Robust):
                base = noise.noise()
                whitened = base.whiten(np.asarray(factor.unwhitenedError(self._estimate), dtype=np.float64))
                weight = float(noise.robust().weight(float(np.linalg.norm(whitened))))
                noise = base
            L = np.asarray(noise.R(), dtype=np.float64)  # L^T L = stated information
            stated = np.linalg.inv(L.T @ L)
            R = weight * L @ true_covariance(kind, i, j, stated) @ L.T  # the true covariance, whitened
            linear = factor.linearize(self._estimate)
            A = np.asarray(linear.jacobian()[0], dtype=np.float64)  # whitened (and weighted) Jacobian
            idx_cols = np.concatenate([np.arange(col[int(k)], col[int(k)] + 6) for k in linear.keys()])
            if up_covariance is not None and isinstance(factor, gtsam.AttitudeFactorPose3):
                shared_rows.append(idx_cols)
                # the up turned by u in the world is the node turned by -u there: R -> Exp(-u) R = R Exp(-R^T u)
                R_node = self._estimate.atPose3(linear.keys()[0]).rotation().matrix()
                shared_vals.append(A.T @ (-A[:, :3] @ R_node.T))
            if first_cloud is not None and kind.startswith(("odometry", "loop")) and first_cloud[0] in (i, j):
                at = [int(k) for k in linear.keys()].index(first_cloud[0])
                cloud_rows.append(idx_cols)
                cloud_vals.append(A.T @ A[:, 6 * at:6 * at + 6])
            for target_rows, target_cols, target_vals, block in ((rows_h, cols_h, vals_h, A.T @ A),
                                                                 (rows_m, cols_m, vals_m, A.T @ R @ A)):
                target_rows.append(np.repeat(idx_cols, len(idx_cols)))
                target_cols.append(np.tile(idx_cols, len(idx_cols)))
                target_vals.append(block.ravel())
        n = 6 * len(nodes)
        H = coo_matrix((np.concatenate(vals_h), (np.concatenate(rows_h), np.concatenate(cols_h))), shape=(n, n)).tocsc()
        M = coo_matrix((np.concatenate(vals_m), (np.concatenate(rows_m), np.concatenate(cols_m))), shape=(n, n)).tocsr()
        lu = splu(H)

        def response(rows: list[np.ndarray], vals: list[np.ndarray], width: int) -> np.ndarray | None:
            """``(n, width)``: the estimate's error per unit of a shared error, ``H^-1 J^T W (de/du)``,
            from each factor's ``J^T W de/du`` block (None: no factor shares it)."""
            if not rows:
                return None
            g = np.zeros((n, width))
            for r, v in zip(rows, vals):
                g[r] += v
            return lu.solve(g)

        tilt = response(shared_rows, shared_vals, 3)  # per unit rotation of the world up
        moved = response(cloud_rows, cloud_vals, 6)  # per unit error of the first cloud
        wanted = list(nodes if keys is None else keys)
        out: dict[int, np.ndarray] = {}
        for start in range(0, len(wanted), batch):
            chunk = wanted[start:start + batch]
            E = np.zeros((n, 6 * len(chunk)))
            for m, k in enumerate(chunk):
                E[col[k]:col[k] + 6, 6 * m:6 * m + 6] = np.eye(6)
            X = lu.solve(E)  # columns of H^-1
            MX = M @ X
            for m, k in enumerate(chunk):
                block = X[:, 6 * m:6 * m + 6].T @ MX[:, 6 * m:6 * m + 6]
                if tilt is not None:
                    G = tilt[col[k]:col[k] + 6]
                    block = block + G @ up_covariance @ G.T
                if moved is not None:
                    G = moved[col[k]:col[k] + 6]
                    block = block + G @ first_cloud[1] @ G.T
                out[k] = 0.5 * (block + block.T)
        return out


def _one_line(exc: BaseException) -> str:
    """GTSAM's multi-line exception text as one line ("... near variable 1 (Symbol: 1).")."""
    lines = [line.strip() for line in str(exc).strip().splitlines() if line.strip()]
    return " ".join(lines[:2]) if lines else type(exc).__name__


def chain_covariance(steps: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Compose ``[(T_k_k+1, Sigma_k_k+1), ...]`` into ``(T_i_j, Sigma_i_j)`` (right perturbations).

    ``T_i_k+1 = T_i_k T_k_k+1`` so ``Sigma_i_k+1 = Ad(T_k_k+1^-1) Sigma_i_k Ad(.)^T + Sigma_k_k+1``.
    Used as a conservative (loop-free) relative uncertainty between two submaps.
    """
    from ..geometry import inverse

    T = np.eye(4)
    S = np.zeros((6, 6))
    for T_step, S_step in steps:
        A = adjoint(inverse(T_step))
        S = A @ S @ A.T + S_step
        T = T @ T_step
    return T, S
