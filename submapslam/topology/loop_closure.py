"""Cycle hypotheses on the submap graph: propose, test, check, then hand to the optimiser.

For every closed submap ``k`` the graph proposes hypotheses ``(i, k)`` with older submaps:
    * spatial: anchors that may be close given the current estimate and its marginal
      covariance (the search radius grows with uncertainty); for a 2D laser, the submaps whose
      *paths* may be close (a planar submap sees what is around its own few metres of path);
    * descriptor: place recognition, independent of drift;
    * hints: manual pairs ("a button pushed at a known landmark").
Each goes through the correspondence test (coarse alignment without a good guess, then fine
registration, gated on fitness, inlier RMSE and overlap), then the seed's check: the implied
transform must also explain the submaps adjacent to ``i`` ("move to adjacent nodes and see
whether the readings agree"), and must be plausible under the current estimate's uncertainty.
Only then is it returned as a loop constraint; the graph builder adds it as a robust edge.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..config import LoopConfig
from ..geometry import inverse, rotation_angle, so3_log
from ..registration.correspondence import (
    CorrespondenceResult,
    below,
    check_correspondence,
    match_voxel,
)
from ..registration.point_to_line import first_point_per_cell
from ..registration.spatial import SubmapClouds
from ..result import LoopRecord
from ..submaps import Submap
from .descriptors import DescriptorIndex, compute_descriptor

log = logging.getLogger(__name__)

# chi-square 99.9% quantiles for the translation gate (2 DOF planar, 3 DOF spatial)
_CHI2_999 = {3: 16.27, 6: 22.46}
#: [m] planar spatial proposals: a submap's path is its scan positions, one per square of this side
_PATH_CELL_M = 0.5
#: planar spatial proposals: submaps at least this far apart on the chain are also near when their
#: paths are; nearer ones only when their anchors are (their paths meet through the submaps between
#: them: 3D logs likewise ask a cycle for 4 submap lengths of path)
_PATH_MIN_GAP = 4
#: [m] planar spatial proposals: a submap whose path passes within this of the new submap's is
#: proposed as one whose anchor is within the search radius's floor would be (farther with the
#: estimate's uncertainty). Ranked alike: a path p metres away counts as an anchor p + (floor -
#: this) away. (Paths ranked by their distance alone, the floor for both: MIT CSAIL 0.116 -> 0.102 m,
#: FR079 0.077 -> 0.080 m, closures 69 -> 96; with this: 0.101 and 0.075 m, BENCHMARKS.md.)
_PATH_NEAR_M = 2.0
#: [m] the same for a log without wheel odometry: the radius's floor, paths ranked by their distance
#: alone. Its odometry drifts more and the anchors' estimate says less of where two passes meet
#: (Intel 0.52 -> 0.30 m, MIT CSAIL 0.78 -> 0.28 m, FR079 0.075 -> 0.080 m without wheels)
_PATH_NEAR_NO_WHEELS_M = 5.0


def se3_log_gtsam(T: np.ndarray) -> np.ndarray:
    """Small-pose tangent vector in GTSAM order ``(rx, ry, rz, tx, ty, tz)`` (decoupled)."""
    return np.concatenate([so3_log(T[:3, :3]), T[:3, 3]])


class GraphEstimate(Protocol):
    """What the loop closer reads of the submap graph (it never writes it)."""

    def pose(self, key: int) -> np.ndarray:
        """Current ``(4, 4)`` ``T_world_submap``."""

    def marginal_covariance(self, key: int) -> np.ndarray:
        """``(6, 6)`` marginal covariance (GTSAM order) of an anchor."""

    def odometry_chain(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        """Odometry-only ``(T_i_j, Sigma_i_j)`` between anchors ``i < j``."""


@dataclass
class Hypothesis:
    i: int
    j: int
    source: str
    initial_guess: np.ndarray | None  # T_i_j from the current estimate, or None
    yaw_hint: float | None
    search_radius: float | None


class LoopCloser:
    """Proposes and verifies loop closures between submaps; returns them as records.

    Reads the graph through a :class:`GraphEstimate`; an accepted record is a constraint the
    caller adds (:class:`~submapslam.graph_builder.GraphBuilder`). Keeps the place descriptor
    of every submap it has seen in its own index.
    """

    def __init__(self, config: LoopConfig, *, planar: bool, voxel_size: float, max_range: float,
                 submap_length: float = 12.0, clouds: SubmapClouds | None = None, timer=None) -> None:
        """``submap_length``: the submaps' cut length [m] (scales the shortest cycle); ``clouds``:
        the prepared 3D clouds shared with the caller (one is made when not given)."""
        self.config = config
        self.submap_length = submap_length
        self._min_radius = config.spatial_min_radius or (5.0 if planar else 20.0)
        self.planar = planar
        self.voxel = voxel_size
        self._match_voxel = match_voxel(voxel_size, planar)
        self.clouds = clouds if clouds is not None else SubmapClouds(self._match_voxel)
        self.max_range = max_range
        self.index = DescriptorIndex()
        self._tested: set[tuple[int, int]] = set()
        self._timer = timer
        self._paths: dict[int, np.ndarray] = {}  # planar: each submap's thinned path (anchor frame)

    def _time(self, stage: str):
        from contextlib import nullcontext

        return self._timer(stage) if self._timer is not None else nullcontext()

    # ------------------------------------------------------------------ proposal
    def _radius(self, cov_i: np.ndarray, cov_j: np.ndarray) -> float:
        """Search radius [m] from the anchors' marginal translation covariances."""
        c = self.config
        block = cov_i[3:6, 3:6] + cov_j[3:6, 3:6]
        if self.planar:
            block = block[:2, :2]
        sigma = float(np.sqrt(max(np.linalg.eigvalsh(block).max(), 0.0)))
        floor = self._min_radius
        return float(np.clip(floor + c.spatial_sigma * sigma, floor, max(floor, c.spatial_max_radius)))

    def propose(self, new: Submap, descriptor: np.ndarray | None, submaps: list[Submap], graph: GraphEstimate,
                hint_pairs: list[tuple[int, int]], wheel_odometry: bool = True) -> list[Hypothesis]:
        """Hypotheses ``(i, new.id)`` with older submaps: spatial, by ``descriptor``, and hints.
        ``wheel_odometry``: whether the log's odometry had wheels to follow (planar path proposals)."""
        c = self.config
        k = new.id
        eligible = min(k - c.min_submap_gap, self._last_cycle_partner(k, submaps))
        hyps: dict[int, Hypothesis] = {}
        if eligible < 0 and not hint_pairs:
            return []
        T_k = graph.pose(k)
        cov_k = graph.marginal_covariance(k)
        # spatial
        if eligible >= 0:
            anchors = np.array([graph.pose(i)[:3, 3] for i in range(eligible + 1)])
            d = np.linalg.norm(anchors - T_k[:3, 3], axis=1)
            far_on_chain = min(eligible, k - _PATH_MIN_GAP) + 1  # submaps 0 .. far_on_chain - 1
            if self.planar and far_on_chain > 0:
                # a path passing within p of the new one's ranks as an anchor p + (floor - near) away
                near = _PATH_NEAR_M if wheel_odometry else _PATH_NEAR_NO_WHEELS_M
                by_path = self._path_distances(new, submaps[:far_on_chain], graph) + max(self._min_radius - near, 0.0)
                d[:far_on_chain] = np.minimum(d[:far_on_chain], by_path)
            order = np.argsort(d, kind="stable")
            for i in order[: 4 * max(1, c.descriptor_top_k)]:
                i = int(i)
                radius = self._radius(graph.marginal_covariance(i), cov_k)
                if d[i] > radius or len(hyps) >= 3:
                    continue
                window = float(np.clip(radius - self._min_radius, c.min_search_window, c.max_search_window))
                hyps[i] = Hypothesis(i, k, "spatial", inverse(graph.pose(i)) @ T_k, None, window)
        # appearance
        if c.use_descriptor and descriptor is not None and eligible >= 0:
            for i, dist, yaw in self.index.query(descriptor, c.descriptor_top_k,
                                                 exclude_ids=set(range(eligible + 1, k + 1))):
                if dist <= c.descriptor_max_distance and i not in hyps:
                    hyps[i] = Hypothesis(i, k, "descriptor", None, yaw, None)
        # manual hints
        for a, b in hint_pairs:
            if b == k and (a, b) not in self._tested:
                hyps[a] = Hypothesis(a, k, "hint", None, None, None)
        return [h for h in hyps.values() if (h.i, h.j) not in self._tested]

    def _path_distances(self, new: Submap, older: list[Submap], graph: GraphEstimate) -> np.ndarray:
        """``(len(older),)`` planar distance [m] from ``new``'s path to each older submap's path,
        both placed by the current estimate (each path: its scan positions, one per
        :data:`_PATH_CELL_M` square). A 2D laser's submap sees what is around its own path (rooms,
        corridors), and one submap's path is metres long: its anchor (the first scan) alone can be
        far from the place two passes share."""
        mine = self._world_path(new, graph)
        theirs = [self._world_path(submap, graph) for submap in older]
        points = np.concatenate(theirs)
        starts = np.cumsum([0] + [len(t) for t in theirs[:-1]])
        nearest = np.full(len(points), np.inf)
        for q in mine:  # a few dozen positions: one pass over the older paths each
            np.minimum(nearest, np.hypot(points[:, 0] - q[0], points[:, 1] - q[1]), out=nearest)
        return np.minimum.reduceat(nearest, starts)

    def _world_path(self, submap: Submap, graph: GraphEstimate) -> np.ndarray:
        """``(P, 2)`` the submap's thinned scan positions in the world frame (current estimate)."""
        path = self._paths.get(submap.id)
        if path is None:
            xy = submap.T_anchor_scans[:, :2, 3]
            path = self._paths[submap.id] = xy[first_point_per_cell(xy, _PATH_CELL_M)]
        T = graph.pose(submap.id)
        return path @ T[:2, :2].T + T[:2, 3]

    def _last_cycle_partner(self, k: int, submaps: list[Submap]) -> int:
        """Newest submap far enough back along the odometry path to close a cycle with ``k``.

        Submaps two or three apart on the path overlap through odometry alone; a "loop" between
        them is a second odometry edge, and a misaligned one bends the chain where nothing can
        contradict it. A cycle needs ``min_loop_path_m`` of driving between the two anchors.
        """
        min_path = self.config.min_loop_path_m
        if min_path is None:
            min_path = 0.0 if self.planar else 4.0 * self.submap_length
        if min_path <= 0:
            return k
        start = np.cumsum([0.0] + [s.distance for s in submaps[:k]])  # path at each anchor [m]
        far = np.flatnonzero(start[k] - start[:k] >= min_path)
        return int(far[-1]) if len(far) else -1

    # ------------------------------------------------------------------ testing
    def _correspond(self, target: Submap, source: Submap, initial_guess, yaw_hint, search_radius,
                    refine_only: bool = False) -> CorrespondenceResult:
        c = self.config
        if self.planar:
            src, tgt = source.points, target.points
        else:  # downsampled cloud, normals and features once per submap
            src, tgt = self.clouds(source), self.clouds(target)
        return check_correspondence(
            src, tgt, planar=self.planar, initial_guess=initial_guess,
            yaw_hint=yaw_hint, voxel_size=self._match_voxel, min_fitness=c.min_fitness,
            max_inlier_rmse=c.max_inlier_rmse, min_overlap=c.min_overlap, search_radius=search_radius,
            yaw_window_deg=c.yaw_window_deg, refine_only=refine_only,
        )

    def _near_enough(self, T_i_j: np.ndarray) -> tuple[bool, str]:
        """The registered anchors must be within ``max_loop_distance_m`` (3D: 2 submap lengths)."""
        limit = self.config.max_loop_distance_m
        if limit is None:
            limit = float("inf") if self.planar else 2.0 * self.submap_length
        distance = float(np.linalg.norm(T_i_j[:3, 3]))
        if round(distance, 4) > limit:
            return False, f"anchors {distance:.1f} m apart > {limit:.1f} m: too far apart for a closure"
        return True, "ok"

    def _structure_gate(self, res: CorrespondenceResult) -> tuple[bool, str]:
        """3D: the walls, poles and cars must agree, not only the ground (scores to 4 decimals)."""
        c = self.config
        if round(res.structure_overlap, 4) < c.min_structure_overlap:
            return False, below("structure overlap", res.structure_overlap, c.min_structure_overlap)
        if round(res.plane_rmse, 4) > c.max_plane_rmse:
            return False, f"structure point-to-plane RMSE {res.plane_rmse:.3f} m > {c.max_plane_rmse:.3f} m"
        return True, "ok"

    def _neighbour_check(self, hyp: Hypothesis, T_i_j: np.ndarray, first: CorrespondenceResult,
                         submaps: list[Submap], graph: GraphEstimate,
                         neighbours: tuple[int, ...] | None = None) -> tuple[bool, str]:
        """Seed's check: the hypothesis must also explain the submaps adjacent to ``i``.

        Submap ``j`` is placed next to ``i - 1`` and ``i + 1`` through the hypothesis and refined
        there. A neighbour that overlaps and lands where the hypothesis says confirms it; one
        that overlaps but has to move away (or fits badly) contradicts it; one without overlap
        says nothing. Accept with no contradiction and at least one confirmation (or, when no
        neighbour overlaps, a very clear first match). ``neighbours``: the submaps to check
        (default ``i - 1`` and ``i + 1``).
        """
        c = self.config
        confirm = contradict = 0
        for n in neighbours if neighbours is not None else (hyp.i - 1, hyp.i + 1):
            if n < 0 or n >= hyp.j - c.min_submap_gap + 1 or n >= len(submaps):
                continue
            T_n_j = inverse(graph.pose(n)) @ graph.pose(hyp.i) @ T_i_j
            res = self._correspond(submaps[n], submaps[hyp.j], T_n_j, None, None, refine_only=True)
            if res.overlap < c.neighbour_min_overlap:
                continue
            delta = inverse(T_n_j) @ res.T_target_source
            agrees = (np.linalg.norm(delta[:3, 3]) <= c.consistency_tolerance_m
                      and np.rad2deg(rotation_angle(delta)) <= c.consistency_tolerance_deg
                      and not res.reason.startswith("inlier RMSE"))  # the test's own, voxel-scaled gate
            confirm += agrees
            contradict += not agrees
        if contradict:
            return False, f"adjacent submaps disagree ({contradict} contradict, {confirm} confirm)"
        if confirm:
            return True, f"{confirm} adjacent submap(s) confirm"
        if first.fitness >= c.unconfirmed_min_fitness:
            return True, "no adjacent overlap; clear match accepted"
        return False, "no adjacent submap overlaps to confirm it"

    def _plausible(self, hyp: Hypothesis, T_i_j: np.ndarray, graph: GraphEstimate) -> tuple[bool, str]:
        """Mahalanobis gate of the loop against the current estimate.

        The uncertainty is the odometry chain's between ``i`` and ``j`` (loop edges ignored: a
        conservative bound that no earlier loop, right or wrong, can shrink), tested on
        ``(x, y, yaw)`` for planar runs and on the full pose otherwise.
        """
        if hyp.source == "hint":
            return True, "manual hint"
        _, cov = graph.odometry_chain(hyp.i, hyp.j)
        T_est = inverse(graph.pose(hyp.i)) @ graph.pose(hyp.j)
        err = se3_log_gtsam(inverse(T_est) @ T_i_j)
        idx = [2, 3, 4] if self.planar else list(range(6))
        floor = np.array([np.deg2rad(1.0)] * 3 + [0.2] * 3)[idx] ** 2  # submap-level noise floor
        S = cov[np.ix_(idx, idx)] + np.diag(floor)
        m2 = float(err[idx] @ np.linalg.solve(S, err[idx]))
        limit = _CHI2_999[len(idx)]
        if m2 > limit:
            return False, f"implausible under current uncertainty (Mahalanobis^2 {m2:.1f} > {limit})"
        return True, "plausible"

    def _reachable(self, hyp: Hypothesis, graph: GraphEstimate) -> tuple[bool, str]:
        """Cheap check before registering a descriptor hypothesis: can it pass :meth:`_plausible`?

        A descriptor match means the two anchors see one place within the descriptor radius
        ``R``, so the loop's translation is at most ``R``. Its error against the estimate is then
        at least ``d - R`` (``d``: the anchors' estimated distance), and the gate's Mahalanobis
        distance at least ``(d - R)^2 / lambda_max`` of the translation block (a marginal never
        exceeds the joint form). When even that bound fails, no registration result can pass.
        """
        if hyp.source != "descriptor" or self.planar:  # planar tests are cheap; 2D results stay as they were
            return True, ""
        _, cov = graph.odometry_chain(hyp.i, hyp.j)
        d = float(np.linalg.norm((inverse(graph.pose(hyp.i)) @ graph.pose(hyp.j))[:3, 3]))
        excess = d - self.config.descriptor_radius
        if excess <= 0:
            return True, ""
        S = cov[3:6, 3:6] + np.eye(3) * 0.2**2  # the submap-level floor of _plausible
        bound = excess**2 / float(np.linalg.eigvalsh(S).max())
        limit = _CHI2_999[6]
        if bound > limit:
            return False, (f"implausible under current uncertainty before registration (anchors {d:.1f} m apart, "
                           f"Mahalanobis^2 >= {bound:.1f} > {limit})")
        return True, ""

    def process(self, new: Submap, submaps: list[Submap], graph: GraphEstimate,
                hint_pairs: list[tuple[int, int]], wheel_odometry: bool = True) -> list[LoopRecord]:
        """Test the hypotheses for a newly closed submap (``wheel_odometry``: as for
        :meth:`propose`); return every tested one.

        Accepted records carry the constraint (``T_i_j`` and the registration's information);
        nothing is added to the graph here.
        """
        with self._time("descriptors"):
            descriptor = compute_descriptor(new.points, planar=self.planar, max_range=self.config.descriptor_radius)
        with self._time("loop_proposal"):
            hyps = self.propose(new, descriptor, submaps, graph, hint_pairs, wheel_odometry)
        records: list[LoopRecord] = []
        with self._time("loop_testing"):
            for hyp in hyps:
                self._tested.add((hyp.i, hyp.j))
                records.append(self._test(hyp, submaps, graph))
        self.index.add(new.id, descriptor)
        return records

    def replay(self, new: Submap, records: list[LoopRecord]) -> list[LoopRecord]:
        """What :meth:`process` did for ``new`` in an earlier run, from its ``records``: the
        descriptor is indexed and the pairs marked tested, with no test run; returns ``records``."""
        with self._time("descriptors"):
            descriptor = compute_descriptor(new.points, planar=self.planar, max_range=self.config.descriptor_radius)
        self._tested.update((rec.i, rec.j) for rec in records)
        self.index.add(new.id, descriptor)
        return records

    def _test(self, hyp: Hypothesis, submaps: list[Submap], graph: GraphEstimate) -> LoopRecord:
        """One hypothesis through the gates: reachable, correspondence, structure (3D),
        plausible under the estimate, confirmed by the adjacent submaps."""
        reachable, why = self._reachable(hyp, graph)
        if not reachable:
            return LoopRecord(hyp.i, hyp.j, hyp.source, False, 0.0, 0.0, float("inf"), why, None)
        record = self.verify(hyp, submaps, graph)
        if record.accepted:
            log.info("loop %d-%d accepted (%s): %s", hyp.i, hyp.j, hyp.source, record.reason)
        return record

    def verify(self, hyp: Hypothesis, submaps: list[Submap], graph: GraphEstimate, *, plausibility: bool = True,
               neighbours: tuple[int, ...] | None = None) -> LoopRecord:
        """The gates a hypothesis passes to become a constraint: correspondence, distance,
        structure (3D), plausibility under the estimate's odometry chain (``plausibility``; off
        between sessions, which have no chain) and the adjacent submaps (``neighbours``: which;
        default ``i``'s neighbours in the chain)."""
        res = self._correspond(submaps[hyp.i], submaps[hyp.j], hyp.initial_guess, hyp.yaw_hint, hyp.search_radius)
        accepted, reason = res.accepted, res.reason
        if accepted:
            accepted, reason = self._near_enough(res.T_target_source)
        if accepted and not self.planar:
            accepted, reason = self._structure_gate(res)
        if accepted and plausibility:
            accepted, reason = self._plausible(hyp, res.T_target_source, graph)
        if accepted:
            accepted, reason = self._neighbour_check(hyp, res.T_target_source, res, submaps, graph, neighbours)
        return LoopRecord(hyp.i, hyp.j, hyp.source, accepted, res.fitness, res.overlap, res.inlier_rmse, reason,
                          res.T_target_source, res.structure_overlap, res.plane_rmse,
                          res.information_gtsam if accepted else None)
