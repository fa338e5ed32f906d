"""CLI command ``ekf``: the stochastic-map reference on a landmark log, optionally with the factor graph."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer

from ..errors import SubmapSlamError
from ._common import OutFolder, Overwrite, console, fail

if TYPE_CHECKING:
    from ..landmark_log import LandmarkLog


def register(app: typer.Typer) -> None:
    """Add ``ekf`` to ``app``."""

    @app.command("ekf")
    def ekf_cmd(
        log: Annotated[Path, typer.Argument(help="MR.CLAM folder, a victoria_park-format file (real or synthetic), "
                                            "or a point-cloud log folder (pole features, unknown association).")],
        out: OutFolder,
        robot: Annotated[int, typer.Option(help="MR.CLAM robot number.")] = 1,
        format: Annotated[str | None, typer.Option(help="mrclam, victoria, synth or cloud (default: sniffed).")] = None,
        a: Annotated[float | None, typer.Option(
            help="Credibility learning rate a [default: 1, or the config's ekf.credibility.a].")] = None,
        b: Annotated[float | None, typer.Option(
            help="Credibility forgetting rate b [default: 1e9, or the config's ekf.credibility.b].")] = None,
        remove_below: Annotated[float | None, typer.Option(
            help="Remove features whose credibility falls below this [default: 0, or the config's "
            "ekf.credibility.remove_below].")] = None,
        min_chances: Annotated[int | None, typer.Option(
            min=1, help="Consider removing a feature only once it had this many chances to be seen, sightings + "
            "misses [default: 1, or the config's ekf.credibility.min_chances].")] = None,
        memory: Annotated[float | None, typer.Option(
            help="Credibility memory in (0, 1]: both counts decay by this at each chance to see a feature, so a "
            "vanished one goes after a bounded number of misses [default: 1, the seed's counts, or the config's "
            "ekf.credibility.memory].")] = None,
        ignore_ids: Annotated[bool, typer.Option(help="Associate by Mahalanobis gating even where the log gives "
                                                 "landmark ids (the ids then only score the result).")] = False,
        max_range: Annotated[float | None, typer.Option(help="Sensor range for unobserved predictions [m] "
                                                        "(default: the log's; unlimited for landmark logs).")] = None,
        config: Annotated[Path | None, typer.Option(
            "--config", "-c", help="YAML config: its ekf section (see dump-config).")] = None,
        compare: Annotated[bool, typer.Option(help="Also solve the GTSAM landmark graph and compare.")] = False,
        incremental: Annotated[bool, typer.Option(help="With --compare: iSAM2 step by step instead of batch LM.")] = False,
        fej: Annotated[bool, typer.Option(help="First-estimates Jacobians (FEJ-EKF, Huang et al. 2008): consistent "
                                          "longer, but needs roughly right first estimates.")] = False,
        overwrite: Overwrite = False,
    ) -> None:
        """Run the full-covariance EKF (stochastic map with credibility); write poses, landmarks, plot."""
        from ..api import run_ekf_log
        from ..config import load_config, with_overrides

        try:
            cred = with_overrides(load_config(config).ekf.credibility, "ekf options",
                                  a=a, b=b, remove_below=remove_below, min_chances=min_chances,
                                  memory=memory)
            summary = run_ekf_log(log, out, format=format, robot=robot, credibility=cred,
                                  max_range=max_range, first_estimate_jacobians=fej,
                                  known_association=False if ignore_ids else None,
                                  compare=compare, incremental=incremental, overwrite=overwrite)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        for line in summary_lines(summary):
            console.print(line, highlight=False)

    @app.command("ekf-nees")
    def ekf_nees_cmd(
        out: Annotated[Path, typer.Option("--out", "-o", help="Output folder (nees.json, nees.png).")],
        runs: Annotated[int, typer.Option(min=2, help="Monte Carlo runs.")] = 50,
        seed: Annotated[int, typer.Option(help="Seed of the first run.")] = 100,
        laps: Annotated[int, typer.Option(min=1, help="Laps per synthetic run.")] = 2,
        graph: Annotated[bool, typer.Option(help="Also the factor graph's (smoother) NEES.")] = True,
        overwrite: Overwrite = False,
    ) -> None:
        """NEES of the EKF (and the smoother) over Monte Carlo runs on synthetic landmark worlds."""
        import tempfile

        from ..api import nees_report, progress_bar

        try:
            with tempfile.TemporaryDirectory() as tmp, progress_bar(runs) as bar:
                task = bar.add_task("runs", total=runs)
                study, doc = nees_report(synthetic_nees_trials(tmp, runs=runs, seed=seed, laps=laps), out,
                                         with_graph=graph, overwrite=overwrite,
                                         progress=lambda k: bar.update(task, completed=k))
        except (SubmapSlamError, OSError) as exc:
            raise fail(exc) from None
        lo, hi = doc["band_95"]
        inside = doc["ekf_fraction_inside"]
        console.print(f"band [{lo:.2f}, {hi:.2f}]; EKF inside for {inside:.0%} of steps; 10-step mean "
                      f"{_band_exit(study['ekf_left_band_at'])} (FEJ-EKF: {_band_exit(study['ekf_fej_left_band_at'])}, "
                      f"graph: {_band_exit(study['graph_left_band_at'])}); results in {out}", highlight=False)


def _band_exit(step: int | None) -> str:
    """How the 10-step mean NEES relates to the 95 % band, in words."""
    return "stays inside the band" if step is None else f"leaves the band at step {step}"


def synthetic_nees_trials(workdir: str | Path, runs: int = 50, seed: int = 100,
                          laps: int = 2) -> Iterator[tuple[LandmarkLog, np.ndarray]]:
    """``(log, truth)`` per Monte Carlo run for :func:`~submapslam.evaluation.landmark_compare.nees_study`:
    synthetic landmark worlds (seeds ``seed``, ``seed + 1``, ...) written under ``workdir``,
    truth ``(N, 3)`` ``x, y, yaw`` in the log's frame (the log starts at the origin); each log carries
    its true landmarks (``truth_landmarks``) in that frame."""
    from datasets_synth.landmarks import generate_landmark_log

    from ..io.landmark_logs import read_victoria_park, with_synthetic_truth

    for r in range(runs):
        folder = Path(workdir) / f"mc{r}"
        path = generate_landmark_log(folder / "syn.txt", seed=seed + r, laps=laps, sigma_range=0.05,
                                     odo_sigma=(0.03, 0.02, 0.01))
        log = with_synthetic_truth(read_victoria_park(path), path)  # the true landmarks too, in the log's frame
        raw = np.loadtxt(folder / "poses_truth.txt")[:, 1:4]
        c, s = np.cos(-raw[0, 2]), np.sin(-raw[0, 2])
        rel = raw - raw[0]
        yield log, np.c_[c * rel[:, 0] - s * rel[:, 1], s * rel[:, 0] + c * rel[:, 1], rel[:, 2]]


def summary_lines(summary: dict) -> list[str]:
    """``key: value`` lines of a summary dict (floats to 4 significant places, nested dicts indented)."""
    def text(v) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        if isinstance(v, list | tuple):
            return ", ".join(text(x) for x in v)
        return str(v)

    lines = []
    for key, value in summary.items():
        if isinstance(value, dict):
            lines.append(f"{key.replace('_', ' ')}:")
            lines += [f"  {k.replace('_', ' ')}: {text(v)}" for k, v in value.items()]
        else:
            lines.append(f"{key.replace('_', ' ')}: {text(value)}")
    return lines
