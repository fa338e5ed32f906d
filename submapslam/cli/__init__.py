"""Command-line interface: a typer app, one module per command. Each command validates its
input, makes one library call and prints; library errors become one red line and exit code 1.
"""

from __future__ import annotations

import logging
from typing import Annotated

import typer

from .. import __version__
from ._common import console

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="submapslam: submap-based SLAM for 2D laser and 3D LiDAR logs.")


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


def _register_commands() -> None:
    from . import (
        batch,
        clean,
        demo,
        drop_sessions,
        dump_config,
        ekf,
        eval_map,
        evaluate,
        localize,
        report,
        run,
        synth,
    )

    for module in (run, dump_config, demo, evaluate, synth, ekf, localize, report, eval_map, clean, batch,
                   drop_sessions):
        module.register(app)


_register_commands()


def main() -> None:
    """Console-script entry point."""
    app()


__all__ = ["app", "main"]
