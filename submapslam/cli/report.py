"""CLI command ``report``: one self-contained HTML page of a results folder."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer

from ..errors import SubmapSlamError
from ._common import console, fail


def register(app: typer.Typer) -> None:
    """Add ``report`` to ``app``."""

    @app.command("report")
    def report_cmd(
        run_dir: Annotated[Path, typer.Argument(help="Results folder of `submapslam run` (or `ekf`).")],
        ref: Annotated[Path | None, typer.Option(help="Reference trajectory (TUM, KITTI or CARMEN) for the error sections.")] = None,
        raw_log: Annotated[Path | None, typer.Option(help="Raw CARMEN log, when REF is a corrected CARMEN log.")] = None,
        out: Annotated[Path | None, typer.Option("--out", "-o", help="The .html file to write (default RUN_DIR/report.html).")] = None,
        align: Annotated[str, typer.Option(help="Alignment to the reference: se3, sim3, se2 or none.")] = "se3",
    ) -> None:
        """Self-contained HTML report: map, trajectory, uncertainty, loops, errors, timings, config, input."""
        from ..api import report_run

        t0 = time.perf_counter()
        try:
            path = report_run(run_dir, out, ref=ref, raw_log=raw_log, align=align)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        size = path.stat().st_size
        console.print(f"report in {path} ({size / 1e6:.2f} MB, {time.perf_counter() - t0:.1f} s)")
