"""The live view: a :class:`~submapslam.observer.RunObserver` that streams a run to Rerun.

Entities (world frame, metres, a top-down 3D view): ``world/scan`` the newest scan,
``world/submaps/<id>`` each closed submap's cloud at its current anchor, ``world/trajectory``
the scans' poses (odometry, corrected by the newest submap's optimised anchor), ``world/anchors``
and ``world/anchor_path`` the optimised submap anchors, ``world/loops/accepted`` and
``world/loops/rejected`` the tested hypotheses (green / red, with the reason as label).
Timelines: ``scan`` (index) and ``scan_time`` (the log's timestamps, as a duration).

``rerun-sdk`` is an optional dependency (``pip install 'submapslam[view]'``); it is imported
when a view is made, and its absence is a :class:`~submapslam.errors.ConfigError` saying so.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..geometry import transform_points
from ..observer import RunObserver
from ..result import LoopRecord

log = logging.getLogger(__name__)


def _rerun():
    try:
        import rerun
    except ImportError:
        raise ConfigError("the live view needs rerun-sdk: pip install 'submapslam[view]' (or rerun-sdk)") from None
    return rerun


def _spawn_viewer(stream, port: int = 9876, wait_s: float = 10.0) -> None:
    """Start the Rerun viewer (the ``rerun`` executable the SDK installs beside this Python,
    found even when the venv is not activated)."""
    import os
    import sys

    bindir = str(Path(sys.executable).parent)
    if bindir not in os.environ.get("PATH", "").split(os.pathsep):
        os.environ["PATH"] = bindir + os.pathsep + os.environ.get("PATH", "")
    try:
        stream.spawn(port=port, connect=False)
    except RuntimeError as exc:
        raise ConfigError(f"could not start the Rerun viewer ({str(exc).splitlines()[0]}); "
                          "on a machine without a display use --record FILE.rrd instead") from None
    # a viewer that dies at once (no display) would leave the stream waiting for it: check it listens
    import socket
    import time

    deadline = time.monotonic() + wait_s
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise ConfigError(f"the Rerun viewer did not start listening on port {port} within {wait_s:.0f} s "
                                  "(no display?); use --record FILE.rrd and open it with `rerun FILE.rrd`") from None
            time.sleep(0.2)


class RerunView(RunObserver):
    """Stream scans, submaps, trajectory and loops to a Rerun viewer (``spawn=True``) and/or an
    ``.rrd`` file (``record``). ``max_scan_points`` thins what is sent of each scan (not what
    the run uses); ``scan_every`` sends every k-th scan only (the trajectory gets every pose)."""

    def __init__(self, *, spawn: bool = False, record: str | Path | None = None, max_scan_points: int = 20000,
                 scan_every: int = 1, application_id: str = "submapslam") -> None:
        if not spawn and record is None:
            raise ConfigError("a live view needs a viewer (spawn) or a recording file (record)")
        rr = _rerun()
        self._rr = rr
        self.stream = rr.RecordingStream(application_id)
        if spawn:
            _spawn_viewer(self.stream)
            if record is not None:  # both: send to the viewer and to the file
                self.stream.set_sinks(rr.GrpcSink(), rr.FileSink(str(record)))
            else:
                self.stream.connect_grpc()
        else:
            self.stream.save(str(record))
        self.max_scan_points = max_scan_points
        self.trajectory_every = 25  # scans between re-sends of the whole trajectory line
        self.scan_every = max(1, int(scan_every))
        self._lock = threading.Lock()  # scans and submaps arrive from two threads
        self._T_world_odom = np.eye(4)
        self._positions: list[np.ndarray] = []
        self._rng = np.random.default_rng(0)
        self._loops: dict[bool, list[tuple[np.ndarray, np.ndarray, str]]] = {True: [], False: []}
        self.stream.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    def _time(self, index: int, timestamp: float | None = None) -> None:
        self.stream.set_time("scan", sequence=index)
        if timestamp is not None:
            self.stream.set_time("scan_time", duration=float(timestamp))

    def on_scan(self, index: int, timestamp: float, T_odom_base: np.ndarray, points: np.ndarray) -> None:
        rr = self._rr
        with self._lock:
            T = self._T_world_odom @ T_odom_base
            self._positions.append(T[:3, 3].copy())
            self._time(index, timestamp)
            if index % self.scan_every == 0 and len(points):
                pts = np.asarray(points, dtype=np.float64)
                if len(pts) > self.max_scan_points:
                    pts = pts[self._rng.choice(len(pts), self.max_scan_points, replace=False)]
                self.stream.log("world/scan", rr.Points3D(transform_points(T, pts), colors=[255, 140, 0], radii=0.03))
            if index % self.trajectory_every == 0:
                self._log_trajectory()
            self.stream.log("world/robot", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))

    def _log_trajectory(self) -> None:
        if len(self._positions) > 1:
            self.stream.log("world/trajectory", self._rr.LineStrips3D([np.array(self._positions)], colors=[40, 90, 220]))

    def on_submap(self, submap_id: int, T_world_submaps: np.ndarray, points: np.ndarray,
                  T_world_odom: np.ndarray) -> None:
        rr = self._rr
        with self._lock:
            self._T_world_odom = np.array(T_world_odom)
            self._time(len(self._positions) - 1)
            pts = np.asarray(points, dtype=np.float32)
            self.stream.log(f"world/submaps/{submap_id}", rr.Points3D(pts, colors=[150, 150, 150], radii=0.02))
            for k, T in enumerate(T_world_submaps):  # every anchor moves when the graph is optimised
                self.stream.log(f"world/submaps/{k}", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
            self.stream.log("world/anchors", rr.Points3D(T_world_submaps[:, :3, 3], colors=[122, 31, 160], radii=0.12,
                                                         labels=[str(k) for k in range(len(T_world_submaps))]))
            # the anchors' path is the optimised trajectory at submap resolution: it bends when a loop closes
            self.stream.log("world/anchor_path", rr.LineStrips3D([T_world_submaps[:, :3, 3]], colors=[122, 31, 160]))
            self._log_trajectory()

    def on_loop(self, record: LoopRecord, T_world_i: np.ndarray, T_world_j: np.ndarray) -> None:
        rr = self._rr
        with self._lock:
            self._loops[bool(record.accepted)].append((T_world_i[:3, 3].copy(), T_world_j[:3, 3].copy(),
                                                       f"{record.i}-{record.j}: {record.reason}"))
            for accepted, color, name in ((True, [26, 154, 26], "accepted"), (False, [214, 32, 32], "rejected")):
                items = self._loops[accepted]
                if items:
                    self.stream.log(f"world/loops/{name}", rr.LineStrips3D(
                        [np.stack([a, b]) for a, b, _ in items], colors=color, labels=[t for _, _, t in items]))

    def close(self) -> None:
        """Send the last trajectory, flush and close the stream (the ``.rrd`` is complete after this)."""
        with self._lock:
            self._log_trajectory()
        try:
            self.stream.flush()
        except RuntimeError as exc:  # a viewer that went away (closed, or no display) loses nothing of the run
            log.warning("live view: %s", str(exc).splitlines()[0])
        self.stream.disconnect()
