"""Watching a run as it happens: the engine's optional observer hook.

:class:`~submapslam.pipeline.SubmapSLAM` calls an observer, if it has one, after each scan is
registered, after each closed submap's graph work, and for every tested loop hypothesis. A
viewer (``submapslam.viz.rerun_view``) or a logger implements the methods it needs by
subclassing :class:`RunObserver`; the engine never waits for anything an observer does and
never reads back from it. Calls come from the engine's threads: ``on_scan`` from the thread that
feeds scans, ``on_submap`` and ``on_loop`` from the graph worker.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .geometry import inverse
from .result import LoopRecord


class RunObserver:
    """No-op base: override what you need. Poses are ``(4, 4)`` float64, metres."""

    def on_scan(self, index: int, timestamp: float, T_odom_base: np.ndarray, points: np.ndarray) -> None:
        """Scan ``index`` registered: its odometry pose and its ``(n, 3)`` points in the sensor frame."""

    def on_submap(self, submap_id: int, T_world_submaps: np.ndarray, points: np.ndarray,
                  T_world_odom: np.ndarray) -> None:
        """Submap ``submap_id`` closed and added to the graph (its loop tests done).

        ``T_world_submaps``: ``(S, 4, 4)`` current estimate of every closed anchor (S = id + 1);
        ``points``: ``(M, 3)`` the submap's cloud in its anchor frame; ``T_world_odom``: the
        correction that takes the newest odometry poses to the world frame.
        """

    def on_loop(self, record: LoopRecord, T_world_i: np.ndarray, T_world_j: np.ndarray) -> None:
        """A loop hypothesis between submaps ``record.i`` and ``record.j`` was tested (accepted or
        not: ``record.accepted``, ``record.reason``), with both anchors' current estimates."""


def notify_closed_submap(observer: RunObserver, submap_id: int, T_odom_anchor: np.ndarray, points: np.ndarray,
                         records: list[LoopRecord], pose_of: Callable[[int], np.ndarray]) -> None:
    """Tell ``observer`` about a closed submap and its loop hypotheses; ``pose_of(k)`` is the
    graph's current ``T_world_submap`` of submap ``k``."""
    anchors = np.array([pose_of(k) for k in range(submap_id + 1)]).reshape(-1, 4, 4)
    observer.on_submap(submap_id, anchors, np.asarray(points), anchors[-1] @ inverse(T_odom_anchor))
    for rec in records:
        observer.on_loop(rec, anchors[rec.i], anchors[rec.j])
