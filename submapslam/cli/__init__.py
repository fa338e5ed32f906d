"""Command-line interface. Each command validates its input, calls one library function and
prints; library errors become one red line and exit code 1."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from . import __version__
from .cli_common import fail
from .errors import SubmapSlamError

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="submapslam: submap-based SLAM for 2D laser and 3D LiDAR logs.")
console = Console()


def _version(value: bool) -> None:
    if value:
        console.print(f"submapslam {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="Print the version and exit.")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log progress details.")] = False,
) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")


@app.command()
def run(
    log: Annotated[Path, typer.Argument(help="Log: CARMEN file, folder of .bin/.ply/.pcd scans, synthetic log folder, "
                                        "ROS bag (.bag, ROS 2 folder, .mcap).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")],
    config: Annotated[Path | None, typer.Option("--config", "-c", help="YAML config (see dump-config).")] = None,
    format: Annotated[str | None, typer.Option("--format", "-f", help="Force the log format.")] = None,
    hints: Annotated[Path | None, typer.Option("--hints", help="Manual loop hints: 'a b' scan indices or timestamps per line.")] = None,
    max_scans: Annotated[int | None, typer.Option("--max-scans", help="Stop after N scans.")] = None,
    no_loops: Annotated[bool, typer.Option("--no-loops", help="Odometry and submaps only.")] = False,
    topic: Annotated[str | None, typer.Option("--topic", help="ROS bag: the PointCloud2/LaserScan topic to read.")] = None,
    odometry_topic: Annotated[str | None, typer.Option(
        "--odometry-topic", help="ROS bag: the nav_msgs/Odometry topic ('' for none).")] = None,
    base_frame: Annotated[str | None, typer.Option(
        "--base-frame", help="ROS bag: robot frame the points are moved into through /tf_static "
        "(default: the odometry's child_frame_id, else base_link).")] = None,
) -> None:
    """Build a map and trajectory from LOG; write poses, graph, map and summary into OUT."""
    from .api import run_log

    try:
        result, paths = run_log(log, out, config=config, format=format, hints=hints,
                                max_scans=max_scans, loops=not no_loops, progress=True,
                                reader_options={"topic": topic, "odometry_topic": odometry_topic,
                                                "base_frame": base_frame})
    except SubmapSlamError as exc:
        raise fail(exc) from None
    s = result.summary()
    console.print(
        f"{s['scans']} scans, {s['submaps']} submaps, {s['loop_candidates_tested']} loop candidates tested, "
        f"{s['loop_closures_accepted']} accepted; {s['wall_time_total_s']:.1f} s, peak {s['peak_memory_mb']:.0f} MiB"
    )
    console.print(f"results in {out}")
    if result.input_error:
        raise fail(f"{result.input_error} (results cover the {s['scans']} scans read before it)")


@app.command("dump-config")
def dump_config_cmd(
    config: Annotated[Path | None, typer.Option("--config", "-c", help="Validate and print this file's effective config.")] = None,
) -> None:
    """Print the effective configuration (defaults, or a file's values) as YAML."""
    from .config import dump_config, load_config

    try:
        console.print(dump_config(load_config(config)), end="", highlight=False, markup=False)
    except SubmapSlamError as exc:
        raise fail(exc) from None


@app.command()
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path("demo_out"),
    world: Annotated[str, typer.Option(help="Synthetic world.")] = "rectangle",
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    laps: Annotated[int, typer.Option(help="Laps around the loop.")] = 2,
) -> None:
    """Generate a synthetic loop world, run the pipeline on it and print the trajectory error."""
    from .api import run_demo

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


def _register_subcommands() -> None:
    from . import cli_ekf, cli_eval, cli_localize, cli_synth

    for module in (cli_eval, cli_synth, cli_ekf, cli_localize):
        module.register(app)


_register_subcommands()


def main() -> None:
    """Console-script entry point."""
    app()
