"""High-level library calls behind the CLI: run a log to a results folder, localise a log in a map."""

from __future__ import annotations

import functools
import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

from .config import PipelineConfig, load_config, with_updates
from .errors import ConfigError, SubmapSlamError
from .result import SlamResult

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Iterator

    import numpy as np

    from .ekf.stochastic_map import CredibilityParams
    from .landmark_log import LandmarkLog
    from .localization import LocalizationConfig, LocalizationResult
    from .mapping.global_map import MapOutputs
    from .observer import RunObserver
    from .session_map import SessionMap

log = logging.getLogger(__name__)


def progress_bar(total: int | None = None):
    """A transient rich progress bar on stderr: done of a total, elapsed time and ETA
    (:func:`submapslam.progress.progress_bar`; the total is given to ``add_task``)."""
    from .progress import progress_bar as bar

    return bar()


def fuse_beside_map_store(session_map: SessionMap, map_folder: Path,
                          fuse: Callable[[], MapOutputs]) -> tuple[MapOutputs, dict[str, Path]]:
    """Save ``session_map`` into ``map_folder`` (:func:`~submapslam.io.map_store.save_map`) and
    return ``fuse()``'s maps with the saved paths. A 2D map is small: saved in a thread while it
    fuses (the writing is mostly compression, off the GIL); a 3D one first, so that the map
    store's copies of the clouds and the city-sized grid never coexist."""
    from .io.map_store import save_map

    if not session_map.result.planar:
        paths = save_map(session_map, map_folder)
        return fuse(), paths
    with ThreadPoolExecutor(max_workers=1) as beside:
        saving = beside.submit(save_map, session_map, map_folder)
        maps = fuse()
        return maps, saving.result()


def run_log(
    log_path: str | Path | None,
    out_dir: str | Path | None,
    *,
    config: str | Path | PipelineConfig | None = None,
    format: str | None = None,
    hints: str | Path | None = None,
    max_scans: int | None = None,
    loops: bool = True,
    progress: bool = False,
    reader_options: dict | None = None,
    overwrite: bool = False,
    stop: threading.Event | None = None,
    resume: bool = False,
    observer: RunObserver | None = None,
    save_map: bool = True,
    session_name: str | None = None,
    on_progress: Callable[[int, int | None], None] | None = None,
    recorded_as: str | None = None,
) -> tuple[SlamResult, dict[str, Path]]:
    """Open ``log_path``, run the pipeline, write results to ``out_dir`` (if given).

    ``reader_options`` go to the log reader (ROS bags: ``topic``, ``odometry_topic``);
    ``observer`` watches the run (:mod:`submapslam.observer`, e.g. the Rerun live view).
    Every option and ``out_dir`` are checked before the log is read
    (:func:`~submapslam.io.output_folder.check_out_folder`: an earlier result in ``out_dir`` is
    replaced only with ``overwrite``); the files are written into a staging folder swapped in at
    the end. Setting ``stop`` ends the run after the current scan with a complete result set
    marked ``interrupted``.

    With ``out_dir``, a checkpoint is kept beside it (:mod:`.io.checkpoint`) every
    ``config.checkpoint_every_submaps`` submaps and when stopped, and removed when the run
    completes; ``resume=True`` continues the run that wrote ``out_dir`` from its checkpoint
    (its log, options and config; ``log_path`` may be None) to the result an uninterrupted run gives.

    ``save_map``: also write the run as a map that can be extended (``OUT/map/``, a one-session
    map named ``session_name``, default the log's file name without extensions).
    ``on_progress(scans done, scans in the log or None)`` is called after each scan (instead of
    ``progress``' bar; e.g. ``batch``'s live view of every log). ``recorded_as``: the log's path
    as the results name it, when ``log_path`` is a copy (``batch`` shipping a log to a Ray
    worker that does not see the original).

    Returns the result and the written paths. Input errors found mid-log keep what was
    computed: results are written and ``result.input_error`` says what stopped the reading.
    """
    from .io.hints import read_hint_file
    from .io.output_folder import check_out_folder
    from .io.registry import open_log
    from .pipeline import run

    t_start = time.perf_counter()
    checkpoint = None
    if resume:
        from .io.checkpoint import read_checkpoint

        if out_dir is None:
            raise SubmapSlamError("resuming needs the output folder of the interrupted run")
        checkpoint, config, started = read_checkpoint(out_dir)
        if log_path is not None and Path(log_path).resolve() != Path(started["log"]).resolve():
            raise SubmapSlamError(f"{out_dir} was started on {started['log']}, not {log_path}")
        log_path, format = started["log"], format or started.get("format")
        reader_options = reader_options or started.get("reader_options")
        hints, max_scans = None, None  # the checkpoint's config holds them
        overwrite = True  # OUT holds this run's own interrupted result, or nothing
    elif log_path is None:
        raise SubmapSlamError("no log given")
    cfg = config if isinstance(config, PipelineConfig) else load_config(config)
    updates: dict = {}
    if max_scans is not None:
        updates["max_scans"] = max_scans
    if not loops:
        updates["loops"] = {"enabled": False}
    if hints is not None:
        updates["loops"] = {**updates.get("loops", {}), "hints_file": str(hints)}
    if updates:
        cfg = with_updates(cfg, updates, "run options")
    inputs = [log_path, hints, cfg.loops.hints_file, config if not isinstance(config, PipelineConfig) else None]
    if out_dir is not None:
        check_out_folder(out_dir, inputs=inputs, overwrite=overwrite)
    hint_pairs = read_hint_file(cfg.loops.hints_file) if cfg.loops.hints_file else None
    reader = open_log(log_path, format, **(reader_options or {}))
    source = recorded_as or str(log_path)
    keep = None
    if out_dir is not None and cfg.checkpoint_every_submaps:
        from .io.checkpoint import write_checkpoint

        started = {"log": str(Path(log_path).resolve()), "format": format, "reader_options": reader_options or {}}

        def keep(ckpt) -> None:
            write_checkpoint(out_dir, ckpt, cfg, started)

    options = dict(source=source, hints=hint_pairs, stop=stop, resume_from=checkpoint,
                   checkpoint_every=cfg.checkpoint_every_submaps, on_checkpoint=keep, observer=observer)
    if progress:
        from .progress import ScanProgress

        with ScanProgress(reader, limit=cfg.max_scans) as bar:
            result = run(reader, cfg, progress=bar, **options)
    elif on_progress is not None:
        from .progress import clip_total, reader_total

        total, estimator = reader_total(reader)
        if total is None and estimator is not None:
            total = estimator()[0]
        total = clip_total(total, 0, cfg.max_scans)
        result = run(reader, cfg, progress=lambda n: on_progress(n, max(total, n) if total is not None else None),
                     **options)
    else:
        result = run(reader, cfg, **options)
    if hint_pairs:
        from .io.hints import hint_problems

        result.hint_problems = hint_problems(hint_pairs, result.timestamps, result.submap_scan_indices)
    paths: dict[str, Path] = {}
    if out_dir is not None:
        from .io.output_folder import staged_folder
        from .io.provenance import input_provenance, write_provenance
        from .io.results import write_results
        from .mapping.global_map import build_map_outputs, grid_process_wanted
        from .process_stats import release_free_memory

        with staged_folder(out_dir, "run", overwrite=overwrite, inputs=inputs) as staging:
            written: dict[str, Path] = {}

            def fuse() -> MapOutputs:
                release_free_memory()  # the run's freed temporaries out of the map fusion's peak
                return build_map_outputs(result, grid_process=grid_process_wanted(result))

            if save_map:  # OUT/map/: what `run --map OUT` extends (io/map_store.py)
                from .fleet import session_map_from_result, session_names

                name = session_name or session_names([log_path])[0]
                maps, map_paths = fuse_beside_map_store(session_map_from_result(result, name), staging / "map", fuse)
                written.update({f"map/{k}": v for k, v in map_paths.items()})
            else:
                maps = fuse()
            written.update(write_results(result, staging, maps, run_started=t_start))
            provenance = input_provenance(log_path, result.timestamps, recorded_as=recorded_as)
            written["input.json"] = write_provenance(staging, provenance)
        paths = {name: Path(out_dir) / name for name in written}
        if not result.interrupted:
            from .io.checkpoint import remove_checkpoint

            remove_checkpoint(out_dir)
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
    overwrite: bool = False,
) -> tuple[LocalizationResult, dict[str, Path]]:
    """Localise every scan of the log at ``log_path`` in the fixed map at ``map_path`` (a run
    folder or a PLY/PCD cloud, world frame) and write the results into ``out_dir``.

    ``initial_pose``: ``"x y yaw"`` of the first localised scan in the map frame (None: global
    search). ``start`` skips that many scans, ``max_scans`` stops after that many. ``out_dir``
    is checked first and written through a staging folder (``overwrite``: replace an earlier
    result). Returns the :class:`~submapslam.localization.LocalizationResult` and the written paths.
    """
    from .io.localization_results import write_localization
    from .io.output_folder import check_out_folder, staged_folder
    from .io.registry import open_log
    from .localization import load_map, localize_log, parse_initial_pose

    check_out_folder(out_dir, inputs=[log_path, map_path], overwrite=overwrite)
    T0 = parse_initial_pose(initial_pose)
    points = load_map(map_path)
    reader = open_log(log_path, format)
    if progress:
        from .progress import ScanProgress

        with ScanProgress(reader, start=start, limit=max_scans) as bar:
            result = localize_log(reader, points, T0, config=config, start=start, max_scans=max_scans,
                                  on_scan=lambda k: bar(k + 1))
    else:
        result = localize_log(reader, points, T0, config=config, start=start, max_scans=max_scans)
    with staged_folder(out_dir, "localize", overwrite=overwrite, inputs=[log_path, map_path]) as staging:
        written = write_localization(result, staging,
                                     extra={"log": str(log_path), "map": str(map_path), "map_points": len(points)})
    return result, {name: Path(out_dir) / p.name for name, p in written.items()}


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
    overwrite: bool = False,
    known_association: bool | None = None,
) -> dict:
    """Read a landmark log, run the stochastic map (EKF) on it, write ``poses_tum.txt``,
    ``landmarks.csv``, ``summary.json`` and ``landmarks.png`` into ``out_dir``; return the summary.

    ``known_association=False`` associates by gating even where the log has landmark ids (None:
    the log's own setting). A synthetic log whose truth says when landmarks vanish and appear
    gets a ``turnover`` section (:func:`~submapslam.ekf.runner.turnover_summary`).

    ``compare`` also solves the landmark factor graph (``incremental``: iSAM2 step by step).
    ``out_dir`` is checked first and written through a staging folder (``overwrite``: replace an
    earlier result).
    """
    from .ekf.runner import run_ekf
    from .evaluation.landmark_compare import ekf_summary, plot_stochastic_map
    from .io.ekf_results import write_ekf_results
    from .io.landmark_logs import read_landmark_log
    from .io.output_folder import check_out_folder, staged_folder

    check_out_folder(out_dir, inputs=[log_path], overwrite=overwrite)
    data = read_landmark_log(log_path, format, robot)
    if known_association is not None:
        from dataclasses import replace

        data = replace(data, known_association=known_association)
    run = run_ekf(data, credibility, max_range=max_range, first_estimate_jacobians=first_estimate_jacobians)
    summary = ekf_summary(data, run, compare=compare, incremental=incremental)
    with staged_folder(out_dir, "ekf", overwrite=overwrite, inputs=[log_path]) as staging:
        write_ekf_results(staging, run, summary)
        if data.truth_landmarks:  # for the report's map (landmarks.png draws them too)
            lines = ["id,x,y"] + [f"{k},{xy[0]:.6f},{xy[1]:.6f}" for k, xy in sorted(data.truth_landmarks.items())]
            (staging / "landmarks_truth.csv").write_text("\n".join(lines) + "\n")
        plot_stochastic_map(staging / "landmarks.png", run, data.truth_landmarks or None, data.truth_poses)
        from .io.provenance import input_provenance, write_provenance

        write_provenance(staging, input_provenance(log_path, run.times))
        if data.truth_poses is not None and len(data.truth_poses) > 1:  # NEES where truth is known (report)
            from .evaluation.ekf_nees import pose_nees_against_truth
            from .io.nees_csv import write_nees_csv

            t, nees = pose_nees_against_truth(run.times, run.poses, run.pose_covs, data.truth_times,
                                              data.truth_poses)
            if len(t):
                write_nees_csv(staging / "nees.csv", t, nees)
    return summary


def nees_report(trials: Iterable[tuple[LandmarkLog, np.ndarray]], out_dir: str | Path,
                with_graph: bool = True, overwrite: bool = False,
                progress: Callable[[int], None] | None = None) -> tuple[dict, dict]:
    """Run :func:`~submapslam.evaluation.landmark_compare.nees_study` on ``trials`` and write
    ``nees.json`` and ``nees.png`` into ``out_dir`` (checked first, written through a staging
    folder); return ``(study, nees.json's dict)``. ``progress(k)`` after the k-th trial."""
    import json

    from .evaluation.landmark_compare import nees_study, nees_summary, plot_nees
    from .io.output_folder import check_out_folder, staged_folder

    check_out_folder(out_dir, overwrite=overwrite)
    if progress is not None:
        trials = _counted(trials, progress)
    study = nees_study(trials, with_graph=with_graph)
    doc = nees_summary(study)
    with staged_folder(out_dir, "ekf-nees", overwrite=overwrite) as staging:
        (staging / "nees.json").write_text(json.dumps(doc, indent=1))
        plot_nees(staging / "nees.png", study)
    return study, doc


def _counted(items: Iterable, progress: Callable[[int], None]) -> Iterator:
    """Yield ``items``, calling ``progress(k)`` once the k-th has been used (asked for the next)."""
    k = 0
    for item in items:
        yield item
        k += 1
        progress(k)


def _reference(ref: str | Path, raw_log: str | Path | None):
    from .io.trajectory import carmen_reference_trajectory, read_trajectory

    return carmen_reference_trajectory(ref, raw_log) if raw_log else read_trajectory(ref)


def evaluate_files(est: str | Path, ref: str | Path, *, align: str = "se3", relations: str | Path | None = None,
                   max_diff: float = 0.02, raw_log: str | Path | None = None, derive_relations: bool = False,
                   scans: str | Path | None = None, match_relations: bool = False) -> dict:
    """ATE of the trajectory file ``est`` against ``ref`` (TUM, KITTI or CARMEN; ``raw_log``: the raw
    CARMEN log when ``ref`` is a corrected one), RPE over consecutive frames, and with
    ``relations`` the relations error (Kümmerle et al. 2009); with ``derive_relations`` (instead of
    a relations file) the relations error on relations derived from ``ref``
    (:func:`~submapslam.evaluation.derived_relations.derive_relations`: pairs close in time and
    pairs across loops). With ``scans`` (the log both trajectories place, e.g. the raw CARMEN log)
    also ``"loop_pair_misfit"``: how far that log's scans part under each trajectory where the
    reference comes back to a place
    (:func:`~submapslam.evaluation.scan_consistency.loop_pair_comparison`); a reference no more
    consistent than the estimate bounds what the ATE can say; its ``"at_worst"`` is the same over
    the pairs at the estimate's largest ATE errors
    (:func:`~submapslam.evaluation.scan_consistency.loop_pair_check`). With ``match_relations``
    (needs ``scans`` and relations) each relation is measured by matching its two scans instead
    (:func:`~submapslam.evaluation.scan_consistency.scan_matched_relations`, the benchmark's own
    method); only those scan matching fixes are kept, and ``"relations_matching"`` gives the counts
    and ``"reference_relations"`` the reference's own error on them.

    Returns ``{"ate": ate(...), "rpe": rpe(...), "relations": ... or None, "warnings": [...]}``
    (how the poses were paired, when it is doubtful: KITTI files of different lengths). An unknown
    ``align`` fails before any file is read.
    """
    import numpy as np

    from .evaluation.derived_relations import derive_relations as derive
    from .evaluation.metrics import Alignment, ate, relations_error, rpe
    from .io.trajectory import read_relations, read_trajectory

    Alignment(align)
    if relations and derive_relations:
        raise ConfigError("give a relations file or derive the relations from the reference, not both")
    if match_relations and (scans is None or not (relations or derive_relations)):
        raise ConfigError("matching relations needs the log's scans and relations (a file or derived from the "
                          "reference)")
    e = read_trajectory(est)
    r = _reference(ref, raw_log)
    warnings = _pairing_warnings(Path(est), Path(ref), e, r, raw_log, max_diff)
    rel = read_relations(relations) if relations else derive(r) if derive_relations else None
    extra = {}
    scans_at = None
    if scans is not None:
        from .io.scan_lookup import scans_read_once

        # the measures ask only for reference and relation times
        times = [r.timestamps] + ([rel.t_a, rel.t_b] if rel is not None else [])
        scans_at = scans_read_once(scans, np.concatenate(times))
    if match_relations:
        from .evaluation.scan_consistency import scan_matched_relations

        rel, counts = scan_matched_relations(r, rel, scans_at)
        extra = {"relations_matching": counts, "reference_relations": relations_error(r, rel, max_diff=max_diff)}
    figures = {"ate": ate(e, r, align=align, max_diff=max_diff),
               "rpe": rpe(e, r, delta=1, unit="frames", max_diff=max_diff),
               "relations": relations_error(e, rel, max_diff=max_diff) if rel is not None else None,
               "warnings": warnings, **extra}
    if scans is not None:
        from .evaluation.scan_consistency import loop_pair_check

        figures["loop_pair_misfit"] = loop_pair_check(e, r, scans_at, figures["ate"])
    return figures


def _raw_log_hint(ref: Path, raw_log) -> str | None:
    """What to say when a CARMEN reference matches the estimate badly and no raw log was given."""
    from .io.trajectory import trajectory_format

    if raw_log is not None or trajectory_format(ref) != "carmen":
        return None
    return (f"if {ref.name} is a corrected log, its timestamps are the raw log's logger time: "
            "give the raw log with --raw-log (raw_log=)")


def _pairing_warnings(est: Path, ref: Path, e, r, raw_log, max_diff: float) -> list[str]:
    """Warnings about how EST and REF were paired: KITTI files of different lengths (paired by
    line), a CARMEN reference whose timestamps match few of the estimate's (none: an error that
    suggests the raw log)."""
    import numpy as np

    from .evaluation.metrics import associate
    from .io.trajectory import trajectory_format

    warnings = []
    kitti = [p.name for p in (est, ref) if trajectory_format(p) == "kitti"]
    if kitti and len(e.timestamps) != len(r.timestamps):
        warnings.append(f"{est.name} has {len(e.timestamps)} poses and {ref.name} {len(r.timestamps)}: "
                        f"KITTI files ({', '.join(kitti)}) have no timestamps, so poses are paired by line "
                        f"and only the first {min(len(e.timestamps), len(r.timestamps))} are compared")
    hint = _raw_log_hint(ref, raw_log)
    if not kitti and not hint:  # (with a hint, the warning below says what went wrong)
        try:
            i_r = associate(e, r, max_diff)[1]
        except SubmapSlamError:
            i_r = np.zeros(0, dtype=int)
        span = float(np.ptp(r.timestamps)) if len(r.timestamps) > 1 else 0.0
        if len(i_r) and span > 0:
            covered = float(np.ptp(r.timestamps[i_r])) / span
            if covered < 0.9:
                warnings.append(f"{est.name} ({len(e.timestamps)} poses) covers {covered:.0%} of {ref.name}'s "
                                f"time ({len(r.timestamps)} poses): the figures are for that part only")
    if hint:
        try:
            matched = len(associate(e, r, max_diff)[0])
        except SubmapSlamError as exc:
            raise SubmapSlamError(f"{exc}; {hint}") from None
        if matched < 0.5 * len(r.timestamps):
            warnings.append(f"only {matched} of the {len(r.timestamps)} reference poses match a timestamp "
                            f"of the estimate; {hint}")
    return warnings


def compare_files(ref: str | Path, estimates: dict[str, str | Path], out_dir: str | Path, *, align: str = "se3",
                  raw_log: str | Path | None = None, overwrite: bool = False):
    """Side-by-side report of the trajectory files ``estimates`` (``{label: path}``) against
    ``ref``, written into ``out_dir`` (checked first, written through a staging folder);
    returns the :class:`~submapslam.evaluation.report.ComparisonResult`. An unknown ``align``
    fails before any file is read."""
    from .evaluation.metrics import Alignment
    from .evaluation.report import compare_trajectories
    from .io.output_folder import check_out_folder, staged_folder
    from .io.trajectory import read_trajectory

    inputs = [ref, raw_log, *estimates.values()]
    Alignment(align)
    check_out_folder(out_dir, inputs=inputs, overwrite=overwrite)
    r = _reference(ref, raw_log)
    trajectories = {label: read_trajectory(p) for label, p in estimates.items()}
    with staged_folder(out_dir, "compare", overwrite=overwrite, inputs=inputs) as staging:
        report = compare_trajectories(r, trajectories, staging, align=align, reference_name=Path(ref).name)
    report.files = {name: Path(out_dir) / p.name for name, p in report.files.items()}
    return report


def report_run(run_dir: str | Path, out_path: str | Path | None = None, *, ref: str | Path | None = None,
               raw_log: str | Path | None = None, align: str = "se3") -> Path:
    """Write the self-contained HTML report of the results folder ``run_dir`` (default
    ``run_dir/report.html``); with ``ref`` (``raw_log``: the raw CARMEN log when ``ref`` is a
    corrected one) the error against it; without ``ref``, against the ground truth the log ships
    (``groundtruth_tum.txt``, or ``groundtruth_kitti.txt`` / ``poses_gt_kitti.txt`` paired with its
    scans, beside it), if any. Returns the page's path.

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
        from .io.run_folder import read_shipped_ground_truth, shipped_ground_truth

        ref = shipped_ground_truth(run_dir)  # a log that ships its ground truth is evaluated against it
        truth = None
        if ref is not None:
            try:
                truth = read_shipped_ground_truth(ref)
            except InputError as exc:  # the page is still written, without the evaluation
                log.warning("%s: not evaluated against it", exc)
        if truth is None:
            return write_run_report(read_run_folder(run_dir), out, None, align=mode)
        return write_run_report(read_run_folder(run_dir), out, truth, align=mode,
                                reference_name=f"{Path(ref).name} (shipped with the log)")
    from concurrent.futures import ThreadPoolExecutor

    # the reference is read (decompressed: bz2/gzip release the GIL) while the map is drawn
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="reference") as pool:
        reference = pool.submit(_reference, ref, raw_log)
        try:
            record = read_run_folder(run_dir)
        except BaseException:
            reference.cancel()
            raise
        return write_run_report(record, out, reference.result, align=mode, reference_name=Path(ref).name,
                                scan_check=lambda: _scan_check(record, reference.result(), raw_log, mode))


def _scan_check(record, reference, raw_log: str | Path | None, align: str = "se3") -> dict | None:
    """The loop-pair misfit of a planar run and its reference on the run's log (``raw_log``, else the
    log ``input.json`` names), also at the run's largest errors after ``align``; None for a 3D run
    (a scan is a cloud, not a line of beams), when the log is not there, or when the reference never
    comes back."""
    from .errors import SubmapSlamError
    from .evaluation.metrics import ate
    from .evaluation.scan_consistency import loop_pair_check
    from .io.scan_lookup import scans_at

    log_path = raw_log if raw_log is not None else (record.provenance or {}).get("path")
    if not record.summary.get("planar") or log_path is None or not Path(log_path).exists() or record.poses is None:
        return None
    try:
        return loop_pair_check(record.poses, reference, functools.partial(scans_at, log_path),
                               ate(record.poses, reference, align=align))
    except SubmapSlamError as exc:
        log.info("no loop-pair check in the report: %s", exc)
        return None


def map_picture(run_dir: str | Path, png: str | Path | None = None) -> Path:
    """Write a PNG of the map and trajectory of the results folder ``run_dir`` (default
    ``run_dir/map.png``); returns its path. An existing file is replaced only when it is a PNG."""
    from .errors import InputError
    from .evaluation.run_figures import save_map_picture
    from .io.run_folder import read_run_folder

    out = Path(png) if png is not None else Path(run_dir) / "map.png"
    if out.is_dir():
        raise InputError(out, "is a folder; give the path of the .png file to write")
    if out.exists():
        with open(out, "rb") as fh:
            if fh.read(8) != b"\x89PNG\r\n\x1a\n":
                raise InputError(out, "exists and is not a PNG picture; not overwriting it")
    save_map_picture(read_run_folder(run_dir), out)
    return out


def evaluate_map_file(map_path: str | Path, log_path: str | Path, *, poses: str | Path | None = None,
                      voxel: float = 0.1, radius: float = 0.15) -> dict:
    """DynamicMap scores (SA, DA, AA) of a map file (PLY/PCD cloud or map_server grid) against a
    labelled log (``labels/NNNNNN.label``) placed at ``poses``.

    The frame rule ``clean`` shares: a map is in the frame of the poses it was made at, and is
    scored there. ``poses`` None: for a map ``clean`` wrote, the poses it was cleaned at (its
    ``summary.json``); for any other map, the log's ground truth. ``frame`` in the result names
    the poses used; ``warnings`` says when ``poses`` differ from those a ``clean`` map was made at.

    For a grid the truth is voxelised into 2D cells of the grid's resolution and the radius is
    at least 0.75 cells (a wall point's cell centre is up to 0.71 cells from its centroid).
    """
    from .errors import SubmapSlamError
    from .evaluation.dynamic_map import LabelledVoxels, score_map
    from .io.labels import count_scans, labelled_scans, map_made_at, read_map_points, scan_poses

    if voxel <= 0 or radius <= 0:
        raise SubmapSlamError(f"--voxel and --radius must be > 0 (got {voxel}, {radius})")
    map_points, resolution = read_map_points(map_path)
    made_at = map_made_at(map_path)
    warnings = []
    if poses is None and made_at is not None:
        if not made_at.is_file():
            raise SubmapSlamError(f"{map_path} was cleaned at {made_at}, which is gone; give --poses "
                                  "(the map is in the frame of the poses it was made at)")
        poses, frame = made_at, f"the poses it was cleaned at ({made_at})"
    elif poses is None:
        frame = "the log's ground truth"
    else:
        frame = f"--poses ({poses})"
        if made_at is not None and made_at.resolve() != Path(poses).resolve():
            warnings.append(f"{Path(map_path).name} was cleaned at {made_at}, not {poses}: if their frames "
                            "differ the scores mean nothing (leave out --poses to use the map's own)")
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
            "grid": planar_grid, "gt_points": truth.points, "frame": frame, "warnings": warnings, **scores}


def clean_log(log_path: str | Path, poses: str | Path, out_dir: str | Path, *, format: str | None = None,
              params=None, progress: bool = False, overwrite: bool = False) -> dict:
    """Remove what moved from a log given one pose per scan (TUM or KITTI ``T_world_base``, scan order);
    write ``map_static.ply``, ``map_dynamic.ply`` (voxel centroids, world frame) and ``summary.json``
    into ``out_dir`` (checked first, written through a staging folder; ``overwrite`` replaces an
    earlier result). Returns the summary (points and voxels kept/removed, wall time, peak memory).
    """
    import time

    from .errors import InputError, SubmapSlamError
    from .io.clean_results import write_clean_results
    from .io.output_folder import check_out_folder, staged_folder
    from .io.registry import open_log
    from .io.trajectory import read_trajectory
    from .mapping.dynamic_removal import RemovalParams, remove_dynamic_points
    from .process_stats import peak_memory_mb

    t0 = time.perf_counter()
    params = params or RemovalParams()
    check_out_folder(out_dir, inputs=[log_path, poses], overwrite=overwrite)
    traj = read_trajectory(poses)
    reader = open_log(log_path, format)
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
        "log": str(log_path), "poses": str(poses), "poses_resolved": str(Path(poses).resolve()),
        "frame": "the frame of the poses (--poses): eval-map scores this map there", "scans": counted["scans"],
        "points_kept": result.points_kept, "points_removed": result.points_removed,
        "voxels_kept": int((~result.dynamic).sum()), "voxels_removed": int(result.dynamic.sum()),
        "voxel_m": params.voxel, "output": "one point per voxel: the centroid of the scan points in it",
        "seconds": result.seconds, "params": {k: getattr(params, k) for k in params.__dataclass_fields__},
    }
    summary["wall_time_s"] = round(time.perf_counter() - t0, 3)
    summary["peak_memory_mb"] = round(peak_memory_mb(), 1)
    with staged_folder(out_dir, "clean", overwrite=overwrite, inputs=[log_path, poses]) as staging:
        write_clean_results(staging, result.centroids[~result.dynamic], result.centroids[result.dynamic], summary)
    return summary
