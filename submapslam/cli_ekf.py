"""CLI command ``ekf``: the stochastic-map reference on a landmark log, optionally with the factor graph."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from .cli_common import fail
from .errors import InputError, SubmapSlamError


def _load(log: Path, fmt: str | None, robot: int):
    from .io.landmark_logs import read_mrclam, read_victoria_park

    if fmt is None:
        fmt = "mrclam" if log.is_dir() else "victoria"
    if fmt == "mrclam":
        return read_mrclam(log, robot)
    if fmt in ("victoria", "synth"):
        return read_victoria_park(log)
    raise InputError(log, f"unknown landmark log format {fmt!r}; use mrclam, victoria or synth")


def register(app: typer.Typer) -> None:
    """Add ``ekf`` to ``app``."""

    @app.command("ekf")
    def ekf_cmd(
        log: Annotated[Path, typer.Argument(help="MR.CLAM folder, or a victoria_park-format file (real or synthetic).")],
        out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")],
        robot: Annotated[int, typer.Option(help="MR.CLAM robot number.")] = 1,
        format: Annotated[str | None, typer.Option(help="mrclam, victoria or synth (default: sniffed).")] = None,
        a: Annotated[float, typer.Option(help="Credibility learning rate a.")] = 1.0,
        b: Annotated[float, typer.Option(help="Credibility forgetting rate b.")] = 1e9,
        remove_below: Annotated[float, typer.Option(help="Remove features whose credibility falls below this.")] = 0.0,
        max_range: Annotated[float, typer.Option(help="Sensor range for unobserved predictions [m].")] = float("inf"),
        compare: Annotated[bool, typer.Option(help="Also solve the GTSAM landmark graph and compare.")] = False,
    ) -> None:
        """Run the full-covariance EKF (stochastic map with credibility); write poses, landmarks, plot."""
        import numpy as np

        from .ekf.outputs import write_ekf_results
        from .ekf.runner import landmark_rmse, run_ekf, trajectory_rmse
        from .ekf.stochastic_map import CredibilityParams

        try:
            data = _load(log, format, robot)
            run = run_ekf(data, CredibilityParams(a=a, b=b, remove_below=remove_below), max_range=max_range)
            est = {lm["id"]: np.array([lm["x"], lm["y"]]) for lm in run.filter.landmarks()}
            summary = {"log": data.name, "steps": len(data.steps), "features": run.filter.n, "ekf_seconds": round(run.seconds, 3),
                       "matched": run.matched, "new": run.new, "unobserved": run.unobserved, "removed": run.removed}
            if data.truth_landmarks:
                summary["ekf_landmark_rmse_m"], summary["landmarks_compared"] = landmark_rmse(est, data.truth_landmarks)
            if data.truth_poses is not None:
                summary["ekf_trajectory_rmse_m"] = trajectory_rmse(run.times, run.poses, data.truth_times, data.truth_poses)
            if compare:
                from .backend.landmark_graph import solve_landmark_graph

                sol = solve_landmark_graph(data)
                diffs = [np.linalg.norm(est[k] - sol.landmarks[k]) for k in sol.landmarks if k in est]
                summary.update(graph_seconds=round(sol.seconds, 3),
                               ekf_vs_graph_landmark_rms_m=float(np.sqrt(np.mean(np.square(diffs)))) if diffs else None,
                               ekf_vs_graph_final_pose=[float(v) for v in run.poses[-1] - sol.poses[-1]])
                if data.truth_landmarks:
                    summary["graph_landmark_rmse_m"], _ = landmark_rmse(sol.landmarks, data.truth_landmarks)
                if data.truth_poses is not None:
                    summary["graph_trajectory_rmse_m"] = trajectory_rmse(run.times, sol.poses[1:], data.truth_times, data.truth_poses)
            write_ekf_results(out, run, summary, data.truth_landmarks or None, data.truth_poses)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        Console().print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in summary.items()})
