"""CLI command ``demo``: generate a synthetic loop world, run the pipeline on it, print the error.

The orchestration (a world from :mod:`datasets_synth`, then the library) lives here, at the
CLI edge: the library never imports :mod:`datasets_synth`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from ..errors import SubmapSlamError
from ._common import console, fail


def run_demo(out_dir: str | Path, *, world: str = "rectangle", seed: int = 0, laps: int = 2,
             max_scans: int | None = None) -> dict:
    """Generate a synthetic loop world, run the pipeline, and measure ATE against ground truth.

    Returns a dict with the ATE (se3-aligned) of wheel odometry, pipeline odometry and the full
    pipeline, loop counts and paths (``report``: the HTML report against the ground truth,
    ``picture``: a PNG of the map and trajectory); the same dict is written to
    ``OUT/demo_report.json``. ``max_scans`` cuts the synthetic log (a quick look).
    """
    import shutil

    from datasets_synth import generate

    from ..api import map_picture, report_run, run_log
    from ..evaluation.metrics import ate
    from ..io.output_folder import MARKER, check_out_folder, write_file_atomically, written_by
    from ..io.trajectory import Trajectory, read_tum

    out = Path(out_dir)
    # a demo folder is the demo's own: made again from the same seed, it is replaced without asking
    own = out.is_dir() and written_by(out) == "demo"
    check_out_folder(out, overwrite=own)
    if own:
        shutil.rmtree(out)
    log_dir = generate(world, out / "log", seed=seed, laps=laps, max_scans=max_scans)
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
        "report": str(report_run(out / "results", out / "report.html", ref=Path(log_dir) / "groundtruth_tum.txt")),
        "picture": str(map_picture(out / "results", out / "map.png")),
    }
    (out / "demo_report.json").write_text(json.dumps(report, indent=2) + "\n")
    write_file_atomically(out / MARKER, json.dumps({"command": "demo"}) + "\n")
    return report


def _ate_summary(stats: dict) -> dict:
    return {k: float(stats[k]) for k in ("rmse", "mean", "max") if k in stats}


def register(app: typer.Typer) -> None:
    """Add ``demo`` to ``app``."""

    @app.command()
    def demo(
        out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path("demo_out"),
        world: Annotated[str, typer.Option(help="Synthetic world.")] = "rectangle",
        seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
        laps: Annotated[int, typer.Option(min=1, help="Laps around the loop.")] = 2,
    ) -> None:
        """Generate a synthetic loop world, run the pipeline on it and print the trajectory error."""
        try:
            report = run_demo(out, world=world, seed=seed, laps=laps)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        table = Table(title=f"demo: {world}, seed {seed}, {laps} laps ({report['scans']} scans)")
        table.add_column("trajectory")
        table.add_column("ATE RMSE [m]", justify="right")
        table.add_column("ATE max [m]", justify="right")
        for name in ("wheel odometry", "odometry (no loop closure)", "submapslam"):
            r = report["ate"][name]
            table.add_row(name, f"{r['rmse']:.3f}", f"{r['max']:.3f}")
        console.print(table)
        console.print(f"{report['loops_accepted']} loop closures accepted of {report['loops_tested']} tested; "
                      f"results in {report['out']}")
        console.print(f"picture of the map and trajectory: {report['picture']}")
        console.print(f"report (open it in a browser): {report['report']}")
        console.print("next, a real log: submapslam run LOG --out OUT, then submapslam report OUT")
