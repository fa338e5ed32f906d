"""A map built from one or more sessions (logs), kept on disk and extended by later sessions.

A :class:`SessionMap` is a :class:`~submapslam.result.SlamResult` whose scans, submaps and graph
cover every session, in session order (session 0's scans first), plus which session each belongs
to. Submap ids and scan indices are global (over all sessions); each session keeps its own
timestamps. Sessions placed in the map share one frame, that of session 0; a session that was
never placed (no verified overlap) stays in its own frame (``placed`` False).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .result import SlamResult


@dataclass
class SessionInfo:
    """One session of a map.

    ``name``: label (the log's file name without its extensions, made unique); ``source``: the
    log's path as given; scans ``[scan_start, scan_end)`` and submaps ``[submap_start,
    submap_end)`` of the map's global numbering; ``placed``: in the map frame (session 0 always
    is); ``links``: verified correspondences that placed it (0 for session 0); ``note``: why it
    was or was not placed.
    """

    name: str
    source: str
    scan_start: int
    scan_end: int
    submap_start: int
    submap_end: int
    placed: bool = True
    links: int = 0
    note: str = ""

    @property
    def scans(self) -> slice:
        return slice(self.scan_start, self.scan_end)

    @property
    def submaps(self) -> range:
        return range(self.submap_start, self.submap_end)

    def to_dict(self) -> dict:
        return {"name": self.name, "source": self.source, "scan_start": self.scan_start, "scan_end": self.scan_end,
                "submap_start": self.submap_start, "submap_end": self.submap_end, "placed": self.placed,
                "links": self.links, "note": self.note}


@dataclass
class SessionMap:
    """Sessions merged into one map.

    ``result``: every session's scans and submaps in one :class:`SlamResult` (global ids; the
    poses of placed sessions in the map frame = session 0's first scan); ``sessions``: one
    :class:`SessionInfo` each, in order; ``descriptors``: ``(S, rings, sectors)`` place
    descriptor per submap (anchor frame).
    """

    result: SlamResult
    sessions: list[SessionInfo]
    descriptors: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 0)))

    @property
    def n_sessions(self) -> int:
        return len(self.sessions)

    def submap_session(self) -> np.ndarray:
        """``(S,)`` session index of every submap."""
        out = np.zeros(self.result.n_submaps, dtype=np.int64)
        for k, s in enumerate(self.sessions):
            out[s.submap_start:s.submap_end] = k
        return out

    def scan_session(self) -> np.ndarray:
        """``(N,)`` session index of every scan."""
        out = np.zeros(self.result.n_scans, dtype=np.int64)
        for k, s in enumerate(self.sessions):
            out[s.scan_start:s.scan_end] = k
        return out

    def session_result(self, k: int) -> SlamResult:
        """Session ``k`` alone as a :class:`SlamResult` (its own scan and submap numbering, poses
        as in the map, edges and loops inside it only)."""
        return restrict(self.result, [self.sessions[k]])

    def placed_result(self) -> SlamResult:
        """The sessions in the map frame (placed), as one :class:`SlamResult` with their global
        order kept (what the fused map and grid are built from)."""
        return restrict(self.result, [s for s in self.sessions if s.placed])


def restrict(result: SlamResult, sessions: list[SessionInfo]) -> SlamResult:
    """The part of ``result`` that belongs to ``sessions`` (in the given order), renumbered:
    scans, submaps, edges and loops whose both ends are inside."""
    scan_idx = np.concatenate([np.arange(s.scan_start, s.scan_end) for s in sessions]) if sessions \
        else np.zeros(0, dtype=np.int64)
    sub_idx = np.concatenate([np.arange(s.submap_start, s.submap_end) for s in sessions]) if sessions \
        else np.zeros(0, dtype=np.int64)
    scan_new = {int(g): n for n, g in enumerate(scan_idx)}
    sub_new = {int(g): n for n, g in enumerate(sub_idx)}
    from dataclasses import replace

    edges = [(sub_new[i], sub_new[j], T, info, kind) for i, j, T, info, kind in result.edges
             if i in sub_new and j in sub_new]
    loops = [replace(lp, i=sub_new[lp.i], j=sub_new[lp.j]) for lp in result.loops
             if lp.i in sub_new and lp.j in sub_new]
    return replace(
        result,
        timestamps=result.timestamps[scan_idx],
        poses=result.poses[scan_idx],
        odometry_poses=result.odometry_poses[scan_idx],
        submap_poses=result.submap_poses[sub_idx],
        submap_covariances=result.submap_covariances[sub_idx],
        submap_points=[result.submap_points[k] for k in sub_idx],
        submap_scan_indices=[[scan_new[i] for i in result.submap_scan_indices[k]] for k in sub_idx],
        submap_scan_poses=[result.submap_scan_poses[k] for k in sub_idx],
        submap_scan_points=[result.submap_scan_points[k] for k in sub_idx],
        submap_scan_no_returns=[result.no_returns_of(k) for k in sub_idx],
        edges=edges,
        loops=loops,
        memory_mb_by_km=[],
    )
