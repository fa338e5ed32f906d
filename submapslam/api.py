"""High-level library calls behind the CLI: run a log to a results folder, run the demo."""

from __future__ import annotations

import logging
from pathlib import Path

from .config import PipelineConfig, load_config
from .result import SlamResult

log = logging.getLogger(__name__)


def _progress_bar(total: int | None):
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
        with _progress_bar(total) as bar:
            task = bar.add_task("run", total=total)
            result = run(reader, cfg, source=str(log_path), hints=hint_pairs,
                         progress=lambda n: bar.update(task, completed=n))
    else:
        result = run(reader, cfg, source=str(log_path), hints=hint_pairs)
    paths: dict[str, Path] = {}
    if out_dir is not None:
        from .io.results import write_results

        paths = write_results(result, out_dir)
    return result, paths


def run_demo(out_dir: str | Path, *, world: str = "rectangle", seed: int = 0, laps: int = 2) -> dict:
    """Generate a synthetic loop world, run the pipeline, and measure ATE against ground truth.

    Returns a dict with the ATE (se3-aligned) of wheel odometry, pipeline odometry and the full
    pipeline, loop counts and paths; the same dict is written to ``OUT/demo_report.json``.
    """
    import json

    from datasets_synth import generate

    from .evaluation.metrics import ate
    from .io.trajectory import Trajectory, read_tum

    out = Path(out_dir)
    log_dir = generate(world, out / "log", seed=seed, laps=laps)
    result, _ = run_log(log_dir, out / "results", progress=True)
    gt = read_tum(Path(log_dir) / "groundtruth_tum.txt")
    wheel = read_tum(Path(log_dir) / "odometry_tum.txt")
    est = Trajectory(result.timestamps, result.poses)
    odo = Trajectory(result.timestamps, result.odometry_poses)
    report = {
        "world": world, "seed": seed, "laps": laps, "scans": result.n_scans, "submaps": result.n_submaps,
        "loops_tested": len(result.loops), "loops_accepted": result.loops_accepted,
        "ate": {name: _ate_summary(ate(t, gt, align="se3"))
                for name, t in (("wheel odometry", wheel), ("odometry (no loop closure)", odo), ("submapslam", est))},
        "out": str(out),
    }
    (out / "demo_report.json").write_text(json.dumps(report, indent=2) + "\n")
    return report


def _ate_summary(stats: dict) -> dict:
    return {k: float(stats[k]) for k in ("rmse", "mean", "max") if k in stats}


