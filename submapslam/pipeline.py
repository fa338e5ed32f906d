"""The streaming engine: scans -> odometry -> submaps -> submap graph -> GTSAM -> SlamResult.

Use it as a stream (``SubmapSLAM.process_scan`` then read ``trajectory()`` / ``map_points()`` at
any moment) or in one call (``run(log)``). Data flows one way; nothing here writes files.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from contextlib import contextmanager
from functools import partial

import numpy as np

from .checkpoint import Checkpoint, KnownScan
from .config import PipelineConfig, narrow_field
from .errors import InputError, OptimisationError, SubmapSlamError
from .geometry import blend_poses_many, inverse
from .graph_builder import GraphBuilder
from .observer import RunObserver, notify_closed_submap
from .odometry import resolve_registration, young_scans
from .odometry_stage import InlineOdometry, OdometryProcess, Registered, start_odometry
from .process_stats import (
    combined_peak_mb,
    current_memory_mb,
    peak_memory_mb,
    release_free_memory,
    single_threaded_blas,
)
from .result import LoopRecord, SlamResult
from .scan import LoopHint, Scan
from .start_frame import StartFrame, spatial_start_correction
from .submaps import Submap, SubmapBuilder
from .uncertainty import calibrate, covariance_scale, scan_jitter_variance

log = logging.getLogger(__name__)


class StageTimer:
    """Accumulates wall time per named stage."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] = self.seconds.get(stage, 0.0) + time.perf_counter() - t0


class SubmapSLAM:
    """Streaming SLAM engine.

    Frames: the world frame is the pose of the first scan (its odometry pose is identity).
    """

    def __init__(self, config: PipelineConfig | None = None, hints: list[LoopHint] | None = None,
                 resume_from: Checkpoint | None = None, observer: RunObserver | None = None) -> None:
        """``resume_from``: the checkpoint of an earlier run of the same log and config; its scans
        are replayed with its decisions (:mod:`.checkpoint`), the rest run live. ``observer``: an
        optional viewer/logger (:mod:`.observer`), told about scans, submaps and loops."""
        self.config = config or PipelineConfig()
        self._replay = resume_from
        self._observer = observer
        self._records_by_submap: dict[int, list[LoopRecord]] = {}  # loop tests per closing submap
        # each scan's registration as the odometry made it, in its own frame (before the start's
        # re-base): what a checkpoint replays
        self._registered: list[KnownScan] = []
        self.timer = StageTimer()
        self._t_start = time.perf_counter()
        self._travelled = 0.0  # odometry path length so far [m]
        self.memory_mb_by_km: list[tuple[float, float]] = []  # (km travelled, resident MiB) per closed submap
        self.scans_by_wall_time: list[tuple[float, int]] = []  # (seconds since start, scans done) per closed submap
        self.planar: bool | None = None
        self.odometry_config = self.config.odometry  # registration "auto" resolved at the first scan
        self._fuse_thinned = False  # 3D: fuse the odometry's thinned scans into submaps (set at the first scan)
        self.map_voxel = self.config.mapping.map_voxel_size or 0.1  # resolved for the log's kind at the first scan
        self._odometry: InlineOdometry | OdometryProcess | None = None
        self._in_flight: deque[Scan] = deque()  # scans submitted for registration, not yet completed
        self._submitted = 0  # scans handed to the registration stage
        self._odometry_peak_mb = 0.0  # the odometry child process's peak resident set [MiB], when it ran
        self._peak_while_odometry_mb = 0.0  # this process's peak [MiB] when the odometry child ended
        self._odometry_closed = False
        self._wheel_scans = 0  # scans that came with wheel odometry
        self._builder: SubmapBuilder | None = None
        self._graph_builder: GraphBuilder | None = None  # made at the first scan (planar or not)
        self._loop_closer = None
        self._clouds = None  # 3D: SubmapClouds
        self._movers = None  # 3D with mapping.split_movers: SubmapMovers (each submap's evidence of what moved)
        self._hints = list(hints or [])
        self.timestamps: list[float] = []
        self._odom_poses: list[np.ndarray] = []
        self._scan_submap: list[int] = []  # submap id per scan, -1 while in the growing submap
        self.submaps: list[Submap] = []
        self._spill = None  # ScanSpill: closed submaps' grid scans on disk (made at the first spill)
        self._spilled = 0  # submaps 0 .. _spilled - 1 have their grid scans on disk
        self.loops: list[LoopRecord] = []
        self.dropped_nan_points = 0
        self.empty_scans = 0
        self.nan_scans: list[str] = []  # scans whose every point was NaN/inf (their sources)
        self.backwards: list[tuple[int, float, float]] = []  # (scan, its time, the time before it)
        self._last_time: float | None = None
        self._streamed = 0  # scans new_poses() has handed out
        self._live_correction = np.eye(4)  # T_world_odom of the newest optimised submap anchor
        # graph work of the last closed submap (odometry edge, loop tests, iSAM2), running in a
        # worker thread while the next scans are registered; waited for before anything reads
        # or extends the graph, so every graph operation happens in the same order as inline
        self._worker = None
        self._pending = None
        # the first scans held until the first is registered again (odometry.startup_refit_scans)
        self._start_frame = StartFrame(0)

    # ------------------------------------------------------------------ streaming
    def process_scan(self, scan: Scan) -> None:
        """Register one scan and update submaps, graph and loops as needed."""
        self.submit_scan(scan)
        self.complete_scan()

    @property
    def in_flight(self) -> int:
        """Scans submitted by :meth:`submit_scan` and not yet completed."""
        return len(self._in_flight)

    @property
    def look_ahead(self) -> int:
        """Scans worth keeping in flight: for an odometry child process a few 3D scans, or a
        submap's worth and more of planar ones; none in-process."""
        if not isinstance(self._odometry, OdometryProcess):
            return 0
        return _PLANAR_SCANS_IN_FLIGHT if self.planar else _SCANS_IN_FLIGHT

    def submit_scan(self, scan: Scan) -> None:
        """Hand one scan to the registration stage. With odometry in a child process
        (``odometry.separate_process``) it is registered there while the caller completes earlier
        scans; :meth:`complete_scan` takes the oldest. ``process_scan`` is the two in one."""
        if self.planar is None:
            self._start(scan)
        points = scan.points
        finite = np.isfinite(points).all(axis=1)
        if not finite.all():
            self.dropped_nan_points += int((~finite).sum())
            log.debug("%s: dropped %d non-finite points", scan.source, int((~finite).sum()))
            scan.points = points[finite]
            if scan.point_times is not None:
                scan.point_times = scan.point_times[finite]
            if len(scan.points) == 0:
                self.nan_scans.append(scan.source or f"scan {self._submitted}")
        if len(scan.points) == 0:
            self.empty_scans += 1
        if self._last_time is not None and scan.timestamp < self._last_time:
            self.backwards.append((self._submitted, scan.timestamp, self._last_time))
        self._last_time = scan.timestamp
        index = self._submitted
        known = self._replay.known_pose(index) if self._replay is not None else None
        if known is not None and scan.timestamp != self._replay.timestamps[index]:
            raise InputError(scan.source or "log", f"scan {index} has timestamp {scan.timestamp}, the "
                             f"checkpoint's {self._replay.timestamps[index]}: not the log it was made from")
        self._odometry.submit(scan, known)
        self._in_flight.append(scan)
        self._submitted += 1

    def complete_scan(self) -> None:
        """Take the oldest submitted scan's registration; update submaps, graph and loops."""
        scan = self._in_flight.popleft()
        with self.timer("odometry"):  # in-process: the registration; a child process: the wait for it
            registered = self._odometry.result()
        self._registered.append(KnownScan(registered.pose, registered.xyt, registered.map_refreshed, registered.guess))
        if self._observer is None:
            # only an observer reads a scan's raw points once it is registered (``registered.frame``
            # holds them as used): the start frame holds 31 3D scans, ~3 MB each of raw points at 64 rings
            scan = dataclasses.replace(scan, points=_NO_POINTS, point_times=None)
        for held_scan, held in self._start_frame.add(scan, registered):
            self._take(held_scan, held)

    def _start_refit(self) -> tuple[int, int]:
        """``(scans, skip)``: the run's first scan is registered again once ``scans`` follow it,
        against those after the first ``skip`` (``odometry.startup_refit_scans``; 3D: after the
        scans the young local map placed, :func:`~submapslam.odometry.young_scans`)."""
        cfg = self.odometry_config
        scans = cfg.startup_refit_scans if cfg.startup_refit_scans is not None else (20 if self.planar else 30)
        return scans, 0 if self.planar else min(young_scans(cfg), max(scans - 1, 0))

    def _take(self, scan: Scan, registered: Registered) -> None:
        """Add a registered scan (pose in the run's frame) to the trajectory, submaps, graph and loops."""
        T_odom_base, frame = registered.pose, registered.frame
        self._wheel_scans += scan.odometry is not None
        if self._odom_poses:
            self._travelled += float(np.linalg.norm(T_odom_base[:3, 3] - self._odom_poses[-1][:3, 3]))
        self.timestamps.append(scan.timestamp)
        self._odom_poses.append(T_odom_base)
        self._scan_submap.append(-1)
        with self.timer("submaps"):
            if self._movers is not None:
                self._movers.add(len(self.timestamps) - 1, T_odom_base, registered.frame_down, frame)
            if self._fuse_thinned:
                submap = self._builder.add(len(self.timestamps) - 1, T_odom_base, registered.frame_down,
                                           full_scan=frame)
            else:
                submap = self._builder.add(len(self.timestamps) - 1, T_odom_base, frame, no_returns=scan.no_returns)
        if self._observer is not None:
            self._observer.on_scan(len(self.timestamps) - 1, scan.timestamp, T_odom_base, scan.points)
        if submap is not None:
            self._close_submap(submap)

    def _start(self, scan: Scan) -> None:
        self.planar = bool(scan.planar)
        cfg = self.config
        self.odometry_config = resolve_registration(cfg.odometry, scan)
        self._odometry = start_odometry(self.odometry_config, self.planar)
        replaying_start = self._replay is not None and self._replay.known_pose(0) is not None
        if replaying_start:  # a resumed run's poses are in the frame its first run settled
            self._start_frame = StartFrame.settled(self._replay.run_frame)
        else:
            scans, skip = self._start_refit()
            refit = None if self.planar else partial(spatial_start_correction, voxel=self._odometry.frame_voxel)
            self._start_frame = StartFrame(scans, refit, skip)
        voxel = cfg.submaps.voxel_size or self._odometry.voxel_size / 2.0
        # 3D: a submap at the odometry's thinning voxel or coarser is the same when fused from the
        # thinned scans, with ~5x fewer points to transform and voxelise
        self._fuse_thinned = not self.planar and voxel >= self._odometry.frame_voxel
        self.map_voxel = cfg.mapping.map_voxel_size or (0.1 if self.planar else max(0.1, voxel))
        self._builder = SubmapBuilder(cfg.submaps, voxel, self.planar, grid_points=self._grid_slice())
        from .registration.correspondence import match_voxel

        if not self.planar and cfg.mapping.split_movers:
            from .mapping.moving_points import NARROW_SPLIT_PARAMS, SPLIT_PARAMS, SubmapMovers

            split = NARROW_SPLIT_PARAMS if narrow_field(self.odometry_config.registration) else SPLIT_PARAMS
            floor = cfg.mapping.split_floor_cell
            self._movers = SubmapMovers(split if floor is None else dataclasses.replace(split, floor_cell=floor))
        if not self.planar:  # prepared clouds, shared by odometry-edge registration and loop tests
            from .registration.spatial import SubmapClouds

            self._clouds = SubmapClouds(match_voxel(voxel, False))
        self._graph_builder = GraphBuilder(cfg.backend, self.odometry_config, planar=self.planar,
                                           match_voxel=match_voxel(voxel, self.planar), clouds=self._clouds,
                                           timer=self.timer)
        if cfg.loops.enabled:
            from .topology.loop_closure import LoopCloser

            self._loop_closer = LoopCloser(cfg.loops, planar=self.planar, voxel_size=voxel,
                                           max_range=cfg.odometry.max_range,
                                           submap_length=self._builder.max_distance, clouds=self._clouds,
                                           timer=self.timer)

    def _grid_slice(self):
        """For 3D runs with grids on: scan -> its obstacle slice (what the occupancy grid traces)."""
        mapping = self.config.mapping
        if self.planar or not mapping.write_grid:
            return None
        from functools import partial

        from .mapping.height_band import obstacle_points

        return partial(obstacle_points, cell=mapping.grid_resolution_3d, min_above_ground=mapping.grid_min_height,
                       max_above_ground=mapping.grid_max_height, ground_z=mapping.grid_ground_z)

    def _settle(self) -> None:
        """Wait for the last submap's graph work (re-raising its error, if any)."""
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.result()

    def _close_submap(self, submap: Submap, background: bool = True) -> None:
        self._settle()
        self.memory_mb_by_km.append((self._travelled / 1000.0, current_memory_mb()))
        self.scans_by_wall_time.append((time.perf_counter() - self._t_start, len(self.timestamps)))
        self.submaps.append(submap)
        self._spill_scans(submap.id - _LATER_SUBMAPS)
        for idx in submap.scan_indices:
            self._scan_submap[idx] = submap.id
        hint_pairs = self._hint_pairs()
        # whether the odometry followed wheels; read here: the worker must not see the main thread's later scans
        wheel = self._wheel_scans > 0 and self.config.odometry.use_wheel_odometry
        movers = self._movers.take(submap.scan_indices) if self._movers is not None else None
        if not background:
            self._add_submap_to_graph(submap, hint_pairs, wheel, movers)
            return
        if self._worker is None:
            from concurrent.futures import ThreadPoolExecutor

            self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="submap-graph")
        # scan registration (main thread) does not read the graph: its KISS-ICP, k-d tree, FFT
        # and numpy kernels overlap with the loop tests on a second core
        self._pending = self._worker.submit(self._add_submap_to_graph, submap, hint_pairs, wheel, movers)

    def _spill_scans(self, end: int) -> None:
        """Grid scans of the closed submaps before ``end`` to disk (:mod:`.mapping.scan_spill`):
        they are read again only by the final grid and scan refinement, and otherwise grow with the
        log's length. 3D submaps' clouds too (~15 MB/km of float16), read back each time a loop
        test or the end needs one. The graph work of a new submap may still edit the grid scans and
        clouds of the ``_LATER_SUBMAPS`` submaps before it (what moved leaves them), so those stay."""
        if end <= self._spilled:
            return
        from .mapping.scan_spill import ScanSpill

        if self._spill is None:
            self._spill = ScanSpill()
        for submap in self.submaps[self._spilled:end]:
            if submap.scan_points:
                submap.scan_points = self._spill.put(submap.scan_points)
            if submap.scan_no_returns:
                submap.scan_no_returns = self._spill.put(submap.scan_no_returns)
            if not submap.planar and len(submap.points):
                cloud = self._spill.put([submap.points])
                submap.keep_points_elsewhere(lambda cloud=cloud: cloud[0])
        self._spilled = end

    def _add_submap_to_graph(self, submap: Submap, hint_pairs: list[tuple[int, int]], wheel_odometry: bool,
                             movers: tuple | None = None) -> None:
        """The graph work of one closed submap: what moved leaves its cloud (``movers``: the
        evidence :meth:`SubmapMovers.take` gave), node and odometry edge, then its loop tests
        (replayed from the checkpoint being resumed, when it holds them)."""
        if movers is not None:
            with self.timer("movers"):
                self._split_movers(submap, movers)
                release_free_memory()  # the split's temporaries out of the resident set (the run's peak)
        previous = self.submaps[submap.id - 1] if submap.id > 0 else None
        replay = self._replay if self._replay is not None and submap.id < self._replay.n_submaps else None
        self._graph_builder.add_submap(submap, previous, wheel_odometry=wheel_odometry,
                                       information=replay.odometry_information.get(submap.id) if replay else None,
                                       tilt=replay.odometry_tilt.get(submap.id) if replay else None,
                                       correction=replay.odometry_correction.get(submap.id) if replay else None)
        records: list[LoopRecord] = []
        if self._loop_closer is not None:
            if replay is not None:
                records = self._loop_closer.replay(submap, replay.loop_records[submap.id])
            else:
                records = self._loop_closer.process(submap, self.submaps, self._graph_builder.estimate(), hint_pairs,
                                                    wheel_odometry)
            self.loops.extend(records)
            self._graph_builder.add_loops(records)
        self._records_by_submap[submap.id] = records
        # what new_poses() applies from now on (one reference assignment: safe to read meanwhile)
        self._live_correction = self._graph_builder.graph.pose(submap.id) @ inverse(submap.T_odom_anchor)
        if self._observer is not None:
            notify_closed_submap(self._observer, submap.id, submap.T_odom_anchor, submap.points, records,
                                 self._graph_builder.graph.pose)

    def _split_movers(self, submap: Submap, movers: tuple) -> None:
        """Move what the evidence says moved out of ``submap``'s cloud into its dynamic cloud (and
        out of its scans' obstacle slices, which the occupancy grid traces), and the same for the
        recent submaps within reach whose points its scans saw through."""
        moved = self._movers.split(movers, submap.T_odom_anchor, submap.points)
        self._move_out(submap, moved)
        reach = self.config.odometry.max_range + self._builder.max_distance
        for earlier in self.submaps[max(0, submap.id - _LATER_SUBMAPS):submap.id]:
            apart = earlier.T_odom_anchor[:3, 3] - submap.T_odom_anchor[:3, 3]
            if np.linalg.norm(apart) > reach or not len(earlier.points):
                continue
            moved = self._movers.seen_through_later(movers, earlier.T_odom_anchor, earlier.points)
            if moved.any():
                self._move_out(earlier, moved)
                if self._clouds is not None:
                    self._clouds.forget(earlier.id)

    def _move_out(self, submap: Submap, moved: np.ndarray) -> None:
        """``moved`` ``(M,)`` bool over ``submap.points``: into its dynamic cloud, and the obstacle-slice
        points of its scans in the same voxels out of the grid's input."""
        from .mapping.moving_points import drop_from_slices

        gone = submap.points[moved]
        previous = submap.dynamic_points if submap.dynamic_points is not None else gone[:0]
        submap.dynamic_points = np.concatenate([previous, gone])
        submap.points = submap.points[~moved]
        if len(gone) and submap.scan_points:
            submap.scan_points = drop_from_slices(submap.scan_points, submap.T_anchor_scans, gone,
                                                  self._movers.params.voxel)

    def checkpoint(self, source: str = "") -> Checkpoint:
        """The decisions so far (every scan's odometry, every closed submap's graph work), after
        waiting for the graph work under way; see :mod:`.checkpoint`."""
        import copy

        self._settle()
        taken = self._registered[:len(self._odom_poses)]  # while the start's scans are passed on: those taken
        return Checkpoint(
            timestamps=np.array(self.timestamps, dtype=np.float64),
            odometry_poses=np.array([known.pose for known in taken]).reshape(-1, 4, 4),
            planar_poses=np.array([known.xyt for known in taken]).reshape(-1, 3) if self.planar else None,
            map_refreshed=np.array([known.map_refreshed for known in taken], dtype=bool),
            guesses={k: known.guess for k, known in enumerate(taken) if known.guess is not None},
            run_frame=self._start_frame.correction,
            odometry_information=dict(self._graph_builder.odometry_information) if self._graph_builder else {},
            odometry_correction=dict(self._graph_builder.odometry_correction) if self._graph_builder else {},
            odometry_tilt=dict(self._graph_builder.odometry_tilt) if self._graph_builder else {},
            loop_records={k: [copy.copy(r) for r in recs] for k, recs in self._records_by_submap.items()},
            source=source,
        )

    def _hint_pairs(self) -> list[tuple[int, int]]:
        """Submap pairs of the manual hints whose scans are both in closed submaps."""
        if not self._hints:
            return []
        stamps = np.asarray(self.timestamps)
        pairs = []
        for hint in self._hints:
            ia, ib = _hint_scan(hint.a, hint.by_index, stamps), _hint_scan(hint.b, hint.by_index, stamps)
            if ia is None or ib is None:
                continue
            sa, sb = self._scan_submap[ia], self._scan_submap[ib]
            if sa >= 0 and sb >= 0 and sa != sb:
                pairs.append((min(sa, sb), max(sa, sb)))
        return pairs

    # ------------------------------------------------------------------ reading state
    def _corrections(self) -> dict[int, np.ndarray]:
        """Per closed submap: ``T_world_odom`` correction = optimised anchor @ odom anchor^-1."""
        if not self.submaps:
            return {}
        graph = self._graph_builder.graph
        return {s.id: graph.pose(s.id) @ inverse(s.T_odom_anchor) for s in self.submaps}

    def new_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """``(timestamps (K,), T_world_base (K, 4, 4))`` of the K scans completed since the last
        call: the cheap streaming read, O(K), that never waits for the graph work running beside.

        Each pose is the scan's odometry corrected by the newest optimised submap anchor known
        when it is read (the live estimate a robot acts on). A run's first scans come together
        once its frame is settled (:class:`~submapslam.start_frame.StartFrame`: a planar run's
        first 21 at the 21st scan, a 3D run's first 31 at the 31st,
        ``odometry.startup_refit_scans``). Earlier poses are not revised here:
        :meth:`trajectory` gives every scan's current, smoothed estimate (O(all scans), after
        waiting for the graph work); :meth:`finish` the final one.
        """
        start, end = self._streamed, len(self._odom_poses)
        self._streamed = end
        if end == start:
            return np.zeros(0), np.zeros((0, 4, 4))
        C = self._live_correction
        odom = np.asarray(self._odom_poses[start:end]).reshape(-1, 4, 4)
        return np.asarray(self.timestamps[start:end], dtype=np.float64), C @ odom

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Current ``(timestamps (N,), T_world_base (N, 4, 4))`` of every scan so far.

        O(all scans), and it waits for the graph work of the last closed submap: a call after
        every scan slows a long run down; :meth:`new_poses` is the cheap streaming read.

        A scan takes its submap's correction (optimised anchor vs odometry), blended towards the
        next submap's by the share of the odometry path between the two anchors it has covered:
        the odometry's drift inside a submap is spread over it instead of jumping at the next anchor.
        """
        self._settle()
        corr = self._corrections()
        last = corr[max(corr)] if corr else np.eye(4)
        poses = np.array(self._odom_poses).reshape(-1, 4, 4)
        ids = np.array(self._scan_submap, dtype=int)
        steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) if len(poses) > 1 else np.zeros(0)
        travelled = np.concatenate([[0.0], np.cumsum(steps)])  # odometry path length at each scan
        start = {s.id: travelled[s.scan_indices[0]] for s in self.submaps}
        out = np.empty_like(poses)
        # scans grouped by submap, each group's corrections at once (scan order kept within)
        order = np.argsort(ids, kind="stable")
        bounds = np.flatnonzero(np.diff(ids[order])) + 1
        for group in np.split(order, bounds) if len(order) else []:
            sid = int(ids[group[0]])
            if sid < 0:
                out[group] = last @ poses[group]
                continue
            C = corr[sid]
            if sid + 1 in corr:
                span = start[sid + 1] - start[sid]
                if span > 1e-9:
                    alpha = np.clip((travelled[group] - start[sid]) / span, 0.0, 1.0)
                    out[group] = blend_poses_many(C, corr[sid + 1], alpha) @ poses[group]
                    continue
            out[group] = C @ poses[group]
        return np.asarray(self.timestamps), out

    def map_points(self, voxel: float | None = None) -> np.ndarray:
        """Fused map ``(M, 3)`` in the world frame from the optimised submap anchors."""
        from .mapping.global_map import fuse_clouds

        self._settle()
        clouds = [(self._graph_builder.graph.pose(s.id), s.points) for s in self.submaps]
        if self._builder is not None and self.submaps:
            T = self._corrections()[self.submaps[-1].id] @ self._builder.current_anchor
            clouds.append((T, self._builder.current_points()))
        return fuse_clouds(clouds, voxel or self.map_voxel)

    # ------------------------------------------------------------------ finishing
    def input_warnings(self) -> list[str]:
        """One line per kind of doubtful input seen: timestamps that run backwards, scans whose
        every point was NaN/inf."""
        lines = []
        if self.backwards:
            k, t, before = self.backwards[0]
            lines.append(f"the log's timestamps run backwards {len(self.backwards)} time(s) (first at scan {k}: "
                         f"{t:.6f} after {before:.6f}); the poses keep the log's order, so their times do too")
        if self.nan_scans:
            lines.append(f"{len(self.nan_scans)} scan(s) hold only NaN/inf points (first: {self.nan_scans[0]}); "
                         "each got the pose odometry predicts")
        return lines

    def finish(self, input_error: str | None = None, source: str = "", interrupted: bool = False,
               failure: str | None = None) -> SlamResult:
        """Close the last submap, run the final batch optimisation and build the result
        (``interrupted``: the scans stop before the end of the log, marked in the result)."""
        if self.planar is None:
            raise SubmapSlamError(f"{source or 'log'}: no scans were processed")
        while self._in_flight:
            self.complete_scan()
        for held_scan, held in self._start_frame.settle(refit=False):  # a log shorter than the start's refit
            self._take(held_scan, held)
        self.close()  # a child process reports its checks as it ends
        odometry_checks = self._odometry.checks() if self._odometry is not None else {}
        try:
            if failure is None:  # after a failure the graph takes nothing more
                last = self._builder.flush()
                if last is not None:
                    self._close_submap(last, background=False)
            self._settle()
        except OptimisationError as exc:
            failure = str(exc)
        if self._worker is not None:
            self._worker.shutdown()
            self._worker = None
        jitter = scan_jitter_variance(np.array(self._odom_poses), np.asarray(self.timestamps))
        refit = start_path = None
        if self._start_frame.correction is not None:  # the covariances count where the re-based frame sits
            scans, skip = self._start_refit()
            refit = range(1 + skip, 1 + scans)
            start = np.array(self._odom_poses[:1 + scans]).reshape(-1, 4, 4)[:, :3, 3]
            start_path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(start, axis=0), axis=1))])
        try:
            reasons, covs = self._graph_builder.finish(jitter, refit, start_path)
        except (OptimisationError, RuntimeError) as exc:  # the estimate so far is kept, without covariances
            log.warning("the final optimisation failed: %s", exc)
            failure = failure or f"the final optimisation failed: {exc}"
            reasons, covs = {}, {k: np.full((6, 6), np.nan) for k in range(len(self.submaps))}
        noise = self._graph_builder.covariance_model  # the reported covariances' noise (3D), else None
        gave_way = list(self._graph_builder.graph.gave_way)
        for rec in self.loops:
            if rec.accepted and (rec.i, rec.j) in reasons:
                rec.accepted = False
                rec.reason = reasons[(rec.i, rec.j)]
                if rec.reason.startswith("dropped by the final check"):
                    rec.blamed = "this closure"
            elif rec.accepted:
                lo, hi = min(rec.i, rec.j), max(rec.i, rec.j)
                rec.blamed = "; ".join(f"{g['constraint']} {g['i']}-{g['j']} (chi2 {g['chi2']:.1f})" for g in gave_way
                                       if lo <= min(g["i"], g["j"]) and max(g["i"], g["j"]) <= hi)
        dropped = sum(why.startswith("dropped by the final check") for why in reasons.values())
        if dropped:
            log.warning("final check dropped %d loop closure(s) the odometry cannot reconcile", dropped)
        backend = self.config.backend
        final_check = ({"loops_dropped": int(dropped), "gave_way": gave_way}
                       if backend.final_check and backend.final_batch else {})
        if final_check and backend.ground_prior_kernel is not None:
            beyond = sum(v > 9.0 for v in self._graph_builder.graph.prior_chi2().values())
            final_check["ground_priors_beyond_3_sigma"] = int(beyond)  # down-weighted by their kernel
        timestamps, poses = self.trajectory()
        n = len(self.submaps)
        graph = self._graph_builder.graph
        scan_poses = [s.T_anchor_scans for s in self.submaps]
        refinement: dict = {}
        if self.planar and self.config.scan_refinement.enabled and n >= 2 and failure is None:
            release_free_memory()  # the run's freed temporaries (every thread's heap) out of the refinement's peak
            with self.timer("scan_refinement"):
                poses, refinement = self._refine_scans(poses, odometry_checks.get("wall_noise_m", 0.0))
            scan_poses = [inverse(graph.pose(s.id)) @ poses[s.scan_indices] for s in self.submaps]
        return SlamResult(
            timestamps=timestamps,
            poses=poses,
            odometry_poses=np.array(self._odom_poses),
            submap_poses=np.array([graph.pose(k) for k in range(n)]).reshape(-1, 4, 4),
            submap_covariances=(np.array([covs[k] for k in range(n)]).reshape(-1, 6, 6) if noise is not None else
                                calibrate(np.array([covs[k] for k in range(n)]).reshape(-1, 6, 6),
                                          covariance_scale(backend, self.planar))),
            covariance_model=({"kind": "measured odometry noise", **noise.summary(),
                               **self._graph_builder.world_up_summary(),
                               **self._graph_builder.first_cloud_summary(),
                               "scan_jitter_variance": [float(v) for v in jitter]}
                              if noise is not None else
                              {"kind": "graph marginals scaled per axis",
                               "scale": [float(v) for v in covariance_scale(backend, self.planar)]}),
            submap_points=[s.points for s in self.submaps],
            submap_scan_indices=[s.scan_indices for s in self.submaps],
            submap_scan_poses=scan_poses,
            submap_scan_points=[s.scan_points for s in self.submaps],
            submap_scan_no_returns=[s.scan_no_returns for s in self.submaps],
            edges=[(e.i, e.j, e.T_i_j, e.information, e.kind) for e in graph.active_edges()],
            loops=self.loops,
            planar=bool(self.planar),
            config=self.config,
            stage_seconds=dict(self.timer.seconds),
            wall_time_s=time.perf_counter() - self._t_start,
            map_voxel_size=self.map_voxel,
            path_length_m=self._travelled,
            memory_mb_by_km=list(self.memory_mb_by_km),
            scans_by_wall_time=list(self.scans_by_wall_time),
            peak_memory_mb=combined_peak_mb(peak_memory_mb(), self._peak_while_odometry_mb, self._odometry_peak_mb),
            main_peak_memory_mb=peak_memory_mb(),
            odometry_peak_memory_mb=self._odometry_peak_mb,
            peak_while_odometry_mb=self._peak_while_odometry_mb,
            input_error=input_error,
            source=source,
            interrupted=interrupted or failure is not None,
            failure=failure,
            optimiser_recoveries=list(graph.recoveries),
            odometry_registration="" if self.planar else self.odometry_config.registration,
            submap_descriptors=self._descriptors(n),
            submap_dynamic_points=[s.dynamic_points for s in self.submaps] if self._movers is not None else None,
            final_check=final_check,
            scan_refinement=refinement,
            odometry_checks=odometry_checks,
            odometry_tilt_drift=(self._graph_builder.tilt_drift.summary()
                                 if self._graph_builder.tilt_drift is not None else {}),
            ground_tilt_change=self._graph_builder.tilt_change_summary(),
            ground_priors=self._graph_builder.ground_prior_test,
        )

    def _refine_scans(self, poses: np.ndarray, wall_noise_m: float) -> tuple[np.ndarray, dict]:
        """Planar: every scan's ``T_world_base`` ``(N, 4, 4)`` after the scan-level refinement
        (:mod:`.scan_refine`) of ``poses`` (the submap solve's), and its figures; ``wall_noise_m``
        [m]: the laser's scatter across walls as the odometry measured it."""
        from .geometry import matrix_to_se2
        from .scan_refine import refine_scans

        where: dict[int, tuple[int, int]] = {}  # scan -> (submap, its place there); the last submap holding it
        for s in self.submaps:
            for k, i in enumerate(s.scan_indices):
                where[i] = (s.id, k)
        if len(where) < len(poses):  # scans not in any closed submap: nothing to refine
            return poses, {}
        scan_points = _ScanLookup(self.submaps, where)
        refined = refine_scans(matrix_to_se2(np.array(self._odom_poses)), matrix_to_se2(poses),
                               [s.scan_indices for s in self.submaps], [s.points for s in self.submaps],
                               scan_points, self.config.scan_refinement, wall_noise_m)
        return refined.poses, refined.stats

    def close(self) -> None:
        """End the registration stage (an odometry child process stops; scans in flight are
        dropped). :meth:`finish` calls it; call it yourself when abandoning a run."""
        if self._odometry is not None and not self._odometry_closed:
            if isinstance(self._odometry, OdometryProcess):
                self._peak_while_odometry_mb = peak_memory_mb()
            self._odometry.close()
            self._odometry_peak_mb = self._odometry.peak_memory_mb
            self._odometry_closed = True
        self._in_flight.clear()

    def _descriptors(self, n: int) -> np.ndarray | None:
        """The loop closer's ``n`` submap descriptors in id order, or None (loops off)."""
        index = self._loop_closer.index if self._loop_closer is not None else None
        if index is None or index.ids != list(range(n)) or not n:
            return None
        return np.array(index.descs)


def run(
    scans: Iterable[Scan],
    config: PipelineConfig | None = None,
    *,
    source: str = "",
    progress: Callable[[int], None] | None = None,
    hints: list[LoopHint] | None = None,
    observer: RunObserver | None = None,
    stop: threading.Event | None = None,
    resume_from: Checkpoint | None = None,
    checkpoint_every: int | None = None,
    on_checkpoint: Callable[[Checkpoint], None] | None = None,
) -> SlamResult:
    """Run the whole pipeline on an iterable of scans (e.g. ``open_log(path)``).

    ``source`` names the log in the result (default: the reader's ``path``, when it has one).
    An :class:`InputError` raised by the reader mid-log does not lose the scans already read:
    the result covers them and carries the message in ``input_error``. Setting ``stop`` (e.g.
    from a SIGINT handler) ends the reading after the current scan; the scans so far are
    optimised as usual and the result is marked ``interrupted``.

    ``on_checkpoint`` receives a :class:`~submapslam.checkpoint.Checkpoint` every
    ``checkpoint_every`` closed submaps and when stopped; ``resume_from`` replays one (the
    result is the one the uninterrupted run gives).
    """
    config = config or PipelineConfig()
    source = source or str(getattr(scans, "path", "") or "")  # a log reader knows its file
    slam = SubmapSLAM(config, hints, resume_from=resume_from, observer=observer)
    if resume_from is not None and resume_from.n_scans and config.max_scans is not None \
            and config.max_scans < resume_from.n_scans:
        raise SubmapSlamError(f"--max-scans {config.max_scans} is below the {resume_from.n_scans} scans "
                              "the checkpoint already covers")
    input_error = None
    failure = None  # an optimiser failure that could not be recovered
    interrupted = False
    n = 0  # scans completed
    submitted = 0
    last_checkpoint = 0  # submaps closed at the last checkpoint

    def complete_one() -> None:
        nonlocal n, last_checkpoint
        slam.complete_scan()
        n += 1
        if (on_checkpoint is not None and checkpoint_every
                and len(slam.submaps) >= last_checkpoint + checkpoint_every):
            last_checkpoint = len(slam.submaps)
            on_checkpoint(slam.checkpoint(source))
        if progress is not None:
            progress(n)

    def stop_requested() -> bool:
        """Whether the run is to stop now (``stop`` is set): logged once."""
        nonlocal interrupted
        if not interrupted and stop is not None and stop.is_set():
            interrupted = True
            log.warning("stopped after %d scans on request", n)
        return interrupted

    def read_all() -> None:
        """Submit and complete every scan until the end, a stop or an input error."""
        nonlocal submitted, input_error
        with ReadAhead(scans) as iterator:
            while config.max_scans is None or submitted < config.max_scans:
                if stop_requested():
                    break
                try:
                    with slam.timer("read"):  # time spent waiting for the reader
                        scan = next(iterator)
                except StopIteration:
                    break
                except InputError as exc:
                    if submitted == 0:
                        raise
                    input_error = str(exc)
                    log.info("stopped reading: %s", exc)  # the result carries it; the CLI prints it once
                    break
                slam.submit_scan(scan)
                submitted += 1
                if slam.in_flight > slam.look_ahead:
                    complete_one()
        # the scans read are all completed (the end of the log, an input error), unless a stop comes
        while slam.in_flight and not stop_requested():
            complete_one()
        if interrupted:
            slam.close()  # the result ends with the scan completed when the stop came: drop those in flight

    with single_threaded_blas():  # the run's threads and its odometry process need the cores
        try:
            try:
                read_all()
            except OptimisationError as exc:  # the run ends here; its result is kept as after a stop
                failure, interrupted = str(exc), True
                slam.close()
            if n == 0 and interrupted:
                raise SubmapSlamError(f"{source or 'log'}: stopped before the first scan was processed")
            if resume_from is not None and n < resume_from.n_scans and input_error is None and not interrupted:
                raise InputError(source or "log",
                                 f"holds {n} scans, fewer than the {resume_from.n_scans} of the checkpoint")
        except BaseException:
            slam.close()  # no result follows: end the odometry process
            raise
        if interrupted and on_checkpoint is not None:
            on_checkpoint(slam.checkpoint(source))
        result = slam.finish(input_error=input_error, source=source, interrupted=interrupted, failure=failure)
    result.log_info = dict(getattr(scans, "log_info", None) or {})  # the reader's account (record, skips)
    result.input_warnings = slam.input_warnings()
    if result.log_info.get("nan_only_scans"):
        files = result.log_info.get("nan_only_files") or ["?"]
        result.input_warnings.append(f"{result.log_info['nan_only_scans']} scan file(s) hold only NaN/inf points "
                                     f"(first: {files[0]}); each got the pose odometry predicts")
    if result.log_info.get("nan_ranges"):
        result.input_warnings.append(f"{result.log_info['nan_ranges']} NaN beam range(s) in the log, read as "
                                     "no return")
    return result


class _ScanLookup:
    """Scan index -> its grid points, read from its submap when asked (spilled scans stay on
    disk but for the few the scan refinement takes)."""

    def __init__(self, submaps: list[Submap], where: dict[int, tuple[int, int]]) -> None:
        self._submaps, self._where = submaps, where

    def __len__(self) -> int:
        return len(self._where)

    def __getitem__(self, i: int) -> np.ndarray:
        m, k = self._where[i]
        return self._submaps[m].scan_points[k]


# 3D: earlier submaps whose points a new submap's scans test for what has moved away since
_LATER_SUBMAPS = 4

#: a registered scan's raw points once no one will read them
_NO_POINTS = np.empty((0, 3))

# scans registered ahead of the one being completed: keeps an odometry child process busy
# while the main process builds submaps (a few scans: ~1 MB each, ~20 ms of registration)
_SCANS_IN_FLIGHT = 3
# planar scans are small (a few kB): the child registers on while this process waits for a
# submap's loop tests, which on a 2D log can take longer than the next submap's scans (MIT CSAIL:
# the last scan registered at 11.6 s with 3 in flight, at 10.8 s with 400, the same poses)
_PLANAR_SCANS_IN_FLIGHT = 256


class ReadAhead:
    """Iterate ``scans`` while a background thread reads the next ``depth`` of them, or fewer
    when their points would take more than ``max_bytes`` (one scan is always read ahead).

    Parsing a scan file (open3d, numpy, decompression) releases the GIL for most of its time,
    so reading overlaps with registration. Order, items and errors are those of the wrapped
    iterable: an exception the reader raises comes out of ``next`` at the same position.
    Leaving the ``with`` block stops the thread (it may have read up to ``depth`` scans more).
    A 64-ring scan's points take 2.5 MB: 8 of them were 8 % of such a run's resident set.
    """

    _END = object()

    def __init__(self, scans: Iterable[Scan], depth: int = 8, max_bytes: int = 8 << 20) -> None:
        import queue

        self._scans = scans
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._max_bytes = max_bytes
        self._queued_bytes = 0  # the points of the scans read and not yet taken
        self._taken = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name="scan-reader", daemon=True)

    def _put(self, item) -> bool:
        import queue

        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _read(self) -> None:
        try:
            for scan in self._scans:
                size = _points_bytes(scan)
                with self._taken:  # room for this one's points, or none queued
                    while (self._queued_bytes and self._queued_bytes + size > self._max_bytes
                           and not self._stop.is_set()):
                        self._taken.wait(0.1)
                    self._queued_bytes += size
                if not self._put((scan, None)):
                    return
        except BaseException as exc:  # handed to the consumer, raised there
            self._put((None, exc))
            return
        self._put((self._END, None))

    def __enter__(self) -> ReadAhead:
        self._thread.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    def __iter__(self) -> ReadAhead:
        return self

    def __next__(self) -> Scan:
        item, error = self._queue.get()
        if error is not None:
            self._queue.put((None, error))  # a reader stays failed
            raise error
        if item is self._END:
            self._queue.put((self._END, None))
            raise StopIteration
        with self._taken:
            self._queued_bytes -= _points_bytes(item)
            self._taken.notify()
        return item


def _points_bytes(scan: Scan) -> int:
    """What a scan's points (and per-point times) take in memory [bytes]."""
    times = scan.point_times
    return scan.points.nbytes + (times.nbytes if times is not None else 0)


def _hint_scan(value: float, by_index: bool, stamps: np.ndarray) -> int | None:
    """Scan index of one hint value, or None while that scan has not been read yet."""
    if by_index:
        return int(value) if value < len(stamps) else None
    if len(stamps) == 0 or value > stamps[-1] or value < stamps[0] - 1.0:  # before the log: never a scan
        return None
    return int(np.argmin(np.abs(stamps - value)))
