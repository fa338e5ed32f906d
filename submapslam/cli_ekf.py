"""CLI command ``ekf``: the stochastic-map reference on a landmark log, optionally with the factor graph."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console

from .cli_common import fail
from .errors import InputError, SubmapSlamError


def _load(log: Path, fmt: str | None, robot: int):
    from .ekf.features import landmark_log_from_cloud_log
    from .io.landmark_logs import read_mrclam, read_victoria_park

    if fmt is None:
        fmt = ("cloud" if (log / "scans").is_dir() else "mrclam") if log.is_dir() else "victoria"
    if fmt == "mrclam":
        return read_mrclam(log, robot)
    if fmt in ("victoria", "synth"):
        return read_victoria_park(log)
    if fmt == "cloud":
        return landmark_log_from_cloud_log(log)
    raise InputError(log, f"unknown landmark log format {fmt!r}; use mrclam, victoria, synth or cloud")


def register(app: typer.Typer) -> None:
    """Add ``ekf`` to ``app``."""

    @app.command("ekf")
    def ekf_cmd(
        log: Annotated[Path, typer.Argument(help="MR.CLAM folder, a victoria_park-format file (real or synthetic), "
                                            "or a point-cloud log folder (pole features, unknown association).")],
        out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")],
        robot: Annotated[int, typer.Option(help="MR.CLAM robot number.")] = 1,
        format: Annotated[str | None, typer.Option(help="mrclam, victoria, synth or cloud (default: sniffed).")] = None,
        a: Annotated[float, typer.Option(help="Credibility learning rate a.")] = 1.0,
        b: Annotated[float, typer.Option(help="Credibility forgetting rate b.")] = 1e9,
        remove_below: Annotated[float, typer.Option(help="Remove features whose credibility falls below this.")] = 0.0,
        max_range: Annotated[float | None, typer.Option(help="Sensor range for unobserved predictions [m] "
                                                        "(default: the log's; unlimited for landmark logs).")] = None,
        compare: Annotated[bool, typer.Option(help="Also solve the GTSAM landmark graph and compare.")] = False,
        incremental: Annotated[bool, typer.Option(help="With --compare: iSAM2 step by step instead of batch LM.")] = False,
        fej: Annotated[bool, typer.Option(help="First-estimates Jacobians (FEJ-EKF, Huang et al. 2008): consistent "
                                          "longer, but needs roughly right first estimates.")] = False,
    ) -> None:
        """Run the full-covariance EKF (stochastic map with credibility); write poses, landmarks, plot."""
        import numpy as np

        from .ekf.outputs import write_ekf_results
        from .ekf.runner import landmark_errors_nearest, landmark_rmse, run_ekf, trajectory_rmse
        from .ekf.stochastic_map import CredibilityParams

        try:
            data = _load(log, format, robot)
            run = run_ekf(data, CredibilityParams(a=a, b=b, remove_below=remove_below), max_range=max_range,
                          first_estimate_jacobians=fej)
            est = {lm["id"]: np.array([lm["x"], lm["y"]]) for lm in run.filter.landmarks()}
            summary = {"log": data.name, "jacobians": "first estimates" if fej else "current estimates",
                       "steps": len(data.steps), "features": run.filter.n, "ekf_seconds": round(run.seconds, 3),
                       "matched": run.matched, "new": run.new, "unobserved": run.unobserved, "removed": run.removed}
            if data.truth_landmarks and data.known_association:
                summary["ekf_landmark_rmse_m"], summary["landmarks_compared"] = landmark_rmse(est, data.truth_landmarks)
            elif data.truth_landmarks:
                near = landmark_errors_nearest(est, data.truth_landmarks)
                summary["ekf_landmark_rmse_m"], summary["landmarks_compared"] = near["rmse"], near["found"]
                summary["landmarks_total"], summary["spurious_features"] = near["total"], near["spurious"]
            if data.truth_poses is not None:
                summary["ekf_trajectory_rmse_m"] = trajectory_rmse(run.times, run.poses, data.truth_times, data.truth_poses)
            if compare:
                from .backend.landmark_graph import solve_landmark_graph
                from .ekf.runner import with_ekf_association
                from .evaluation.landmark_compare import compare_landmark_solutions

                # without ids in the log, the graph gets the filter's own data association
                graph_data = data if data.known_association else with_ekf_association(data, run)
                sol = solve_landmark_graph(graph_data, incremental=incremental, warm_start=True)
                summary["comparison"] = compare_landmark_solutions(data, run, sol)
            write_ekf_results(out, run, summary, data.truth_landmarks or None, data.truth_poses)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        Console().print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in summary.items()})

    @app.command("ekf-nees")
    def ekf_nees_cmd(
        out: Annotated[Path, typer.Option("--out", "-o", help="Output folder (nees.json, nees.png).")],
        runs: Annotated[int, typer.Option(min=2, help="Monte Carlo runs.")] = 50,
        seed: Annotated[int, typer.Option(help="Seed of the first run.")] = 100,
        laps: Annotated[int, typer.Option(min=1, help="Laps per synthetic run.")] = 2,
        graph: Annotated[bool, typer.Option(help="Also the factor graph's (smoother) NEES.")] = True,
    ) -> None:
        """NEES of the EKF (and the smoother) over Monte Carlo runs on synthetic landmark worlds."""
        import json
        import tempfile

        from .evaluation.landmark_compare import nees_study, plot_nees

        try:
            out.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory() as tmp:
                study = nees_study(tmp, runs=runs, seed=seed, laps=laps, with_graph=graph)
        except (SubmapSlamError, OSError) as exc:
            raise fail(exc) from None
        lo, hi = study["band"]
        inside = float(np.mean((study["ekf"] >= lo) & (study["ekf"] <= hi)))
        doc = {"runs": runs, "band_95": [lo, hi], "ekf_fraction_inside": inside,
               "ekf_left_band_at": study["ekf_left_band_at"], "ekf_fej_left_band_at": study["ekf_fej_left_band_at"],
               "graph_left_band_at": study["graph_left_band_at"],
               "ekf_mean_nees": study["ekf"].tolist(), "ekf_fej_mean_nees": study["ekf_fej"].tolist(),
               "graph_mean_nees": None if study["graph"] is None else study["graph"].tolist()}
        (out / "nees.json").write_text(json.dumps(doc, indent=1))
        plot_nees(out / "nees.png", study)
        Console().print(f"band [{lo:.2f}, {hi:.2f}]; EKF inside for {inside:.0%} of steps; 10-step mean leaves "
                        f"the band at step {study['ekf_left_band_at']} (FEJ-EKF: {study['ekf_fej_left_band_at']}, "
                        f"graph: {study['graph_left_band_at']})")
