"""High-level library calls behind the CLI: run a log to a results folder, localise a log in a map."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

from .config import PipelineConfig, load_config
from .result import SlamResult

if TYPE_CHECKING:
    from collections.abc import Iterable

    import numpy as np

    from .ekf.stochastic_map import CredibilityParams
    from .landmark_log import LandmarkLog
    from .localization import LocalizationConfig, LocalizationResult

log = logging.getLogger(__name__)


def progress_bar(total: int | None):
    """A transient rich progress bar on stderr (scans done of ``total``, None: unknown)."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("[bold]scans"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    console=Console(stderr=True), transient=True)


def run_log(
    log_path: str | Path,
    out_dir: str | Path | None,
    *,
    config: str | Path | PipelineConfig | None = None,
    format: str | None = None,
    hints: str | Path | None = None,
    max_scans: int | None = None,
    loops: bool = True,
    progress: bool = False,
    reader_options: dict | None = None,
) -> tuple[SlamResult, dict[str, Path]]:
    """Open ``log_path``, run the pipeline, write results to ``out_dir`` (if given).

    ``reader_options`` go to the log reader (ROS bags: ``topic``, ``odometry_topic``).

    Returns the result and the written paths. Input errors found mid-log keep what was
    computed: results are written and ``result.input_error`` says what stopped the reading.
    """
    from .io.hints import read_hint_file
    from .io.registry import open_log
    from .pipeline import run

    cfg = config if isinstance(config, PipelineConfig) else load_config(config)
    updates = {}
    if max_scans is not None:
        updates["max_scans"] = max_scans
    if not loops:
        cfg = cfg.model_copy(update={"loops": cfg.loops.model_copy(update={"enabled": False})})
    if hints is not None:
        cfg = cfg.model_copy(update={"loops": cfg.loops.model_copy(update={"hints_file": Path(hints)})})
    if updates:
        cfg = cfg.model_copy(update=updates)
    hint_pairs = read_hint_file(cfg.loops.hints_file) if cfg.loops.hints_file else None
    reader = open_log(log_path, format, **(reader_options or {}))
    try:
        total = len(reader)  # type: ignore[arg-type]
    except TypeError:
        total = None
    if max_scans is not None and total is not None:
        total = min(total, max_scans)
    if progress:
        with progress_bar(total) as bar:
            task = bar.add_task("run", total=total)
            result = run(reader, cfg, source=str(log_path), hints=hint_pairs,
                         progress=lambda n: bar.update(task, completed=n))
    else:
        result = run(reader, cfg, source=str(log_path), hints=hint_pairs)
    paths: dict[str, Path] = {}
    if out_dir is not None:
        from .io.results import write_results
        from .mapping.global_map import build_map_outputs

        paths = write_results(result, out_dir, build_map_outputs(result))
    return result, paths


def localize_to_folder(
    log_path: str | Path,
    map_path: str | Path,
    out_dir: str | Path,
    *,
    initial_pose: str | None = None,
    format: str | None = None,
    start: int = 0,
    max_scans: int | None = None,
    config: LocalizationConfig | None = None,
    progress: bool = False,
) -> tuple[LocalizationResult, dict[str, Path]]:
    """Localise every scan of the log at ``log_path`` in the fixed map at ``map_path`` (a run
    folder or a PLY/PCD cloud, world frame) and write the results into ``out_dir``.

    ``initial_pose``: ``"x y yaw"`` of the first localised scan in the map frame (None: global
    search). ``start`` skips that many scans, ``max_scans`` stops after that many. Returns the
    :class:`~submapslam.localization.LocalizationResult` and the written paths.
    """
    from .io.localization_results import write_localization
    from .io.registry import open_log
    from .localization import load_map, localize_log, parse_initial_pose

    T0 = parse_initial_pose(initial_pose)
    points = load_map(map_path)
    reader = open_log(log_path, format)
    if progress:
        try:
            total = max(0, len(reader) - start)  # type: ignore[arg-type]
            total = min(total, max_scans) if max_scans else total
        except TypeError:
            total = None
        with progress_bar(total) as bar:
            task = bar.add_task("localize", total=total)
            result = localize_log(reader, points, T0, config=config, start=start, max_scans=max_scans,
                                  on_scan=lambda k: bar.update(task, completed=k + 1))
    else:
        result = localize_log(reader, points, T0, config=config, start=start, max_scans=max_scans)
    paths = write_localization(result, out_dir,
                               extra={"log": str(log_path), "map": str(map_path), "map_points": len(points)})
    return result, paths


def run_ekf_log(
    log_path: str | Path,
    out_dir: str | Path,
    *,
    format: str | None = None,
    robot: int = 1,
    credibility: CredibilityParams | None = None,
    max_range: float | None = None,
    first_estimate_jacobians: bool = False,
    compare: bool = False,
    incremental: bool = False,
) -> dict:
    """Read a landmark log, run the stochastic map (EKF) on it, write ``poses_tum.txt``,
    ``landmarks.csv``, ``summary.json`` and ``landmarks.png`` into ``out_dir``; return the summary.

    ``compare`` also solves the landmark factor graph (``incremental``: iSAM2 step by step).
    """
    from .ekf.runner import run_ekf
    from .evaluation.landmark_compare import ekf_summary, plot_stochastic_map
    from .io.ekf_results import write_ekf_results
    from .io.landmark_logs import read_landmark_log

    data = read_landmark_log(log_path, format, robot)
    run = run_ekf(data, credibility, max_range=max_range, first_estimate_jacobians=first_estimate_jacobians)
    summary = ekf_summary(data, run, compare=compare, incremental=incremental)
    write_ekf_results(out_dir, run, summary)
    plot_stochastic_map(Path(out_dir) / "landmarks.png", run, data.truth_landmarks or None, data.truth_poses)
    return summary


def nees_report(trials: Iterable[tuple[LandmarkLog, np.ndarray]], out_dir: str | Path,
                with_graph: bool = True) -> tuple[dict, dict]:
    """Run :func:`~submapslam.evaluation.landmark_compare.nees_study` on ``trials`` and write
    ``nees.json`` and ``nees.png`` into ``out_dir`` (created); return ``(study, nees.json's dict)``."""
    import json

    from .evaluation.landmark_compare import nees_study, nees_summary, plot_nees

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    study = nees_study(trials, with_graph=with_graph)
    doc = nees_summary(study)
    (out / "nees.json").write_text(json.dumps(doc, indent=1))
    plot_nees(out / "nees.png", study)
    return study, doc


def _reference(ref: str | Path, raw_log: str | Path | None):
    from .io.trajectory import carmen_reference_trajectory, read_trajectory

    return carmen_reference_trajectory(ref, raw_log) if raw_log else read_trajectory(ref)


def evaluate_files(est: str | Path, ref: str | Path, *, align: str = "se3", relations: str | Path | None = None,
                   max_diff: float = 0.02, raw_log: str | Path | None = None) -> dict:
    """ATE of the trajectory file ``est`` against ``ref`` (TUM, KITTI or CARMEN; ``raw_log``: the raw
    CARMEN log when ``ref`` is a corrected one), RPE over consecutive frames, and with
    ``relations`` the relations error (Kümmerle et al. 2009).

    Returns ``{"ate": ate(...), "rpe": rpe(...), "relations": ... or None}``. An unknown
    ``align`` fails before any file is read.
    """
    from .evaluation.metrics import Alignment, ate, relations_error, rpe
    from .io.trajectory import read_relations, read_trajectory

    Alignment(align)
    e = read_trajectory(est)
    r = _reference(ref, raw_log)
    return {"ate": ate(e, r, align=align, max_diff=max_diff),
            "rpe": rpe(e, r, delta=1, unit="frames", max_diff=max_diff),
            "relations": relations_error(e, read_relations(relations), max_diff=max_diff) if relations else None}


def compare_files(ref: str | Path, estimates: dict[str, str | Path], out_dir: str | Path, *, align: str = "se3",
                  raw_log: str | Path | None = None):
    """Side-by-side report of the trajectory files ``estimates`` (``{label: path}``) against
    ``ref``, written into ``out_dir``; returns the
    :class:`~submapslam.evaluation.report.ComparisonResult`. An unknown ``align`` fails before
    any file is read."""
    from .evaluation.metrics import Alignment
    from .evaluation.report import compare_trajectories
    from .io.trajectory import read_trajectory

    Alignment(align)
    r = _reference(ref, raw_log)
    return compare_trajectories(r, {label: read_trajectory(p) for label, p in estimates.items()}, out_dir, align=align)


def evaluate_map_file(map_path: str | Path, log_path: str | Path, *, poses: str | Path | None = None,
                      voxel: float = 0.1, radius: float = 0.15) -> dict:
    """DynamicMap scores (SA, DA, AA) of a map file (PLY/PCD cloud or map_server grid) against a
    labelled log (``labels/NNNNNN.label``) placed at ``poses`` (default: the log's ground truth).

    For a grid the truth is voxelised into 2D cells of the grid's resolution and the radius is
    at least 0.75 cells (a wall point's cell centre is up to 0.71 cells from its centroid).
    """
    from .errors import SubmapSlamError
    from .evaluation.dynamic_map import LabelledVoxels, score_map
    from .io.labels import count_scans, labelled_scans, read_map_points, scan_poses

    if voxel <= 0 or radius <= 0:
        raise SubmapSlamError(f"--voxel and --radius must be > 0 (got {voxel}, {radius})")
    map_points, resolution = read_map_points(map_path)
    T = scan_poses(log_path, poses, count_scans(log_path))
    planar_grid = resolution is not None
    cell = resolution if planar_grid else voxel
    truth = None
    for k, points, labels, planar in labelled_scans(log_path):
        if truth is None:
            truth = LabelledVoxels(cell, planar=planar or planar_grid)
        truth.add(points @ T[k][:3, :3].T + T[k][:3, 3], labels)
    if truth is None:
        raise SubmapSlamError(f"{log_path}: no scans")
    r = max(radius, 0.75 * resolution) if planar_grid else radius
    scores = score_map(truth, map_points, r).as_dict()
    return {"map": str(map_path), "log": str(log_path), "voxel": cell, "radius": r,
            "grid": planar_grid, "gt_points": truth.points, **scores}


def clean_log(log_path: str | Path, poses: str | Path, out_dir: str | Path, *, format: str | None = None,
              params=None, progress: bool = False) -> dict:
    """Remove what moved from a log given one pose per scan (TUM or KITTI ``T_world_base``, scan order);
    write ``map_static.ply``, ``map_dynamic.ply`` (voxel centroids, world frame) and ``summary.json``
    into ``out_dir``. Returns the summary (points and voxels kept/removed, wall time, peak memory).
    """
    import time

    from .errors import InputError, SubmapSlamError
    from .io.clean_results import check_clean_folder, write_clean_results
    from .io.registry import open_log
    from .io.trajectory import read_trajectory
    from .mapping.dynamic_removal import RemovalParams, remove_dynamic_points
    from .process_stats import peak_memory_mb

    t0 = time.perf_counter()
    params = params or RemovalParams()
    traj = read_trajectory(poses)
    reader = open_log(log_path, format)
    out = check_clean_folder(out_dir)
    planar = bool(getattr(reader, "planar", False))
    counted = {"scans": 0}

    def scans():
        for k, scan in enumerate(open_log(log_path, format)):
            if k >= len(traj.poses):
                raise InputError(Path(poses), f"{len(traj.poses)} poses, but the log has more scans "
                                              "(one pose per scan, in scan order)")
            counted["scans"] = k + 1
            yield scan.points

    bar = progress_bar(None) if progress else None
    if bar is not None:
        bar.start()
        task = bar.add_task("scans", total=2 * len(traj.poses))
    try:
        result = remove_dynamic_points(
            scans, traj.poses, getattr(reader, "T_base_sensor", None), params, planar=planar,
            progress=None if bar is None else (
                lambda stage, k: bar.update(task, completed=k + (len(traj.poses) if stage == "evidence" else 0))))
    finally:
        if bar is not None:
            bar.stop()
    if counted["scans"] != len(traj.poses):
        raise InputError(Path(poses), f"{len(traj.poses)} poses for {counted['scans']} scans "
                                      "(one pose per scan, in scan order)")
    if not len(result.keys):
        raise SubmapSlamError(f"{log_path}: the scans hold no points")
    summary = {
        "log": str(log_path), "poses": str(poses), "scans": counted["scans"],
        "points_kept": result.points_kept, "points_removed": result.points_removed,
        "voxels_kept": int((~result.dynamic).sum()), "voxels_removed": int(result.dynamic.sum()),
        "voxel_m": params.voxel, "output": "one point per voxel: the centroid of the scan points in it",
        "seconds": result.seconds, "params": {k: getattr(params, k) for k in params.__dataclass_fields__},
    }
    summary["wall_time_s"] = round(time.perf_counter() - t0, 3)
    summary["peak_memory_mb"] = round(peak_memory_mb(), 1)
    write_clean_results(out, result.centroids[~result.dynamic], result.centroids[result.dynamic], summary)
    return summary
