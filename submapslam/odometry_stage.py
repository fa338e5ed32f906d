"""Where scans are registered: in this process, or in a child process a few scans ahead.

KISS-ICP's registration holds Python's GIL for its whole call (about 20 ms for a 16-ring
scan), so in one process it cannot overlap with the submap-graph work (loop tests, iSAM2) that
runs in a thread beside it: each waits for the other. :class:`OdometryProcess` runs the same
:class:`~submapslam.odometry.Odometry` in a child process with a core of its own; the scans go
in, ``(pose, frame)`` come back in order, the same numbers the in-process
:class:`InlineOdometry` gives (the computation is the same, float64 end to end).

Both stages have one interface: :meth:`submit` a scan, :meth:`result` the oldest scan not yet
returned, :meth:`close` at the end.
"""

from __future__ import annotations

import logging
import subprocess
from collections import deque
from dataclasses import dataclass

import numpy as np

from .checkpoint import KnownScan
from .child_process import ChildProcess, child_streams, usable_cores
from .child_process import own_peak_kib as _own_peak_kib
from .child_process import receive as _receive
from .child_process import send as _send
from .config import OdometryConfig
from .errors import SubmapSlamError
from .odometry import Odometry, odometry_voxels
from .process_stats import single_threaded_blas
from .scan import Scan

log = logging.getLogger(__name__)
Known = KnownScan | None  # a resumed run's record of the scan's registration


#: [s] how long a child whose answers stopped coming may take to end before it is stopped
_END_WAIT_S = 10.0


@dataclass
class Registered:
    """One registered scan.

    pose: ``(4, 4)`` ``T_odom_base``. frame: ``(N, 3)`` the scan's points in its base frame after
    range filtering and motion compensation. frame_down: the same thinned to the odometry's
    ``frame_voxel`` (what registration used). xyt: planar logs: ``(3,)`` x, y, yaw as refined.
    map_refreshed: the scans waiting for the local map entered it early for this one
    (:attr:`~submapslam.odometry.Odometry.last_map_refreshed`). guess: ``(4, 4)`` the guess the
    kept registration started from where not the prediction (:attr:`~submapslam.odometry.Odometry.last_guess`).
    A checkpoint keeps both.
    """

    pose: np.ndarray
    frame: np.ndarray
    frame_down: np.ndarray
    xyt: np.ndarray | None
    map_refreshed: bool = False
    guess: np.ndarray | None = None


class InlineOdometry:
    """Registration in this process, when :meth:`result` is called."""

    def __init__(self, config: OdometryConfig, planar: bool) -> None:
        self._odometry = Odometry(config, planar)
        self.voxel_size, self.frame_voxel = self._odometry.voxel_size, self._odometry.frame_voxel
        self._pending: deque[tuple[Scan, Known]] = deque()
        self.peak_memory_mb = 0.0  # no child process

    def submit(self, scan: Scan, known: Known = None) -> None:
        self._pending.append((scan, known))

    def result(self) -> Registered:
        scan, known = self._pending.popleft()
        pose, frame = self._odometry.register(scan, known)
        return Registered(pose, frame, self._odometry.last_frame_down, self._odometry.last_xyt,
                          self._odometry.last_map_refreshed, self._odometry.last_guess)

    def checks(self) -> dict:
        """:meth:`Odometry.checks` of the registration so far."""
        return self._odometry.checks()

    def close(self) -> None:
        self._pending.clear()


def _exact_float32(values: np.ndarray | None) -> np.ndarray | None:
    """``values`` as float32 when that loses nothing (scans read from float32 files: half the
    bytes to send), else as they are."""
    if values is not None and values.dtype == np.float64:
        single = values.astype(np.float32)
        if np.array_equal(single, values):
            return single
    return values


def _kept_points(points: np.ndarray, frame: np.ndarray, config: OdometryConfig) -> np.ndarray | None:
    """A boolean mask with ``points[mask] == frame`` exactly (the frame is the scan range-filtered,
    not deskewed: 30x fewer bytes to send than the frame), or None when it is not that."""
    if config.deskew:
        return None
    distance = np.linalg.norm(points, axis=1)
    mask = (distance < config.max_range) & (distance > config.min_range)
    return mask if int(mask.sum()) == len(frame) and np.array_equal(points[mask], frame) else None


def _serve() -> None:
    """The child process (``python -m submapslam.odometry_stage``): the config first, then
    scans from stdin until None, each answered on stdout; last, its peak resident set [KiB] and
    :meth:`Odometry.checks`.
    Anything a library prints goes to stderr: stdout carries only the messages."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it finishes the scans in flight
    single_threaded_blas(load_scipy=False)
    inbox, outbox = child_streams()
    try:
        config, planar = _receive(inbox)
        odometry = Odometry(OdometryConfig(**config), planar)
        while (item := _receive(inbox)) is not None:
            points, point_times, wheel, known, stamp, timed = item
            points = points.astype(np.float64)
            point_times = None if point_times is None else point_times.astype(np.float64)
            try:
                pose, frame = odometry.register(Scan(0, stamp, points, point_times, wheel, planar, timed=timed),
                                                known)
                kept = _kept_points(points, frame, odometry.config)
                _send(outbox, ("ok", (pose, frame if kept is None else kept, odometry.last_frame_down,
                                      odometry.last_xyt, odometry.last_map_refreshed, odometry.last_guess)))
            except Exception as exc:  # noqa: BLE001 - handed to the parent, raised there
                _send(outbox, ("error", f"{exc.__class__.__name__}: {exc}"))
        _send(outbox, ("end", (_own_peak_kib(), odometry.checks())))
    except (EOFError, BrokenPipeError):  # the parent is gone
        pass


class OdometryProcess:
    """Registration in a child process (``python -m submapslam.odometry_stage``, a fresh
    interpreter: nothing of this process is copied or re-run, not even a caller's script).

    Scans are queued without waiting (a writer thread feeds the child) and the child's answers
    are read as they come (a reader thread: the child never waits for this process to take
    them, however many scans ahead it is); :meth:`result` waits for the oldest. The child
    ignores SIGINT (the parent decides what an interrupt means) and ends when its input closes.
    """

    def __init__(self, config: OdometryConfig, planar: bool) -> None:
        self.voxel_size, self.frame_voxel = odometry_voxels(config, planar)
        self._child = ChildProcess("submapslam.odometry_stage", "odometry")
        self._process = self._child.process
        self._child.put((config.model_dump(), planar))
        self._in_flight = 0
        self._submitted: deque[np.ndarray] = deque()  # the points of the scans in flight
        self.peak_memory_mb = 0.0  # the child's peak resident set [MiB], known after close()
        self._checks: dict = {}  # the child's Odometry.checks(), known after close()

    def submit(self, scan: Scan, known: Known = None) -> None:
        self._child.put((_exact_float32(scan.points), _exact_float32(scan.point_times), scan.odometry, known,
                          float(scan.timestamp), scan.timed))
        self._submitted.append(scan.points)
        self._in_flight += 1

    @property
    def ready(self) -> int:
        """Scans the child has answered that :meth:`result` has not yet taken."""
        return self._child.waiting

    def _answer(self) -> tuple[str, object]:
        answer = self._child.get()  # None once the child has ended, for every later call too
        if answer is None:
            try:
                code = self._process.wait(timeout=_END_WAIT_S)
            except subprocess.TimeoutExpired:  # its output broke while it runs: it is stopped
                self._process.kill()
                code = self._process.wait()
            raise SubmapSlamError(f"the odometry process ended unexpectedly (exit code {code})")
        return answer

    def result(self) -> Registered:
        if not self._in_flight:
            raise SubmapSlamError("no scan was submitted to the odometry process")
        kind, value = self._answer()
        self._in_flight -= 1
        points = self._submitted.popleft()
        if kind == "error":
            raise SubmapSlamError(f"odometry: {value}")
        pose, frame, frame_down, xyt, map_refreshed, guess = value
        return Registered(pose, points[frame] if frame.dtype == bool else frame, frame_down, xyt, map_refreshed, guess)

    def checks(self) -> dict:
        """:meth:`Odometry.checks` of the child's registration, known once :meth:`close` has
        ended it (empty before, and after a child that died)."""
        return dict(self._checks)

    def close(self) -> None:
        """Stop the child (scans still in flight are dropped) and record its peak memory and
        checks."""
        if self._process.poll() is None:
            self._child.put(None)
            try:
                while True:
                    kind, value = self._answer()
                    if kind == "end":
                        peak_kib, self._checks = value
                        self.peak_memory_mb = peak_kib / 1024.0
                        break
            except SubmapSlamError:
                pass
        self._child.close()  # waits for the child (a child that does not end is stopped)
        self._in_flight = 0
        self._submitted.clear()


def start_odometry(config: OdometryConfig, planar: bool) -> InlineOdometry | OdometryProcess:
    """The registration stage ``config.separate_process`` asks for (None: a child process for
    3D logs, and for 2D lasers when this process may use more than one core: the child then
    registers while the graph worker tests loops, instead of each waiting for the GIL)."""
    separate = config.separate_process
    if separate is None:
        separate = not planar or usable_cores() > 1
    if separate:
        try:
            return OdometryProcess(config, planar)
        except OSError as exc:  # no process could be started (limits, no interpreter): the same poses here
            log.warning("odometry runs in this process: its child process could not start (%s)", exc)
    return InlineOdometry(config, planar)


if __name__ == "__main__":
    _serve()
