"""The result object of a run: everything writers and reports need, no files involved."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .config import PipelineConfig
from .process_stats import memory_growth_mb_per_km, peaks_by_process


@dataclass
class LoopRecord:
    """One tested cycle hypothesis between submaps ``i`` (older) and ``j`` (newer).

    An accepted one is a loop constraint: ``T_i_j`` (pose of ``j``'s anchor in ``i``'s) with the
    registration's ``information``; the graph builder adds it to the graph.
    """

    i: int
    j: int
    source: str  # "spatial" | "descriptor" | "hint"
    accepted: bool
    fitness: float
    overlap: float
    inlier_rmse: float
    reason: str
    T_i_j: np.ndarray | None = None
    structure_overlap: float = float("nan")  # 3D: overlap of the non-ground points, both ways
    plane_rmse: float = float("nan")  # 3D: point-to-plane RMSE [m] of those inliers
    information: np.ndarray | None = None  # (6, 6) GTSAM order: the registration's, as measured
    blamed: str = ""  # accepted closures: the constraint the final check blamed instead ("this closure": dropped)


@dataclass
class SlamResult:
    """Output of :func:`submapslam.pipeline.run`.

    Attributes:
        timestamps: ``(N,)`` scan timestamps as the log gives them, input order.
        poses: ``(N, 4, 4)`` optimised ``T_world_base`` per scan (world = first scan's frame).
        odometry_poses: ``(N, 4, 4)`` the same before loop closure (odometry only).
        submap_poses: ``(S, 4, 4)`` optimised ``T_world_submap`` anchors.
        submap_covariances: ``(S, 6, 6)`` marginal covariances of the anchors, GTSAM order
            ``(rx, ry, rz, tx, ty, tz)`` in the anchor frame.
        submap_points: list of ``(M_k, 3)`` submap clouds in their anchor frames (3D: float16 or
            float32, :func:`~submapslam.submaps.compact_points`).
        submap_scan_indices: list of scan-index lists per submap.
        submap_scan_poses: list of ``(K, 4, 4)`` ``T_anchor_scan`` per submap.
        submap_scan_points: per submap, each scan's ``(n, 3)`` sensor-frame points for the
            occupancy grids: the whole scan of a 2D laser, the obstacle slice of a 3D scan
            (empty lists when grids are off).
        edges: ``(i, j, T_i_j (4,4), information (6,6), kind)`` tuples of the submap graph.
        loops: every tested hypothesis.
        stage_seconds: wall time per stage; stages overlap (a closed submap's graph work runs
            beside the next scans' registration), so they add up to more than ``wall_time_s``.
        wall_time_s: wall-clock seconds from the engine's start to the result.
        map_voxel_size: [m] voxel of the fused map (the config's, resolved for the log's kind).
        path_length_m: odometry path length [m].
        memory_mb_by_km: ``(km travelled, resident MiB)`` when each submap closed.
        scans_by_wall_time: ``(seconds since the engine's start, scans done)`` when each submap
            closed (scans/s along the run).
        peak_memory_mb: peak resident set [MiB] when the result was made: this process's
            (``ru_maxrss``); when registration ran in a child process, at least this process's
            peak when the child ended plus the child's own peak (an upper bound of what both held
            at once: the child ends before the maps are fused).
        odometry_peak_memory_mb: the odometry child process's peak resident set [MiB] (its
            ``VmHWM``); 0 when the scans were registered in this process.
        main_peak_memory_mb: this process's own peak resident set [MiB] (``ru_maxrss``).
        peak_while_odometry_mb: this process's peak [MiB] when the odometry child ended (0: none ran).
        input_error: message of an input error that stopped reading early (results cover
            the scans read before it), else None.
        source: the log the scans came from.
        interrupted: the run was stopped (Ctrl-C, SIGTERM) before the end of the log; the
            result covers the scans read until then.
        submap_descriptors: ``(S, rings, sectors)`` the place descriptors the loop closer computed,
            one per submap in id order (None when loop closure was off).
        log_info: what the reader reports about the log (its ``log_info``: e.g. the CARMEN
            record read, damaged records skipped), written into ``summary.json``.
        hint_problems: one message per manual loop hint the log could not use.
        input_warnings: one line per kind of doubtful input the run accepted (timestamps running
            backwards, all-NaN scans, NaN beam ranges).
        optimiser_recoveries: one line per GTSAM failure the back end recovered from (the graph
            regularised, or the batch pass skipped).
        failure: the message of an optimiser failure that could not be recovered: the run
            ended there (``interrupted`` is set) and the result covers the scans before it.
        odometry_registration: the 3D registration used (``odometry.registration`` resolved:
            kiss_icp or voxel_gicp); "" for 2D lasers.
        submap_dynamic_points: 3D runs with ``mapping.split_movers``: per submap the ``(D_k, 3)``
            points (anchor frame) that moved, taken out of ``submap_points``; None otherwise.
        submap_scan_no_returns: planar runs: per submap each scan's ``(m, 3)`` ends of the beams
            that returned nothing (free space in the grid; an empty list per submap when the log
            gives none; a map folder keeps them).
        odometry_checks: planar and narrow-field 3D runs: how often the odometry's checks tried
            more than its first guess (:meth:`~submapslam.odometry.Odometry.checks`), and for planar
            runs ``wall_noise_m``, the laser's measured scatter across walls; empty otherwise.
        scan_refinement: planar runs: the figures of the scan-level refinement after the submap
            solve (:mod:`~submapslam.scan_refine`: keyframes, matches tried and kept, seconds);
            empty when it did not run. ``poses`` and ``submap_scan_poses`` are the refined ones.
    """

    timestamps: np.ndarray
    poses: np.ndarray
    odometry_poses: np.ndarray
    submap_poses: np.ndarray
    submap_covariances: np.ndarray
    submap_points: list[np.ndarray]
    submap_scan_indices: list[list[int]]
    submap_scan_poses: list[np.ndarray]
    submap_scan_points: list[list[np.ndarray]]
    edges: list[tuple]
    loops: list[LoopRecord]
    planar: bool
    config: PipelineConfig
    stage_seconds: dict[str, float] = field(default_factory=dict)
    wall_time_s: float = 0.0
    map_voxel_size: float = 0.1
    path_length_m: float = 0.0
    memory_mb_by_km: list[tuple[float, float]] = field(default_factory=list)
    scans_by_wall_time: list[tuple[float, int]] = field(default_factory=list)
    peak_memory_mb: float = 0.0
    odometry_peak_memory_mb: float = 0.0
    main_peak_memory_mb: float = 0.0
    peak_while_odometry_mb: float = 0.0
    input_error: str | None = None
    source: str = ""
    interrupted: bool = False
    submap_descriptors: np.ndarray | None = None
    log_info: dict = field(default_factory=dict)
    hint_problems: list[str] = field(default_factory=list)
    input_warnings: list[str] = field(default_factory=list)
    optimiser_recoveries: list[str] = field(default_factory=list)
    failure: str | None = None
    odometry_registration: str = ""
    submap_dynamic_points: list[np.ndarray] | None = None
    final_check: dict = field(default_factory=dict)
    submap_scan_no_returns: list[list[np.ndarray]] = field(default_factory=list)
    scan_refinement: dict = field(default_factory=dict)
    odometry_checks: dict = field(default_factory=dict)
    odometry_tilt_drift: dict = field(default_factory=dict)
    covariance_model: dict = field(default_factory=dict)  # how submap_covariances were made (summary.json)
    ground_tilt_change: dict = field(default_factory=dict)  # uncertainty.TiltChangeSpread.summary()
    ground_priors: dict = field(default_factory=dict)  # GraphBuilder.ground_prior_test: level test, kept or not

    @property
    def n_scans(self) -> int:
        return len(self.timestamps)

    @property
    def n_submaps(self) -> int:
        return len(self.submap_poses)

    @property
    def loops_accepted(self) -> int:
        return sum(1 for lp in self.loops if lp.accepted)

    def no_returns_of(self, k: int) -> list[np.ndarray]:
        """Submap ``k``'s per-scan ``(m, 3)`` no-return beam ends (:attr:`submap_scan_no_returns`),
        or an empty list when the run keeps none for it."""
        held = self.submap_scan_no_returns
        return held[k] if len(held) == self.n_submaps else []

    def pose_covariances(self) -> np.ndarray | None:
        """``(N, 6, 6)`` covariance of every scan pose (GTSAM order ``(rx, ry, rz, x, y, z)``, in
        the scan's own frame: :func:`~submapslam.uncertainty.scan_covariances`); None when the run
        has no covariances."""
        from .uncertainty import scan_covariances

        return scan_covariances(self)

    def odometry_consistency(self) -> dict:
        """How far the optimised anchors moved each odometry edge from its measurement.

        Per odometry edge ``(i, i + 1)`` the whitened squared residual ``e^T I e`` of
        ``e = log(T_meas^-1 T_i^-1 T_j)`` (GTSAM order, first order in the rotation) at the
        optimised anchors. With no ground truth at run time this is what tells that the loops
        made the graph disagree with the odometry: on the real 2D logs a consistent run stays
        below chi2 4 per edge (mean below 0.1 per DOF); MIT CSAIL before its odometry fix, which
        ended worse than its odometry, reached 10.3. ``disagrees_with_odometry`` is set when one
        edge exceeds the chi-square 95 % bound (3 DOF planar: 7.81; 6 DOF: 12.59) or the mean
        per DOF exceeds 0.25. Returns the figures and a ``message`` (None when consistent).
        """
        from .geometry import inverse, so3_log

        dof, bound = (3, 7.81) if self.planar else (6, 12.59)
        chi2, worst = [], None
        for i, j, T_i_j, info, kind in self.edges:
            if kind != "odometry" or max(i, j) >= len(self.submap_poses):
                continue
            err = inverse(np.asarray(T_i_j)) @ inverse(self.submap_poses[i]) @ self.submap_poses[j]
            e = np.concatenate([so3_log(err[:3, :3]), err[:3, 3]])
            value = float(e @ np.asarray(info) @ e)
            if worst is None or value > worst[2]:
                worst = (int(i), int(j), value)
            chi2.append(value)
        if not chi2:
            return {"odometry_edges": 0, "disagrees_with_odometry": False, "message": None}
        values = np.asarray(chi2)
        mean_per_dof = float(values.mean()) / dof
        disagrees = bool(values.max() > bound or mean_per_dof > 0.25)
        message = None
        if disagrees:
            message = (f"the optimised map disagrees with the odometry: odometry edge {worst[0]}-{worst[1]} "
                       f"stretched to chi2 {worst[2]:.1f} (95 % bound {bound}), {int((values > bound).sum())} of "
                       f"{len(values)} edges beyond it, mean {mean_per_dof:.2f} per DOF; loop closures may be "
                       "wrong: the result can be worse than the odometry alone (compare odometry_tum.txt)")
        return {"odometry_edges": len(values), "odometry_chi2_max": round(float(values.max()), 3),
                "odometry_chi2_mean_per_dof": round(mean_per_dof, 4), "worst_odometry_edge": [worst[0], worst[1]],
                "edges_beyond_bound": int((values > bound).sum()), "chi2_bound": bound,
                "disagrees_with_odometry": disagrees, "message": message}

    def summary(self) -> dict:
        """Figures for ``summary.json``."""
        growth = memory_growth_mb_per_km(self.memory_mb_by_km)
        return {
            "source": self.source,
            "scans": self.n_scans,
            "submaps": self.n_submaps,
            "planar": self.planar,
            "loop_candidates_tested": len(self.loops),
            "loop_closures_accepted": self.loops_accepted,
            "loop_closures_rejected": len(self.loops) - self.loops_accepted,
            "path_length_m": round(self.path_length_m, 3),
            "wall_time_s": {k: round(v, 3) for k, v in self.stage_seconds.items()},
            "wall_time_s_note": "per stage; stages overlap in time (graph work runs beside the next scans' "
                                "registration), so they add up to more than wall_time_total_s",
            "wall_time_total_s": round(self.wall_time_s, 3),
            "scans_per_second": round(self.n_scans / self.wall_time_s, 2) if self.wall_time_s > 0 else None,
            "peak_memory_mb": round(self.peak_memory_mb, 1),
            "peak_memory_mb_by_process": peaks_by_process(self.main_peak_memory_mb, self.peak_while_odometry_mb,
                                                          self.odometry_peak_memory_mb),
            "memory_mb_by_km": [[round(km, 4), round(mb, 1)] for km, mb in self.memory_mb_by_km],
            "memory_growth_mb_per_km": None if growth is None else round(growth, 1),
            "scans_by_wall_time_s": [[round(t, 3), n] for t, n in self.scans_by_wall_time],
            "input_error": self.input_error,
            "interrupted": self.interrupted,
            **self.log_info,
            "hint_problems": list(self.hint_problems),
            "input_warnings": list(self.input_warnings),
            "odometry_registration": self.odometry_registration or None,
            "optimiser_recoveries": list(self.optimiser_recoveries),
            "failure": self.failure,
            **({"final_check": self.final_check} if self.final_check else {}),
            **({"odometry_checks": self.odometry_checks} if self.odometry_checks else {}),
            **({"scan_refinement": self.scan_refinement} if self.scan_refinement else {}),
            **({"odometry_tilt_drift": self.odometry_tilt_drift} if self.odometry_tilt_drift else {}),
            **({"covariance_model": self.covariance_model} if self.covariance_model else {}),
            **({"ground_tilt_change": self.ground_tilt_change} if self.ground_tilt_change else {}),
            **({"ground_priors": self.ground_priors} if self.ground_priors else {}),
            "consistency": self.odometry_consistency(),
        }
