"""Merge sessions into one map: place each new session, then optimise the merged graph.

The merged graph holds every session's submaps (global ids, session order), every session's
own edges (odometry and its loops), and the cross-session links that placed a session (robust
loop edges, checked again by GNC and the final check). Session 0's first anchor is the map
frame (a hard prior); each later session's first anchor has a weak prior only, so a session
that was never placed keeps its own frame instead of making the system singular.

A *frozen* base map (``freeze_base``; Cartographer's frozen trajectories) does not move: every
anchor of it is held by a hard prior, its own edges are carried over without being judged again,
and its scan poses, anchors and covariances come out exactly as they went in. The new sessions
are placed and optimised against it, so whatever was drawn or annotated in the map's frame
stays where it was.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..backend.pose_graph import GROUND_ATTITUDE_PRIOR
from ..config import PipelineConfig, narrow_field
from ..geometry import blend_poses_many, inverse
from ..graph_builder import PRIOR_INFORMATION, WALL_VERTICAL_PRIOR
from ..result import SlamResult
from ..session_map import SessionInfo, SessionMap
from ..submaps import Submap
from ..uncertainty import calibrate, covariance_scale

if TYPE_CHECKING:
    from ..topology.session_placement import VerifyMany

log = logging.getLogger(__name__)


def session_names(sources: list[str | Path], taken: list[str] | tuple[str, ...] = ()) -> list[str]:
    """One unique name per log: the file name without its extensions (``intel.clf.bz2`` ->
    ``intel``), a folder's own name; repeats (also of the ``taken`` names, e.g. a map's sessions)
    get ``_2``, ``_3`` ...; unsafe characters become ``_``."""
    names: list[str] = list(taken)
    for src in sources:
        p = Path(src)
        base = p.name if p.is_dir() else p.name.split(".")[0] or p.name
        base = re.sub(r"[^A-Za-z0-9_.-]", "_", base) or "session"
        name, k = base, 2
        while name in names or name == "merged":
            name, k = f"{base}_{k}", k + 1
        names.append(name)
    return names[len(taken):]


def session_map_from_result(result: SlamResult, name: str) -> SessionMap:
    """One run as a one-session map (its place descriptors computed from its submap clouds)."""
    from ..topology.descriptors import compute_descriptor

    if result.submap_descriptors is not None and len(result.submap_descriptors) == result.n_submaps:
        descriptors = result.submap_descriptors  # the loop closer's own, computed once
    else:
        desc = [compute_descriptor(p, planar=result.planar, max_range=result.config.loops.descriptor_radius)
                for p in result.submap_points]
        descriptors = np.array(desc) if desc else np.zeros((0, 0, 0))
    info = SessionInfo(name, result.source, 0, result.n_scans, 0, result.n_submaps, placed=True, links=0,
                       note="defines the map frame")
    return SessionMap(result, [info], descriptors)


def _concatenate(maps: list[SessionMap]) -> tuple[SlamResult, list[SessionInfo], np.ndarray]:
    """Every map's sessions in one result with global scan and submap numbering."""
    parts, sessions, descs = [], [], []
    scan_off = sub_off = 0
    for m in maps:
        r = m.result
        sessions += [replace(s, scan_start=s.scan_start + scan_off, scan_end=s.scan_end + scan_off,
                             submap_start=s.submap_start + sub_off, submap_end=s.submap_end + sub_off)
                     for s in m.sessions]
        parts.append((r, scan_off, sub_off))
        descs.append(m.descriptors)
        scan_off += r.n_scans
        sub_off += r.n_submaps
    first = maps[0].result
    cat = SlamResult(
        timestamps=np.concatenate([r.timestamps for r, _, _ in parts]),
        poses=np.concatenate([r.poses.reshape(-1, 4, 4) for r, _, _ in parts]),
        odometry_poses=np.concatenate([r.odometry_poses.reshape(-1, 4, 4) for r, _, _ in parts]),
        submap_poses=np.concatenate([r.submap_poses.reshape(-1, 4, 4) for r, _, _ in parts]),
        submap_covariances=np.concatenate([r.submap_covariances.reshape(-1, 6, 6) for r, _, _ in parts]),
        submap_points=[p for r, _, _ in parts for p in r.submap_points],
        submap_scan_indices=[[i + so for i in idx] for r, so, _ in parts for idx in r.submap_scan_indices],
        submap_scan_poses=[p for r, _, _ in parts for p in r.submap_scan_poses],
        submap_scan_points=[p for r, _, _ in parts for p in r.submap_scan_points],
        submap_scan_no_returns=[r.no_returns_of(k) for r, _, _ in parts for k in range(r.n_submaps)],
        edges=[(i + mo, j + mo, T, info, kind) for r, _, mo in parts for i, j, T, info, kind in r.edges],
        loops=[replace(lp, i=lp.i + mo, j=lp.j + mo) for r, _, mo in parts for lp in r.loops],
        planar=first.planar, config=first.config,
        stage_seconds={}, wall_time_s=sum(r.wall_time_s for r, _, _ in parts),
        map_voxel_size=first.map_voxel_size, path_length_m=sum(r.path_length_m for r, _, _ in parts),
        memory_mb_by_km=[], peak_memory_mb=max(r.peak_memory_mb for r, _, _ in parts),
        main_peak_memory_mb=max(r.main_peak_memory_mb for r, _, _ in parts),
        odometry_peak_memory_mb=max(r.odometry_peak_memory_mb for r, _, _ in parts),
        peak_while_odometry_mb=max(r.peak_while_odometry_mb for r, _, _ in parts),
        input_error=next((r.input_error for r, _, _ in parts if r.input_error), None),
        source=" + ".join(r.source for r, _, _ in parts if r.source),
    )
    shapes = {d.shape[1:] for d in descs if len(d)}
    descriptors = np.concatenate([d for d in descs if len(d)]) if shapes else np.zeros((0, 0, 0))
    return cat, sessions, descriptors


def _submaps(result: SlamResult, start: int = 0) -> list[Submap]:
    """The result's submaps from id ``start`` on as :class:`Submap` objects (global ids) for the
    correspondence tests."""
    out = []
    for k, (T, poses, pts, idx) in enumerate(zip(result.submap_poses[start:], result.submap_scan_poses[start:],
                                                  result.submap_points[start:], result.submap_scan_indices[start:]),
                                             start):
        steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) if len(poses) > 1 else np.zeros(0)
        out.append(Submap(id=k, scan_indices=list(idx), T_odom_anchor=T, T_anchor_scans=poses, points=pts,
                          distance=float(steps.sum()), planar=result.planar))
    return out


def _move_session(result: SlamResult, s: SessionInfo, T: np.ndarray) -> None:
    """Apply ``T`` (4, 4) to every pose of session ``s`` (scans and anchors), in place."""
    result.poses[s.scans] = T @ result.poses[s.scans]
    result.submap_poses[s.submap_start:s.submap_end] = T @ result.submap_poses[s.submap_start:s.submap_end]


def _scan_poses_after(result: SlamResult, sessions: list[SessionInfo], new_anchor_poses: np.ndarray) -> np.ndarray:
    """Scan poses ``(N, 4, 4)`` moved with their submaps' anchors.

    Each scan takes its submap's correction (new anchor @ old anchor^-1), blended towards the
    next submap's of the same session by the share of the path between the two anchors it has
    covered (as the engine spreads corrections inside a submap).
    """
    old = result.submap_poses
    corr = new_anchor_poses @ np.linalg.inv(old)
    out = result.poses.copy()
    for s in sessions:
        owner = np.full(s.scan_end - s.scan_start, -1, dtype=np.int64)
        for k in s.submaps:
            owner[np.asarray(result.submap_scan_indices[k], dtype=np.int64) - s.scan_start] = k
        poses = result.poses[s.scans]
        steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) if len(poses) > 1 else np.zeros(0)
        travelled = np.concatenate([[0.0], np.cumsum(steps)])
        for k in s.submaps:
            rows = np.flatnonzero(owner == k)
            if not len(rows):
                continue
            start_k = travelled[result.submap_scan_indices[k][0] - s.scan_start]
            if k + 1 < s.submap_end:
                span = travelled[result.submap_scan_indices[k + 1][0] - s.scan_start] - start_k
                if span > 1e-9:
                    alpha = np.clip((travelled[rows] - start_k) / span, 0.0, 1.0)
                    out[s.scan_start + rows] = blend_poses_many(corr[k], corr[k + 1], alpha) @ poses[rows]
                    continue
            out[s.scan_start + rows] = corr[k] @ poses[rows]
    return out


def _add_ground_attitudes(graph, result: SlamResult, sessions: list[SessionInfo], config: PipelineConfig,
                          ground_ups: dict[int, tuple[np.ndarray | None, np.ndarray | None]]) -> None:
    """3D: the engine's soft priors on each anchor's attitude (as the graph builder adds them):
    level, in the up direction of the map frame for placed sessions and of its own frame for an
    unplaced one (without it the merged graph may tilt where the links are few), and (unless the
    walls give the level) the ground tilted like the ground under the session's previous anchor, at the configured
    ``ground_tilt_change_sigma_deg`` (a single run measures that sigma from its own odometry,
    :class:`~submapslam.uncertainty.TiltChangeSpread`; a merge does not yet). The level priors
    come from the walls' vertical (``wall_vertical_sigma_deg``; spinning LiDARs) when any submap of
    the merge has one (a submap without walls: its ground plane), else from the ground planes; the
    up they hold the anchors to is agreed as a single run agrees it (:func:`_world_up`).
    ``ground_ups``: each submap's ``(ground normal, walls' vertical)`` in its anchor frame (either
    None), filled in here where missing and kept by the caller (a submap's points never change; the merge optimises many times)."""
    sigma = config.backend.ground_attitude_sigma_deg
    change = config.backend.ground_tilt_change_sigma_deg
    if result.planar or (sigma is None and change is None):
        return
    from ..mapping.height_band import ground_normal
    from ..mapping.vertical import submap_vertical

    # a narrow-field sensor keeps its ground planes
    walls_sigma = (config.backend.wall_vertical_sigma_deg if sigma is not None
                   and not narrow_field(result.odometry_registration) else None)
    for s in sessions:
        for k in s.submaps:
            if k not in ground_ups:  # 3D: the map voxel is the submaps' (at least 0.1 m)
                up = ground_normal(result.submap_points[k])
                vertical = (None if walls_sigma is None
                            else submap_vertical(result.submap_points[k], up, result.map_voxel_size))
                ground_ups[k] = (up, vertical)
    walls = walls_sigma is not None and any(ground_ups[k][1] is not None for s in sessions for k in s.submaps)
    map_up = _world_up(result, [k for s in sessions if s.placed for k in s.submaps], ground_ups, walls)
    for s in sessions:
        own_up = None if s.placed else _world_up(result, list(s.submaps), ground_ups, walls)
        up_before = None
        for k in s.submaps:
            up, vertical = ground_ups[k]
            if up is not None and change is not None and up_before is not None and not walls:
                T_guess = inverse(result.submap_poses[k - 1]) @ result.submap_poses[k]
                graph.add_relative_attitude(k - 1, k, up_before, up, T_guess, np.deg2rad(change))
            up_before = up
            target = map_up if s.placed else own_up
            if sigma is None or target is None:
                continue
            if walls and vertical is not None:
                graph.add_attitude(k, vertical, target, np.deg2rad(walls_sigma), kind=WALL_VERTICAL_PRIOR)
            elif up is not None:  # no walls here (or none in the merge): its ground plane, as a single run does
                graph.add_attitude(k, up, target, np.deg2rad(sigma), kind=GROUND_ATTITUDE_PRIOR)


def _world_up(result: SlamResult, ids: list[int], ground_ups: dict[int, tuple], walls: bool) -> np.ndarray | None:
    """``(3,)`` the up (map frame) that the level priors of the submaps ``ids`` (in order) hold them
    to, by a single run's rule (:class:`~submapslam.graph_builder.GraphBuilder`): the consensus of
    the first :data:`~submapslam.graph_builder.WORLD_UP_VOTES` walls' verticals (``walls``), else
    the first ground normal, each turned into the map frame by its anchor; None when there is none."""
    from ..graph_builder import WORLD_UP_VOTES, consensus_up

    which = 1 if walls else 0
    votes = [result.submap_poses[k][:3, :3] @ ground_ups[k][which] for k in ids if ground_ups[k][which] is not None]
    if not votes:
        return None
    return consensus_up(votes[:WORLD_UP_VOTES]) if walls else votes[0]


def _optimise(result: SlamResult, sessions: list[SessionInfo], config: PipelineConfig,
              ground_ups: dict[int, tuple], frozen: tuple[int, int] = (0, 0)) -> list[tuple[int, int, str]]:
    """Optimise the merged graph in place: anchors, scans, covariances, edges kept
    (``ground_ups``: see :func:`_add_ground_attitudes`). ``frozen``: (scans, submaps) at the
    start of the result that belong to a frozen base map: held, and returned exactly as they were.

    Returns ``(i, j, why)`` of loop edges the optimiser rejected.
    """
    from ..backend.pose_graph import PoseGraph, floor_information

    fixed_scans, fixed = frozen
    graph = PoseGraph(config.backend)
    start = {s.submap_start for s in sessions if s.placed}
    own_frame = {s.submap_start for s in sessions if not s.placed}  # held where they are
    # weak: a later session's start may be anywhere (placed ones are held by their links); a
    # planar session's z, roll and pitch stay pinned like the map's (not observable in 2D)
    sigma = np.array([np.pi] * 3 + [config.sessions.start_prior_sigma_m] * 3)
    if result.planar:
        sigma[[0, 1, 5]] = 1e-4
    weak = np.diag(1.0 / sigma**2)
    for k, T in enumerate(result.submap_poses):
        prior = PRIOR_INFORMATION if k < fixed or k == 0 or k in own_frame else (weak if k in start else None)
        graph.add_node(k, T, prior)
    _add_ground_attitudes(graph, result, sessions, config, ground_ups)
    floor_m, floor_rad = config.backend.loop_sigma_floor_m, float(np.deg2rad(config.backend.loop_sigma_floor_deg))
    frozen_edges = [e for e in result.edges if e[0] < fixed and e[1] < fixed]  # between held anchors: kept as they are
    for i, j, T_i_j, info, kind in result.edges:
        if not (i < fixed and j < fixed):
            graph.add_between(i, j, T_i_j, info, kind)
    for rec in result.loops:  # cross-session links not yet edges
        if rec.accepted and rec.source == "session" and not any(e[0] == rec.i and e[1] == rec.j for e in result.edges):
            graph.add_between(rec.i, rec.j, rec.T_i_j, floor_information(rec.information, floor_m, floor_rad), "loop")
    try:
        graph.update()
        weights = graph.optimize_batch() if config.backend.final_batch else {}
        dropped = graph.final_check() if config.backend.final_batch and config.backend.final_check else []
    except RuntimeError as exc:  # gtsam: an ill-conditioned system; keep the placement unoptimised
        log.warning("merged graph not optimised (%s); sessions keep their placed poses",
                    str(exc).strip().splitlines()[0])
        return []
    rejected = [(i, j, f"rejected by the optimiser (GNC weight {w:.2f})") for (i, j), w in weights.items() if w < 0.5]
    rejected += dropped
    n = result.n_submaps
    covs = graph.all_marginal_covariances(range(fixed, n))  # a frozen map keeps its own
    scale = covariance_scale(config.backend, result.planar)
    covs = {k: calibrate(c, scale) for k, c in covs.items()}  # as a single run reports them
    new_poses = np.array([graph.pose(k) for k in range(n)]).reshape(-1, 4, 4)
    new_poses[:fixed] = result.submap_poses[:fixed]  # a frozen map: exactly where it was
    scan_poses = _scan_poses_after(result, sessions, new_poses)
    scan_poses[:fixed_scans] = result.poses[:fixed_scans]
    result.poses = scan_poses
    result.submap_poses = new_poses
    result.submap_covariances = np.array([result.submap_covariances[k] if k < fixed else covs[k]
                                          for k in range(n)]).reshape(-1, 6, 6)
    result.edges = frozen_edges + [(e.i, e.j, e.T_i_j, e.information, e.kind) for e in graph.active_edges()]
    return rejected


class SessionMerger:
    """Adds sessions to a map one at a time, in the order given, then tries the unplaced ones again.

    ``add`` places each new session against the sessions already in the map frame (then
    optimises the merged graph and searches again near the optimised estimate), so a caller can
    merge each log as soon as it and the logs before it are done (``batch`` does, beside the
    logs still running); ``finish`` retries the sessions not yet placed while any placement
    succeeds, since sessions in any order may find their place through each other. The same
    sessions added in the same order give the same map.
    """

    def __init__(self, base: SessionMap, config: PipelineConfig | None = None,
                 verify_elsewhere: Callable[[dict], VerifyMany] | None = None, freeze_base: bool = False) -> None:
        """``verify_elsewhere``: given the loop closer's constructor arguments, a function that runs
        batches of independent placement tests elsewhere (``batch`` on Ray: on its workers).
        ``freeze_base``: ``base`` does not move (its poses, covariances and edges come out as they
        went in); the sessions added are placed and optimised against it."""
        from ..topology.loop_closure import LoopCloser
        from ..topology.session_placement import SessionPlacer

        self.config = config or base.result.config
        self._seconds = 0.0
        result, sessions, descriptors = _concatenate([base])  # copies: ``base`` is not changed
        result.poses, result.submap_poses = result.poses.copy(), result.submap_poses.copy()
        self.map = SessionMap(result, sessions, descriptors)
        self._n_base = base.n_sessions
        self._frozen = (result.n_scans, result.n_submaps) if freeze_base else (0, 0)  # held scans, submaps
        self._tried_at: dict[int, int] = {}  # session index -> sessions placed when it was last tried
        self._ground_ups: dict[int, tuple] = {}  # 3D: submap id -> (ground normal, walls' vertical) (global ids)
        planar = base.result.planar
        cfg = self.config
        voxel = cfg.submaps.voxel_size or _submap_voxel(base.result)
        closer_args = {"config": cfg.loops, "planar": planar, "voxel_size": voxel, "max_range": cfg.odometry.max_range,
                       "submap_length": cfg.submaps.max_distance or (5.0 if planar else 12.0)}
        self._closer = LoopCloser(**closer_args)
        self._placer = SessionPlacer(self._closer, cfg.sessions,
                                     verify_elsewhere(closer_args) if verify_elsewhere is not None else None)
        self._submaps = _submaps(result)

    def add(self, addition: SessionMap) -> None:
        """Append ``addition``'s sessions (not changed) and try to place each of them."""
        t = time.perf_counter()
        _check_kind(self.map, addition)
        first = self.map.n_sessions
        result, sessions, descriptors = _concatenate([self.map, addition])
        result.poses, result.submap_poses = result.poses.copy(), result.submap_poses.copy()
        for s in sessions[first:]:
            s.placed, s.links, s.note = False, 0, ""
        self.map = SessionMap(result, sessions, descriptors)
        self._submaps += _submaps(result, len(self._submaps))  # ids are global: the addition's are appended
        for k in range(first, len(sessions)):
            self._try(k)
        self._seconds += time.perf_counter() - t

    def finish(self) -> SessionMap:
        """Retry the unplaced sessions while any placement succeeds; return the merged map."""
        t = time.perf_counter()
        result, sessions = self.map.result, self.map.sessions
        progress = True
        while progress:
            progress = False
            for k in range(self._n_base, len(sessions)):
                placed_now = sum(s.placed for s in sessions)
                if not sessions[k].placed and self._tried_at.get(k) != placed_now:  # else: the same map again
                    progress |= self._try(k)
        if not any(s.placed for s in sessions[self._n_base:]) and len(sessions) > self._n_base:
            _mark_rejected(result, _optimise(result, sessions, self.config, self._ground_ups, self._frozen))  # covariances of the joint graph
        self._seconds += time.perf_counter() - t
        result.stage_seconds = {**result.stage_seconds, "merge": self._seconds}
        result.wall_time_s += self._seconds
        return self.map

    def _try(self, k: int) -> bool:
        """Place session ``k`` against the sessions in the map frame; True when it was placed."""
        result, sessions, descriptors = self.map.result, self.map.sessions, self.map.descriptors
        s, config, placer, submaps = sessions[k], self.config, self._placer, self._submaps
        self._tried_at[k] = sum(m.placed for m in sessions)
        map_ids = [i for m in sessions if m.placed for i in m.submaps]
        if not map_ids:
            return False
        ids = list(s.submaps)
        placement = placer.place(
            submaps, map_ids, {i: result.submap_poses[i] for i in map_ids}, {i: descriptors[i] for i in map_ids},
            ids, {i: result.submap_poses[i] for i in ids}, {i: descriptors[i] for i in ids})
        s.note = placement.reason
        tested = {(lp.i, lp.j) for lp in result.loops}
        result.loops.extend(r for r in placement.records if (r.i, r.j) not in tested)
        if placement.T_map_session is None:
            return False
        _move_session(result, s, placement.T_map_session)
        s.placed, s.links = True, len(placement.links)
        for i in s.submaps:  # the session's anchors now lie in the map frame
            submaps[i].T_odom_anchor = result.submap_poses[i]
        _mark_rejected(result, _optimise(result, sessions, config, self._ground_ups, self._frozen))
        added = 0
        for _ in range(config.sessions.densify_passes):  # more links where the optimised estimate puts it
            others = [i for m in sessions if m.placed and m is not s for i in m.submaps]
            tested = {(lp.i, lp.j) for lp in result.loops}
            dense = placer.densify(submaps, others, {i: result.submap_poses[i] for i in others}, ids,
                                   {i: result.submap_poses[i] for i in ids}, tested)
            result.loops.extend(dense)
            s.links += sum(r.accepted for r in dense)
            added += sum(r.accepted for r in dense)
            if not any(r.accepted for r in dense):
                break
            _mark_rejected(result, _optimise(result, sessions, config, self._ground_ups, self._frozen))
        if added:
            s.note += f"; {added} more link(s) near the optimised estimate"
        for i in range(result.n_submaps):
            submaps[i].T_odom_anchor = result.submap_poses[i]
        log.info("session %s: %s", s.name, s.note)
        return True


def merge_sessions(base: SessionMap, additions: list[SessionMap],
                   config: PipelineConfig | None = None, *, freeze_base: bool = False) -> SessionMap:
    """Add the sessions of ``additions`` to the map ``base`` (:class:`SessionMerger`): each is
    placed against the sessions already in the map frame as it is added, the unplaced ones are
    tried again after every later success, and the merged graph is optimised (with
    ``freeze_base``, around ``base`` held as it is: its poses come out unchanged).

    Returns the merged map (``base`` and ``additions`` are not changed); a session that found no
    consistent overlap is kept with ``placed`` False, in its own frame, with the reason in ``note``.
    """
    for addition in additions:  # before any work
        _check_kind(base, addition)
    merger = SessionMerger(base, config, freeze_base=freeze_base)
    for addition in additions:
        merger.add(addition)
    return merger.finish()


def _check_kind(base: SessionMap, addition: SessionMap) -> None:
    """A 2D laser session and a 3D LiDAR map (or the reverse) do not merge: one clear line."""
    if addition.result.planar != base.result.planar:
        from ..errors import InputError

        raise InputError(addition.result.source or addition.sessions[0].name,
                         "a 2D laser session cannot join a 3D LiDAR map (or the reverse)")


def _mark_rejected(result: SlamResult, rejected: list[tuple[int, int, str]]) -> None:
    why = {(i, j): w for i, j, w in rejected}
    for rec in result.loops:
        if rec.accepted and (rec.i, rec.j) in why:
            rec.accepted, rec.reason = False, why[(rec.i, rec.j)]


def _submap_voxel(result: SlamResult) -> float:
    """The submap voxel the run used (the odometry's default resolution: half its voxel)."""
    from ..odometry import Odometry

    return Odometry(result.config.odometry, result.planar).voxel_size / 2.0
