"""Edit a map of several sessions: drop sessions from it (Cartographer's delete trajectory).

A dropped session takes its scans, its submaps, its place descriptors and every edge and loop
test that touches one of its submaps with it; nothing else moves: the sessions kept keep their
poses in the map frame, their covariances and their own and shared edges, so whatever was drawn
in the map's frame stays valid. The map's fused grid and cloud are rebuilt from the sessions
kept (:func:`~submapslam.fleet_api.write_session_map`): a box only a dropped session saw leaves
the map, and one that only a dropped session saw leave comes back.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..errors import SubmapSlamError
from ..session_map import SessionInfo, SessionMap, restrict


def drop_sessions(session_map: SessionMap, names: list[str]) -> SessionMap:
    """``session_map`` without the sessions called ``names`` (``session_map`` is not changed).

    The sessions kept keep their order; the first of them must be placed (it holds the map
    frame from then on). Raises :class:`~submapslam.errors.SubmapSlamError` (one line) for a
    name the map does not hold, when nothing would be left, or when the first session kept is
    not in the map frame.
    """
    known = [s.name for s in session_map.sessions]
    unknown = [n for n in names if n not in known]
    if unknown:
        raise SubmapSlamError(f"no session {', '.join(unknown)} in the map (its sessions: {', '.join(known)})")
    kept = [s for s in session_map.sessions if s.name not in set(names)]
    if not kept:
        raise SubmapSlamError("dropping every session would leave no map: keep at least one")
    if not kept[0].placed:
        raise SubmapSlamError(f"session {kept[0].name} would come first but is not in the map frame (never placed): "
                              "drop it too, or keep a placed session before it")
    result = restrict(session_map.result, kept)
    sessions: list[SessionInfo] = []
    scan_at = submap_at = 0
    for s in kept:
        n_scans, n_submaps = s.scan_end - s.scan_start, s.submap_end - s.submap_start
        sessions.append(replace(s, scan_start=scan_at, scan_end=scan_at + n_scans,
                                submap_start=submap_at, submap_end=submap_at + n_submaps))
        scan_at, submap_at = scan_at + n_scans, submap_at + n_submaps
    ids = np.concatenate([np.arange(s.submap_start, s.submap_end) for s in kept]).astype(np.int64)
    dynamic = session_map.result.submap_dynamic_points
    result = replace(
        result,
        path_length_m=sum(_travelled(result.odometry_poses[s.scans]) for s in sessions),
        source=" + ".join(s.source for s in sessions if s.source),
        submap_descriptors=None,  # the map's own descriptors below
        submap_dynamic_points=None if dynamic is None else [dynamic[k] for k in ids],
    )
    descriptors = session_map.descriptors[ids] if len(session_map.descriptors) else session_map.descriptors
    return SessionMap(result, sessions, descriptors)


def _travelled(poses: np.ndarray) -> float:
    """Path length [m] along ``(N, 4, 4)`` poses."""
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum()) if len(poses) > 1 else 0.0
