"""Place a new session in an existing map: cross-session cycle hypotheses, verified like loops.

A new session starts with an unknown pose relative to the map. Its submaps are matched to the
map's by place descriptor (independent of any pose), and each hypothesis goes through the loop
closer's own gates (:class:`~submapslam.topology.loop_closure.LoopCloser`): the correspondence
test, the 3D structure gates, and the seed's check that the submaps adjacent in the map
confirm it. The verified links must then agree with each other: each implies a transform
``T_map_session``, and only the largest group of pairwise-consistent links (their implied
transforms put the session's submaps within a tolerance of each other) places the session. With
the session placed, every session submap is tested against the map submaps near where it now
lies (a guided search, as the loop closer's spatial hypotheses). Nothing here writes a graph:
the accepted links are returned as :class:`~submapslam.result.LoopRecord` for the caller.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..config import LoopConfig, SessionConfig
from ..geometry import inverse, rotation_angle
from ..result import LoopRecord
from ..submaps import Submap
from .descriptors import DescriptorIndex
from .loop_closure import Hypothesis, LoopCloser

log = logging.getLogger(__name__)


@dataclass
class Placement:
    """Outcome of placing one session.

    ``T_map_session``: ``(4, 4)`` pose of the session's frame in the map (None: not placed);
    ``records``: every tested cross-session hypothesis (``i`` a map submap, ``j`` a session
    submap, global ids), accepted ones being the links; ``reason``: why placed or not.
    """

    T_map_session: np.ndarray | None
    records: list[LoopRecord] = field(default_factory=list)
    reason: str = ""

    @property
    def links(self) -> list[LoopRecord]:
        return [r for r in self.records if r.accepted]


@dataclass(eq=False)  # compared by identity (holds arrays)
class _Confirmation:
    """The guided search for one candidate placement: the links ``group`` it came from, its frame
    ``T_map_session`` (4, 4), the records tested, session submaps linked / put on the map."""

    group: list[int]
    frame: np.ndarray
    records: list[LoopRecord]
    linked: int
    on_map: int
    agreement: float
    confirmed: bool


class _MapPoses:
    """The map's submap poses, read the way the loop closer reads a graph."""

    def __init__(self, poses: dict[int, np.ndarray]) -> None:
        self.poses = poses
        self.keys = poses.keys()

    def pose(self, key: int) -> np.ndarray:
        return self.poses[key]


VerifyItems = list[tuple[Hypothesis, tuple[int, ...]]]
# verifies ``(hypothesis, adjacent map submaps)`` items against ``submaps`` (global ids) and the
# map's poses ``{id: T_map_submap}``, in order; e.g. on worker processes (batch on Ray)
VerifyMany = Callable[[VerifyItems, list[Submap], dict[int, np.ndarray]], list[LoopRecord]]


def verify_items(closer: LoopCloser, items: VerifyItems, submaps: list[Submap],
                 map_poses: dict[int, np.ndarray]) -> list[LoopRecord]:
    """The loop closer's gates without the odometry-chain plausibility (there is no chain between
    sessions): correspondence, distance, structure (3D), the given adjacent map submaps."""
    graph = _MapPoses(map_poses)
    return [closer.verify(hyp, submaps, graph, plausibility=False, neighbours=adjacent) for hyp, adjacent in items]


def implied_frame(T_map_i: np.ndarray, T_i_j: np.ndarray, T_session_j: np.ndarray) -> np.ndarray:
    """``T_map_session`` that a link ``T_i_j`` (map submap i, session submap j) implies."""
    return T_map_i @ T_i_j @ inverse(T_session_j)


def consistent(F_a: np.ndarray, F_b: np.ndarray, T_session_a: np.ndarray, T_session_b: np.ndarray,
               config: SessionConfig) -> bool:
    """Do two links agree? Each link's frame places both session submaps; the two placements
    must be within ``config``'s tolerance (grows with the session path between the two)."""
    d = float(np.linalg.norm(T_session_a[:3, 3] - T_session_b[:3, 3]))
    tol_m = config.consistency_tolerance_m + config.consistency_per_m * d
    tol_rad = np.deg2rad(config.consistency_tolerance_deg)
    for T in (T_session_a, T_session_b):
        delta = inverse(F_a @ T) @ (F_b @ T)
        if np.linalg.norm(delta[:3, 3]) > tol_m or rotation_angle(delta) > tol_rad:
            return False
    return True


def consistent_groups(frames: list[np.ndarray], session_poses: list[np.ndarray], session_ids: list[int],
                      config: SessionConfig, scores: list[float] | None = None, min_support: int = 1) -> list[list[int]]:
    """Candidate placements: groups of pairwise-consistent links (a greedy clique from every seed),
    best first, each at most once, those from at least ``min_support`` distinct session submaps.

    Best = most distinct session submaps (links of one session submap to adjacent map submaps
    are one observation, not independent evidence), then most links, then the highest summed
    ``scores`` (fitness).
    """
    n = len(frames)
    if n == 0:
        return []
    scores = scores or [0.0] * n
    ok = np.eye(n, dtype=bool)
    for a in range(n):
        for b in range(a + 1, n):
            ok[a, b] = ok[b, a] = consistent(frames[a], frames[b], session_poses[a], session_poses[b], config)
    degree = ok.sum(axis=1)
    keyed: dict[tuple[int, ...], tuple[int, int, float]] = {}
    for seed in range(n):
        group = [seed]
        for c in sorted(np.flatnonzero(ok[seed]), key=lambda c: (-degree[c], -scores[c], c)):
            c = int(c)
            if c not in group and all(ok[c, g] for g in group):
                group.append(c)
        members = tuple(sorted(group))
        keyed.setdefault(members, (len({session_ids[g] for g in group}), len(group), sum(scores[g] for g in group)))
    # ties keep the order of the first seed that found them (the greedy search's own order)
    order = sorted(keyed, key=lambda g: keyed[g], reverse=True)
    return [list(g) for g in order if keyed[g][0] >= min_support]


def largest_consistent_group(frames: list[np.ndarray], session_poses: list[np.ndarray], session_ids: list[int],
                             config: SessionConfig, scores: list[float] | None = None) -> list[int]:
    """Indices of the best set of pairwise-consistent links (see :func:`consistent_groups`)."""
    groups = consistent_groups(frames, session_poses, session_ids, config, scores)
    return groups[0] if groups else []


def distinct(group: list[int], session_ids: list[int]) -> int:
    """Distinct session submaps among the links ``group``."""
    return len({session_ids[g] for g in group})


class SessionPlacer:
    """Places sessions against a map with the loop closer's verification.

    ``closer``: a :class:`LoopCloser` built for the map's kind of log (its gates, registration
    voxel and prepared clouds); ``config``: the placement's own settings.
    """

    def __init__(self, closer: LoopCloser, config: SessionConfig, verify_many: VerifyMany | None = None,
                 window: int = 48) -> None:
        """``verify_many``: runs batches of independent tests elsewhere (place recognition ``window``
        hypotheses at a time, each densify pass at once); the decisions are those of the tests
        one at a time (tests past an early stop are dropped)."""
        self.closer = closer
        self.config = config
        self.verify_many = verify_many
        self.window = window

    @property
    def loops(self) -> LoopConfig:
        return self.closer.config

    def _verify(self, hyp: Hypothesis, submaps: list[Submap], map_poses: _MapPoses) -> LoopRecord:
        """One test (:func:`verify_items`), the map's own adjacent submaps confirming."""
        return self._verify_all([hyp], submaps, map_poses)[0]

    def _verify_all(self, hyps: list[Hypothesis], submaps: list[Submap], map_poses: _MapPoses) -> list[LoopRecord]:
        """Independent tests, in order: here, or through ``verify_many`` when there are several."""
        items = [(h, tuple(n for n in (h.i - 1, h.i + 1) if n in map_poses.keys)) for h in hyps]
        if self.verify_many is None or len(items) < 2:
            return verify_items(self.closer, items, submaps, map_poses.poses)
        return self.verify_many(items, submaps, map_poses.poses)

    def place(self, submaps: list[Submap], map_ids: list[int], map_poses: dict[int, np.ndarray],
              map_descriptors: dict[int, np.ndarray], session_ids: list[int],
              session_poses: dict[int, np.ndarray], session_descriptors: dict[int, np.ndarray]) -> Placement:
        """Place one session.

        ``submaps``: every submap, indexed by global id (map's and session's); ``map_ids`` /
        ``session_ids``: global ids of each side; ``map_poses``: ``T_map_submap``;
        ``session_poses``: ``T_session_submap`` (the session's own frame); descriptors per id.

        Three steps: place recognition gives verified links; groups of mutually consistent links
        are candidate placements (best first); the first candidate that the rest of the session
        confirms by the guided search places the session.
        """
        cfg = self.config
        graph = _MapPoses(map_poses)
        links, records, tested = self._recognise(submaps, map_ids, map_descriptors, session_ids, session_poses,
                                                 session_descriptors, graph)
        accepted = [r for r in records if r.accepted]
        frames = [f for f, _, _ in links]
        link_js = [j for _, j, _ in links]
        fitness = [r.fitness for _, _, r in links]
        # weaker candidates only when recognition saw every hypothesis it had (else the others, and
        # so whether a candidate is ambiguous, are unknown)
        weakest = cfg.min_links if tested >= cfg.max_recognition_tests else min(cfg.min_candidate_links, cfg.min_links)
        groups = consistent_groups(frames, [session_poses[j] for j in link_js], link_js, cfg, fitness)
        support = distinct(groups[0], link_js) if groups else 0
        if support < weakest:
            for rec in accepted:
                rec.accepted, rec.information = False, None
                rec.reason = f"not confirmed: consistent links from {support} session submap(s) < {weakest} needed"
            why = (f"not placed: {len(accepted)} verified match(es) with the map, consistent ones from at most "
                   f"{support} session submap(s) (need {weakest}); {tested} hypotheses tested")
            return Placement(None, records, why)
        # the best candidate the guided search confirms places the session; one from fewer than
        # min_links session submaps only when no other group of links (weaker ones included) is
        # confirmed too: look-alike places, a symmetric building, confirm a wrong frame as well
        candidates = groups[: cfg.max_candidates]
        outcomes: list[_Confirmation] = []
        for rank, group in enumerate(candidates):
            outcome = self._confirm(group, links, {(r.i, r.j) for r in records}, submaps, map_ids, map_poses,
                                    session_ids, session_poses, graph)
            outcomes.append(outcome)
            log.info("candidate placement %d (%d links from %d session submaps): confirmed by %d of %d (%.0f%%)",
                     rank + 1, len(group), distinct(group, link_js), outcome.linked, outcome.on_map,
                     100 * outcome.agreement)
            if outcome.confirmed and distinct(group, link_js) >= cfg.min_links:
                break
        confirmed = [o for o in outcomes if o.confirmed]
        placing = [o for o in confirmed if distinct(o.group, link_js) >= weakest]
        outcome = placing[0] if placing else outcomes[0]  # none confirmed: report the best candidate's search
        outcome.confirmed = bool(placing)
        if len(confirmed) > 1 and distinct(outcome.group, link_js) < cfg.min_links:
            for o in confirmed:
                o.confirmed = False
            for rec in accepted:
                rec.accepted, rec.information = False, None
                rec.reason = "ambiguous: other cross-session links confirm another placement"
            for rec in (r for o in outcomes for r in o.records if r.accepted):
                rec.accepted, rec.information = False, None
                rec.reason = "ambiguous: the session is confirmed in more than one place"
            return Placement(None, records + outcome.records, (
                f"not placed: ambiguous, {len(confirmed)} candidate placements (from fewer than {cfg.min_links} "
                f"session submaps each by place recognition) are each confirmed by the rest of the session"))
        members = {id(links[k][2]) for k in outcome.group} if outcome.confirmed else set()
        for rec in accepted:
            if id(rec) not in members:
                rec.accepted, rec.information = False, None
                rec.reason = ("inconsistent with the other cross-session links" if outcome.confirmed else
                              "placement not confirmed by the other session submaps")
        records += outcome.records
        group_support = distinct(outcome.group, link_js)
        if not outcome.confirmed:
            for rec in outcome.records:
                if rec.accepted:
                    rec.accepted, rec.information = False, None
                    rec.reason = "placement not confirmed by the other session submaps"
            return Placement(None, records, (
                f"not placed: the best placement ({group_support} session submaps agreeing by place recognition; "
                f"{len(candidates)} candidate placement(s) tried) is confirmed by only {outcome.linked} of the "
                f"{outcome.on_map} session submaps it puts on the map ({outcome.agreement:.0%}; "
                f"{cfg.min_agreement:.0%} and {cfg.min_links} needed)"))
        n_links = sum(r.accepted for r in records)
        log.info("session placed by %d links (%d in the recognition group, candidate %d)", n_links,
                 len(outcome.group), outcomes.index(outcome) + 1)
        return Placement(outcome.frame, records, (
            f"placed by {n_links} verified link(s) ({len(outcome.group)} agreeing by place recognition, from "
            f"{group_support} session submaps; {outcome.linked} of the {outcome.on_map} session submaps on the "
            f"map confirm it)"))

    def _recognise(self, submaps: list[Submap], map_ids: list[int], map_descriptors: dict[int, np.ndarray],
                   session_ids: list[int], session_poses: dict[int, np.ndarray],
                   session_descriptors: dict[int, np.ndarray], graph: _MapPoses
                   ) -> tuple[list[tuple[np.ndarray, int, LoopRecord]], list[LoopRecord], int]:
        """Place recognition: descriptor hypotheses, verified; stops once consistent links come from
        ``enough_links`` session submaps. Returns the links ``(T_map_session implied, session
        submap j, record)``, every tested record and the number of tests."""
        cfg = self.config
        index = DescriptorIndex()
        for i in map_ids:
            index.add(i, map_descriptors[i])
        records: list[LoopRecord] = []
        links: list[tuple[np.ndarray, int, LoopRecord]] = []
        # each session submap's nearest map submaps by descriptor, along the session, capped (the
        # most alike pairs first instead found a wrong frame first in a symmetric building: its
        # look-alike places come in consistent groups)
        hyps = [Hypothesis(i, j, "session", None, yaw, None) for j in session_ids
                for i, dist, yaw in index.query(session_descriptors[j], cfg.descriptor_top_k)
                if dist <= cfg.descriptor_max_distance][: cfg.max_recognition_tests]
        tested = 0
        step = self.window if self.verify_many is not None else 1
        for start in range(0, len(hyps), step):
            block = hyps[start:start + step]
            for hyp, rec in zip(block, self._verify_all(block, submaps, graph)):
                tested += 1
                records.append(rec)
                if rec.accepted:
                    links.append((implied_frame(graph.pose(rec.i), rec.T_i_j, session_poses[hyp.j]), hyp.j, rec))
                    frames = [f for f, _, _ in links]
                    js = [m for _, m, _ in links]
                    group = largest_consistent_group(frames, [session_poses[m] for m in js], js, cfg,
                                                     [r.fitness for _, _, r in links])
                    if distinct(group, js) >= cfg.enough_links:
                        return links, records, tested
        return links, records, tested

    def _confirm(self, group: list[int], links: list[tuple[np.ndarray, int, LoopRecord]],
                 done: set[tuple[int, int]], submaps: list[Submap],
                 map_ids: list[int], map_poses: dict[int, np.ndarray], session_ids: list[int],
                 session_poses: dict[int, np.ndarray], graph: _MapPoses) -> _Confirmation:
        """The guided search for one candidate placement (the links ``group``): each session submap
        against the map submaps near where the candidate puts it. A right placement is confirmed by
        most session submaps that land on the map, and by at least ``min_links`` of them. Pairs in
        ``done`` (tested by place recognition) are not tested again."""
        cfg, loops = self.config, self.loops
        best = max(group, key=lambda k: links[k][2].fitness)
        linked = {links[k][1] for k in group}
        radius = loops.spatial_min_radius or (5.0 if self.closer.planar else 20.0)
        map_xyz = np.array([map_poses[i][:3, 3] for i in map_ids])
        records: list[LoopRecord] = []
        # the frame each verified link implies, by session submap: a session submap is searched
        # for through the link nearest to it along the session (drift between the two sessions
        # bends the frame along the way; one frame for all would miss the far end)
        local = {links[k][1]: links[k][0] for k in group}
        tried = set(done)
        # outward from the candidate's links along the session, so that each link found moves the
        # frame its neighbours are searched through
        seeds = sorted(local)
        order = sorted(session_ids, key=lambda j: (min(abs(j - m) for m in seeds), j))
        for _ in range(max(1, cfg.guided_passes)):  # later passes: through the links the last one found
            on_map, found = 0, False
            for j in order:
                F_j = local[min(local, key=lambda m: (abs(m - j), m))]
                Q = F_j @ session_poses[j]
                d = np.linalg.norm(map_xyz - Q[:3, 3], axis=1)
                near = [map_ids[k] for k in np.argsort(d, kind="stable")[: cfg.guided_per_submap] if d[k] <= radius]
                on_map += bool(near) or j in linked
                for i in near:
                    if (i, j) in tried:
                        continue
                    tried.add((i, j))
                    guess = inverse(map_poses[i]) @ Q
                    rec = self._verify(Hypothesis(i, j, "session", guess, None, loops.min_search_window), submaps,
                                       graph)
                    frame = implied_frame(map_poses[i], rec.T_i_j, session_poses[j]) if rec.accepted else None
                    if rec.accepted and not consistent(F_j, frame, session_poses[j], session_poses[j], cfg):
                        rec.accepted, rec.information = False, None
                        rec.reason = "inconsistent with the session's placement"
                    records.append(rec)
                    if rec.accepted:
                        found |= j not in local
                        linked.add(j)
                        local.setdefault(j, frame)
            if not found:
                break
        agreement = len(linked) / max(on_map, 1)
        confirmed = agreement >= cfg.min_agreement and len(linked) >= cfg.min_links
        return _Confirmation(group, links[best][0], records, len(linked), on_map, agreement, confirmed)

    def densify(self, submaps: list[Submap], map_ids: list[int], map_poses: dict[int, np.ndarray],
                session_ids: list[int], session_poses: dict[int, np.ndarray],
                tested: set[tuple[int, int]]) -> list[LoopRecord]:
        """After a placement and an optimisation: test each session submap against the map
        submaps near it in the current estimate (``session_poses`` now in the map frame), as the
        loop closer's spatial hypotheses; pairs in ``tested`` are skipped. A link must agree with
        the estimate within the consistency tolerance. Returns every tested record."""
        cfg, loops = self.config, self.loops
        graph = _MapPoses(map_poses)
        radius = loops.spatial_min_radius or (5.0 if self.closer.planar else 20.0)
        map_xyz = np.array([map_poses[i][:3, 3] for i in map_ids])
        hyps = []
        for j in session_ids:
            Q = session_poses[j]
            d = np.linalg.norm(map_xyz - Q[:3, 3], axis=1)
            near = [map_ids[k] for k in np.argsort(d, kind="stable")[: cfg.densify_per_submap] if d[k] <= radius]
            hyps += [Hypothesis(i, j, "session", inverse(map_poses[i]) @ Q, None, loops.min_search_window)
                     for i in near if (i, j) not in tested]
        records = self._verify_all(hyps, submaps, graph)
        for rec in records:
            Q = session_poses[rec.j]
            if rec.accepted and not consistent(np.eye(4), implied_frame(map_poses[rec.i], rec.T_i_j, Q), Q, Q, cfg):
                rec.accepted, rec.information = False, None
                rec.reason = "inconsistent with the merged estimate"
        return records
