"""A run's progress, kept so that an interrupted run can be resumed to the same result.

A :class:`Checkpoint` holds what the expensive steps decided: every scan's odometry pose, each
submap's odometry-edge information (from a registration) and each submap's tested loop
hypotheses with their constraints. Resuming re-reads the log and replays those scans through
the same steps with the decisions taken from the checkpoint (no ICP, no correspondence test),
which rebuilds the odometry's local map, the submaps, the descriptor index and the GTSAM graph
in the same order with the same numbers; after the checkpoint's last scan the run continues
live. Because every step is deterministic, the resumed run ends with the trajectory an
uninterrupted run gives.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from .result import LoopRecord


class KnownScan(NamedTuple):
    """A resumed run's record of one scan's registration, which the odometry replays without ICP."""

    pose: np.ndarray  # (4, 4) T_odom_base as registered
    xyt: np.ndarray | None = None  # planar: (3,) x, y, yaw as refined
    map_refreshed: bool = False  # the scans waiting for the local map entered it early for this one
    guess: np.ndarray | None = None  # (4, 4) the guess the kept registration started from; None: the prediction


@dataclass
class Checkpoint:
    """The decisions of the first :attr:`n_scans` scans of a run.

    Attributes:
        timestamps: ``(K,)`` the scans' timestamps (a resumed log must give the same).
        odometry_poses: ``(K, 4, 4)`` ``T_odom_base`` of scans ``0..K-1`` as registered, in the
            odometry's own frame (before the start's re-base, :attr:`run_frame`).
        planar_poses: ``(K, 3)`` the same as ``x, y, yaw`` for planar logs (the refinement's own
            numbers, which a matrix round trip would change in the last bit), else None.
        run_frame: ``(4, 4)`` ``T_run_odom``, the re-base of a planar run's frame on its first scan
            registered again (:class:`~submapslam.start_frame.StartFrame`; every pose after the
            first is in the run's frame by it), None: none.
        odometry_information: per submap id >= 1, the ``(6, 6)`` information of its odometry
            edge from the previous submap (GTSAM order).
        odometry_tilt: per submap id (3D, where measured), the ``(2,)`` roll and pitch [rad] by
            which the registration between the two submaps corrected that edge (the run's
            estimate of its own tilt drift is made of these).
        odometry_correction: per submap id (where measured), the whole ``(6,)`` correction
            (GTSAM order, [rad, m]; the run's measured odometry noise is made of these).
        loop_records: per submap id, the hypotheses tested when it closed, in test order.
        source: the log the scans came from.
        map_refreshed: ``(K,)`` bool, the scans for which the odometry put the scans waiting for
            its local map into it early (:meth:`~submapslam.odometry.Odometry._fresh_map_if_off`);
            None: none.
        guesses: scan index -> ``(4, 4)`` the guess its kept registration started from, where not
            the prediction (a guess over a gap, the constant-velocity guess against the wheels'):
            the adaptive threshold learns from how far the registration moved from it.
    """

    timestamps: np.ndarray
    odometry_poses: np.ndarray
    planar_poses: np.ndarray | None
    odometry_information: dict[int, np.ndarray] = field(default_factory=dict)
    odometry_tilt: dict[int, np.ndarray] = field(default_factory=dict)
    odometry_correction: dict[int, np.ndarray] = field(default_factory=dict)
    loop_records: dict[int, list[LoopRecord]] = field(default_factory=dict)
    source: str = ""
    run_frame: np.ndarray | None = None
    map_refreshed: np.ndarray | None = None
    guesses: dict[int, np.ndarray] = field(default_factory=dict)

    @property
    def n_scans(self) -> int:
        return len(self.odometry_poses)

    @property
    def n_submaps(self) -> int:
        """Submaps whose graph work (odometry edge, loop tests) the checkpoint holds."""
        return len(self.loop_records)

    def known_pose(self, scan_index: int) -> KnownScan | None:
        """The registration of a scan the checkpoint covers, else None."""
        if scan_index >= self.n_scans:
            return None
        xyt = self.planar_poses[scan_index] if self.planar_poses is not None else None
        refreshed = self.map_refreshed is not None and bool(self.map_refreshed[scan_index])
        return KnownScan(self.odometry_poses[scan_index], xyt, refreshed, self.guesses.get(scan_index))
