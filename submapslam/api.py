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
    from .observer import RunObserver

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
    observer: RunObserver | None = None,
) -> tuple[SlamResult, dict[str, Path]]:
    """Open ``log_path``, run the pipeline, write results to ``out_dir`` (if given).

    ``reader_options`` go to the log reader (ROS bags: ``topic``, ``odometry_topic``);
    ``observer`` watches the run (:mod:`submapslam.observer`, e.g. the Rerun live view).

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
                         progress=lambda n: bar.update(task, completed=n), observer=observer)
    else:
        result = run(reader, cfg, source=str(log_path), hints=hint_pairs, observer=observer)
    paths: dict[str, Path] = {}
    if out_dir is not None:
        from .io.provenance import input_provenance, write_provenance
        from .io.results import write_results
        from .mapping.global_map import build_map_outputs

        paths = write_results(result, out_dir, build_map_outputs(result))
        paths["input.json"] = write_provenance(out_dir, input_provenance(log_path, result.timestamps))
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
    from .io.provenance import input_provenance, write_provenance

    write_provenance(out_dir, input_provenance(log_path, run.times))
    if data.truth_poses is not None and len(data.truth_poses) > 1:  # NEES where truth is known (report)
        from .evaluation.ekf_nees import pose_nees_against_truth
        from .io.nees_csv import write_nees_csv

        t, nees = pose_nees_against_truth(run.times, run.poses, run.pose_covs, data.truth_times, data.truth_poses)
        if len(t):
            write_nees_csv(Path(out_dir) / "nees.csv", t, nees)
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
    return compare_trajectories(r, {label: read_trajectory(p) for label, p in estimates.items()}, out_dir, align=align,
                                reference_name=Path(ref).name)


def report_run(run_dir: str | Path, out_path: str | Path | None = None, *, ref: str | Path | None = None,
               raw_log: str | Path | None = None, align: str = "se3") -> Path:
    """Write the self-contained HTML report of the results folder ``run_dir`` (default
    ``run_dir/report.html``); with ``ref`` (``raw_log``: the raw CARMEN log when ``ref`` is a
    corrected one) the error against it. Returns the page's path.

    An existing file at ``out_path`` is replaced only when it is a report this function wrote;
    anything else is an error, so no file of the user's is overwritten.
    """
    from .errors import InputError
    from .evaluation.html_page import is_report
    from .evaluation.html_report import write_run_report
    from .evaluation.metrics import Alignment
    from .io.run_folder import read_run_folder

    mode = Alignment(align)
    out = Path(out_path) if out_path is not None else Path(run_dir) / "report.html"
    if out.exists():
        if out.is_dir():
            raise InputError(out, "is a folder; --out takes the path of the .html file to write")
        with open(out, "rb") as fh:
            if not is_report(fh.read(2048)):
                raise InputError(out, "exists and is not a submapslam report; not overwriting it (choose another --out)")
    if not out.parent.is_dir():
        raise InputError(out.parent, "no such folder for the report")
    if ref is None:
        return write_run_report(read_run_folder(run_dir), out, None, align=mode)
    from concurrent.futures import ThreadPoolExecutor

    # the reference is read (decompressed: bz2/gzip release the GIL) while the map is drawn
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="reference") as pool:
        reference = pool.submit(_reference, ref, raw_log)
        try:
            record = read_run_folder(run_dir)
        except BaseException:
            reference.cancel()
            raise
        return write_run_report(record, out, reference.result, align=mode, reference_name=Path(ref).name)
