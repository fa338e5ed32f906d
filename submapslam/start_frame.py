"""The run's frame of a planar run, settled once the first scan has been registered again.

Registered against a map of one scan, the first scans of a run carry a shared heading error
(0.05-0.08 deg on the rooms world) that every later pose inherits. :class:`StartFrame` holds the
first ``1 + scans`` registered scans, registers the first again (point-to-line) against all the
others (:func:`~submapslam.registration.point_to_line.refit_first_scan`) and re-bases the run on
it: every pose after the first is left-multiplied by one rigid correction ``T_run_odom``, so the
first scan keeps its pose and the others their odometry relative to each other. A correction
larger than :data:`MAX_SHIFT_M` / :data:`MAX_TURN_RAD` is not believed (the run keeps the
odometry's frame).
"""

from __future__ import annotations

import logging

import numpy as np

from .geometry import inverse, matrix_to_se2, se2_to_matrix
from .odometry_stage import Registered
from .registration.point_to_line import refit_first_scan
from .scan import Scan

log = logging.getLogger(__name__)

#: the re-base moves the run's frame by at most this much [m, rad]; a larger refit is not believed
MAX_SHIFT_M = 0.1
MAX_TURN_RAD = float(np.deg2rad(1.0))

Held = tuple[Scan, Registered]


class StartFrame:
    """Holds a planar run's first scans until the first is registered again; then passes every
    scan on with its pose in the run's frame.

    ``scans``: how many scans after the first the refit waits for (0: no refit, every scan passes
    straight through, as for 3D runs). A resumed run takes the frame its first run settled:
    :meth:`settled`."""

    def __init__(self, scans: int) -> None:
        self._scans = scans
        self._held: list[Held] | None = [] if scans > 0 else None
        self._released = 0  # scans passed on so far
        self.correction: np.ndarray | None = None  # (4, 4) T_run_odom; None: the identity

    @classmethod
    def settled(cls, correction: np.ndarray | None) -> StartFrame:
        """A resumed run's: the frame its first run settled (``correction`` ``(4, 4)``, None:
        the odometry's own), applied to the scans the odometry registers again from the start."""
        frame = cls(0)
        frame.correction = None if correction is None else np.asarray(correction, dtype=np.float64)
        return frame

    def add(self, scan: Scan, registered: Registered) -> list[Held]:
        """The scans ready to be taken, in order, their poses in the run's frame: none while the
        start is held, all held ones when the refit is made, else this one."""
        if self._held is None:
            return [self._release(scan, registered)]
        self._held.append((scan, registered))
        return self.settle(refit=True) if len(self._held) > self._scans else []

    def settle(self, refit: bool) -> list[Held]:
        """Release the held scans (all of them; none once settled), with ``refit`` after the
        re-base. A log shorter than the refit's window ends with ``refit=False``: its scans as
        registered."""
        held, self._held = self._held or [], None
        if refit and len(held) > 1:
            self.correction = _start_correction([registered for _, registered in held])
        return [self._release(scan, registered) for scan, registered in held]

    def _release(self, scan: Scan, registered: Registered) -> Held:
        """A scan passed on: the first as registered, the others in the run's frame."""
        self._released += 1
        return scan, registered if self._released == 1 else self.in_run_frame(registered)

    def in_run_frame(self, registered: Registered) -> Registered:
        """``registered`` (a pose in the odometry's frame) with its pose (and planar ``xyt``) in the
        run's frame."""
        if self.correction is None:
            return registered
        pose = self.correction @ registered.pose
        xyt = matrix_to_se2(pose) if registered.xyt is not None else None
        return Registered(pose, registered.frame, registered.frame_down, xyt)


def _start_correction(held: list[Registered]) -> np.ndarray | None:
    """``(4, 4)`` T_run_odom: the first scan's odometry pose over its pose registered again against
    the scans after it; None when the refit failed or moved it too far to be believed."""
    refit_xyt = refit_first_scan([r.frame_down[:, :2] for r in held], np.array([r.xyt for r in held]))
    if refit_xyt is None:
        return None
    correction = held[0].pose @ inverse(se2_to_matrix(*refit_xyt))
    moved = matrix_to_se2(correction)
    if np.hypot(moved[0], moved[1]) > MAX_SHIFT_M or abs(moved[2]) > MAX_TURN_RAD:
        log.debug("first scan registered again %s away: not believed, the run keeps the odometry's frame", moved)
        return None
    log.debug("first scan registered again: the run's frame moves by %s", moved)
    return correction
