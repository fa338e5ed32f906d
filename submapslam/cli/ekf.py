"""CLI command ``ekf``: the stochastic-map reference on a landmark log, optionally with the factor graph."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from .cli_common import fail
from .errors import SubmapSlamError


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
        from .ekf.runner import run_ekf
        from .ekf.stochastic_map import CredibilityParams
        from .evaluation.landmark_compare import ekf_summary, plot_stochastic_map
        from .io.ekf_results import write_ekf_results
        from .io.landmark_logs import read_landmark_log

        try:
            cred = CredibilityParams(a=a, b=b, remove_below=remove_below)
            data = read_landmark_log(log, format, robot)
            run = run_ekf(data, cred, max_range=max_range, first_estimate_jacobians=fej)
            summary = ekf_summary(data, run, compare=compare, incremental=incremental)
            write_ekf_results(out, run, summary)
            plot_stochastic_map(out / "landmarks.png", run, data.truth_landmarks or None, data.truth_poses)
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

        from .evaluation.landmark_compare import nees_study, nees_summary, plot_nees

        try:
            out.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory() as tmp:
                study = nees_study(tmp, runs=runs, seed=seed, laps=laps, with_graph=graph)
        except (SubmapSlamError, OSError) as exc:
            raise fail(exc) from None
        doc = nees_summary(study)
        (out / "nees.json").write_text(json.dumps(doc, indent=1))
        plot_nees(out / "nees.png", study)
        lo, hi = doc["band_95"]
        inside = doc["ekf_fraction_inside"]
        Console().print(f"band [{lo:.2f}, {hi:.2f}]; EKF inside for {inside:.0%} of steps; 10-step mean leaves "
                        f"the band at step {study['ekf_left_band_at']} (FEJ-EKF: {study['ekf_fej_left_band_at']}, "
                        f"graph: {study['graph_left_band_at']})")
