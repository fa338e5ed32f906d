"""The run's frame, settled once the first scan has been registered again.

Registered against a map of one scan, the first scans of a run carry a shared error that every
later pose inherits: a heading error of 0.05-0.08 deg on the rooms world (2D); on a 16-ring
LiDAR, whose ground rings pull each young registration towards the first scan's rings, tilts of
up to 1.4 deg a scan at the steep start of a terrain drive along KITTI 08, where the scans after
them agree to 0.1 deg. :class:`StartFrame` holds the first ``1 + scans`` registered scans,
registers the first again against the later ones and re-bases the run on it: every pose after
the first is left-multiplied by one rigid correction ``T_run_odom``, so the first scan keeps its
pose and the others their odometry relative to each other. Planar runs register the first scan
point-to-line against all the others (:func:`planar_start_correction`); 3D runs by GICP against
the scans registered once the local map held a few scans (:func:`spatial_start_correction`). A
correction larger than the limits is not believed (the run keeps the odometry's frame).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable

import numpy as np

from .geometry import inverse, matrix_to_se2, rotation_angle, se2_to_matrix, transform_points
from .odometry_stage import Registered
from .registration.point_to_line import refit_first_scan
from .scan import Scan

log = logging.getLogger(__name__)

#: the re-base moves a planar run's frame by at most this much [m, rad]; a larger refit is not believed
MAX_SHIFT_M = 0.1
MAX_TURN_RAD = float(np.deg2rad(1.0))
#: the same for a 3D run, whose refit must also fit the later scans better than the odometry's pose
#: (the young map's errors reach 1.4 deg a scan in tilt; one 16-ring start registered its second
#: scan 3 m and 3.5 deg off, which the refit put right)
MAX_SHIFT_3D_M = 5.0
MAX_TURN_3D_RAD = float(np.deg2rad(10.0))

Held = tuple[Scan, Registered]
#: ``(the first registered scan, the scans it registers against) -> (4, 4) T_run_odom`` or None
Refit = Callable[[Registered, list[Registered]], "np.ndarray | None"]


class StartFrame:
    """Holds a run's first scans until the first is registered again; then passes every scan on
    with its pose in the run's frame.

    ``scans``: how many scans after the first the refit waits for (0: no refit, every scan passes
    straight through); ``refit``: how the first is registered again (default
    :func:`planar_start_correction`), against the held scans after the first ``skip``. A resumed
    run takes the frame its first run settled: :meth:`settled`."""

    def __init__(self, scans: int, refit: Refit | None = None, skip: int = 0) -> None:
        self._scans = scans
        self._refit = refit or planar_start_correction
        self._skip = skip
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
        if refit and len(held) > 1 + self._skip:
            self.correction = self._refit(held[0][1], [registered for _, registered in held[1 + self._skip:]])
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
        return dataclasses.replace(registered, pose=pose, xyt=xyt)


def planar_start_correction(first: Registered, later: list[Registered]) -> np.ndarray | None:
    """``(4, 4)`` T_run_odom: the ``first`` scan's odometry pose over its pose registered again
    (point-to-line) against the ``later`` ones; None when the refit failed or moved it too far to
    be believed."""
    held = [first, *later]
    refit_xyt = refit_first_scan([r.frame_down[:, :2] for r in held], np.array([r.xyt for r in held]))
    if refit_xyt is None:
        return None
    return _believed(first.pose @ inverse(se2_to_matrix(*refit_xyt)), MAX_SHIFT_M, MAX_TURN_RAD)


def spatial_start_correction(first: Registered, later: list[Registered], voxel: float) -> np.ndarray | None:
    """3D: ``(4, 4)`` T_run_odom from the ``first`` scan registered again (GICP at ``voxel`` [m],
    matches within 4 voxels) against the ``later`` ones together; None when the refit fits them
    no better than the odometry's pose (the share of points within a voxel), or moved the scan too
    far to be believed."""
    from .registration.spatial import SpatialCloud, gicp, registration_fit

    if len(first.frame_down) < 50:
        return None
    world = np.vstack([transform_points(r.pose, r.frame_down) for r in later])
    scan, target = SpatialCloud(first.frame_down, voxel), SpatialCloud(world, voxel)
    refit = gicp(scan, target, first.pose, max_distance=4.0 * voxel)
    if registration_fit(scan, target, refit, voxel)[0] < registration_fit(scan, target, first.pose, voxel)[0]:
        log.debug("first scan registered again fits the later scans worse: the run keeps the odometry's frame")
        return None
    return _believed(first.pose @ inverse(refit), MAX_SHIFT_3D_M, MAX_TURN_3D_RAD)


def _believed(correction: np.ndarray, max_shift: float, max_turn: float) -> np.ndarray | None:
    """``correction`` ``(4, 4)``, or None when it moves the frame more than ``max_shift`` [m] or
    turns it more than ``max_turn`` [rad]."""
    shift = float(np.linalg.norm(correction[:3, 3]))
    turn = rotation_angle(correction[:3, :3])
    if shift > max_shift or turn > max_turn:
        log.debug("first scan registered again %.3f m, %.3f deg away: not believed, the run keeps the "
                  "odometry's frame", shift, np.degrees(turn))
        return None
    log.debug("first scan registered again: the run's frame moves by %.3f m, %.3f deg", shift, np.degrees(turn))
    return correction
