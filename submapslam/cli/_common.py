"""What every CLI command shares: the consoles and the one-red-line error exit."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

OutFolder = Annotated[Path, typer.Option("--out", "-o", help="Output folder.")]
"""The ``--out`` option of the commands that write a results folder."""

console = Console(markup=False)  # results are printed as they are: "[m]" in a table is a unit, not markup
err_console = Console(stderr=True)


def fail(exc: BaseException | str) -> typer.Exit:
    """Print one red error line and return the ``Exit(1)`` to raise."""
    err_console.print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
    return typer.Exit(1)

Overwrite = Annotated[bool, typer.Option(
    "--overwrite", help="Replace the results of an earlier submapslam command in OUT (never a folder of yours).")]
"""The ``--overwrite`` option of the commands that write a results folder."""
