"""Relations (Kümmerle et al. 2009) derived from a reference trajectory, e.g. a corrected log.

The benchmark's own relation files were made by hand-checked scan matching; where a log has
only a corrected trajectory, its relative poses give two kinds of relations:

* **local**: each reference pose with the next one at least ``local_min_dt`` later (pairs close
  in time: the map's local accuracy, where rotation errors show first);
* **across loops**: a pose with a later pose near the same place (``loop_radius_m``, headings
  within ``loop_max_yaw_deg``) after at least ``loop_min_dt`` seconds and ``loop_min_path_m``
  of driving (the accuracy of the closed cycles).

They inherit the reference's own errors (a few centimetres for the corrected Freiburg logs), so
they are *derived* relations, not the benchmark's files; the figures they give are comparable
between runs, and only roughly with published ones.
"""

from __future__ import annotations

import numpy as np

from ..errors import SubmapSlamError
from ..geometry import inverse
from ..trajectory import Relations, Trajectory


def derive_relations(ref: Trajectory, *, local_min_dt: float = 0.0, loop_radius_m: float = 1.0,
                     loop_max_yaw_deg: float = 45.0, loop_min_dt: float = 30.0, loop_min_path_m: float = 10.0,
                     loop_stride: int = 1) -> Relations:
    """Local and across-loop relations from ``ref`` (``timestamps (N,)`` [s], ``poses (N, 4, 4)``).

    Local: pose ``k`` with the first later pose at least ``local_min_dt`` [s] after it. Across
    loops: every ``loop_stride``-th pose ``a`` with the nearest (in position) pose ``b`` that is
    at least ``loop_min_dt`` [s] and ``loop_min_path_m`` [m] of reference path later, within
    ``loop_radius_m`` [m] and ``loop_max_yaw_deg`` [deg] of heading. Returns
    :class:`~submapslam.trajectory.Relations` with ``T_a_b = T_w_a^-1 T_w_b`` (local first),
    sorted by time within each kind. Raises :class:`SubmapSlamError` for fewer than two poses.
    """
    if len(ref) < 2:
        raise SubmapSlamError(f"a reference of {len(ref)} pose(s) gives no relations: need at least two")
    order = np.argsort(ref.timestamps, kind="stable")
    t, P = ref.timestamps[order], ref.poses[order]
    xy = P[:, :3, 3]
    yaw = np.arctan2(P[:, 1, 0], P[:, 0, 0])
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    pairs: list[tuple[int, int]] = []
    nxt = np.searchsorted(t, t + local_min_dt, side="left")
    for a in range(len(t)):
        b = max(int(nxt[a]), a + 1)
        if b < len(t):
            pairs.append((a, b))
    for a in range(0, len(t), max(1, int(loop_stride))):
        later = (t - t[a] >= loop_min_dt) & (path - path[a] >= loop_min_path_m)
        if not later.any():
            continue
        d = np.linalg.norm(xy - xy[a], axis=1)
        dyaw = np.abs((yaw - yaw[a] + np.pi) % (2 * np.pi) - np.pi)
        ok = later & (d <= loop_radius_m) & (np.rad2deg(dyaw) <= loop_max_yaw_deg)
        if ok.any():
            cand = np.flatnonzero(ok)
            pairs.append((a, int(cand[np.argmin(d[cand])])))
    ia = np.array([p[0] for p in pairs], dtype=int)
    ib = np.array([p[1] for p in pairs], dtype=int)
    return Relations(t[ia], t[ib], inverse(P[ia]) @ P[ib])


def count_loop_relations(relations: Relations, loop_min_dt: float = 30.0) -> int:
    """How many of ``relations`` span at least ``loop_min_dt`` [s] (the across-loop ones)."""
    return int(np.count_nonzero(np.abs(relations.t_b - relations.t_a) >= loop_min_dt))
