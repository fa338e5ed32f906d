"""What every CLI command shares: the consoles and the one-red-line error exit."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

OutFolder = Annotated[Path, typer.Option("--out", "-o", help="Output folder.")]
"""The ``--out`` option of the commands that write a results folder."""

class _Console(Console):
    """A rich console that does not wrap at 80 columns when its output is not a terminal (a file,
    a pipe, a test): tables and long names stay whole there; a terminal keeps its own width."""

    @property
    def size(self):  # type: ignore[override]
        from rich.console import ConsoleDimensions

        size = Console.size.fget(self)  # type: ignore[attr-defined]
        if self.is_terminal or self._width is not None:
            return size
        return ConsoleDimensions(max(size.width, _PIPED_WIDTH), size.height)

    @size.setter
    def size(self, new_size) -> None:
        Console.size.fset(self, new_size)  # type: ignore[attr-defined]


_PIPED_WIDTH = 240  # columns when not a terminal

console = _Console(markup=False)  # results are printed as they are: "[m]" in a table is a unit, not markup
err_console = _Console(stderr=True)


def fail(exc: BaseException | str) -> typer.Exit:
    """Print one red error line and return the ``Exit(1)`` to raise."""
    err_console.print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
    return typer.Exit(1)

Overwrite = Annotated[bool, typer.Option(
    "--overwrite", help="Replace the results of an earlier submapslam command in OUT (never a folder of yours).")]
"""The ``--overwrite`` option of the commands that write a results folder."""


def next_steps(out: Path, paths: dict[str, Path]) -> list[str]:
    """The lines that end a run: the files that matter in ``out`` and the ``report`` command."""
    names = [n for n in ("poses_tum.txt", "map.pgm", "map.ply", "summary.json") if n in paths]
    if not names:
        names = sorted(p for p in paths if "/" not in p)[:4]
    lines = [f"results in {out}: " + ", ".join(names) + (f" (+{len(paths) - len(names)} more)" if len(paths) > len(names) else "")]
    lines.append(f"next: submapslam report {out}   (one HTML page: map, trajectory, loops, errors)")
    return lines


def plural(n: int, word: str) -> str:
    """``"1 session"``, ``"2 sessions"``."""
    return f"{n} {word}" if n == 1 else f"{n} {word}s"
