"""CLI commands ``eval`` and ``compare``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from .cli_common import fail
from .errors import SubmapSlamError

console = Console()


def register(app: typer.Typer) -> None:
    """Add ``eval`` and ``compare`` to ``app``."""

    @app.command("eval")
    def eval_cmd(
        est: Annotated[Path, typer.Argument(help="Estimated trajectory (TUM, KITTI or CARMEN).")],
        ref: Annotated[Path, typer.Argument(help="Reference trajectory (TUM, KITTI or CARMEN).")],
        align: Annotated[str, typer.Option(help="Alignment: se3, sim3, se2 or none.")] = "se3",
        relations: Annotated[Path | None, typer.Option(help="Relations file (Kümmerle et al. 2009).")] = None,
        json_out: Annotated[Path | None, typer.Option("--json", help="Write all figures as JSON.")] = None,
        max_diff: Annotated[float, typer.Option(help="Timestamp association tolerance [s].")] = 0.02,
        raw_log: Annotated[Path | None, typer.Option(help="Raw CARMEN log, when REF is a corrected CARMEN log.")] = None,
    ) -> None:
        """ATE (RMSE) and RPE of EST against REF; with --relations the relations error."""
        from .evaluation.metrics import Alignment, ate, relations_error, rpe
        from .io.trajectory import carmen_reference_trajectory, read_relations, read_trajectory

        try:
            Alignment(align)  # an unknown value fails before any file is read
            e = read_trajectory(est)
            r = carmen_reference_trajectory(ref, raw_log) if raw_log else read_trajectory(ref)
            a = ate(e, r, align=align, max_diff=max_diff)
            p = rpe(e, r, delta=1, unit="frames", max_diff=max_diff)
            rel = relations_error(e, read_relations(relations), max_diff=max_diff) if relations else None
        except SubmapSlamError as exc:
            raise fail(exc) from None
        table = Table(title=f"{est.name} vs {ref.name} ({a['n']} poses, align {align})")
        table.add_column("metric")
        for col in ("rmse", "mean", "median", "std", "max"):
            table.add_column(col, justify="right")
        table.add_row("ATE [m]", *(f"{a[k]:.4f}" for k in ("rmse", "mean", "median", "std", "max")))
        table.add_row("RPE trans [m/frame]", *(f"{p[k]:.4f}" for k in ("rmse", "mean", "median", "std", "max")))
        table.add_row("RPE rot [deg/frame]", *(f"{p['rotation_' + k]:.4f}" for k in ("rmse", "mean", "median", "std", "max")))
        console.print(table)
        out = {"ate": {k: v for k, v in a.items() if k not in ("errors", "timestamps")}, "rpe": p}
        if rel is not None:
            console.print(f"relations ({rel['n']}): translation {rel['trans_mean']:.4f} ± {rel['trans_std']:.4f} m, "
                          f"rotation {rel['rot_mean_deg']:.4f} ± {rel['rot_std_deg']:.4f} deg")
            out["relations"] = rel
        if json_out:
            json_out.write_text(json.dumps(out, indent=2) + "\n")

    @app.command("compare")
    def compare_cmd(
        ref: Annotated[Path, typer.Argument(help="Reference trajectory.")],
        est: Annotated[list[Path], typer.Argument(help="Estimated trajectories (TUM/KITTI/CARMEN).")],
        out: Annotated[Path, typer.Option("--out", "-o", help="Report folder.")],
        label: Annotated[list[str] | None, typer.Option(help="Names for the estimates, in order.")] = None,
        align: Annotated[str, typer.Option(help="Alignment: se3, sim3, se2 or none.")] = "se3",
        raw_log: Annotated[Path | None, typer.Option(help="Raw CARMEN log, when REF is a corrected CARMEN log.")] = None,
    ) -> None:
        """Side-by-side report (table + plots) of several trajectories against one reference."""
        from .evaluation.metrics import Alignment
        from .evaluation.report import compare_trajectories
        from .io.trajectory import carmen_reference_trajectory, read_trajectory

        labels = list(label or [])
        if labels and len(labels) != len(est):
            raise fail(SubmapSlamError(f"{len(labels)} labels for {len(est)} trajectories"))
        try:
            Alignment(align)  # an unknown value fails before any file is read
            r = carmen_reference_trajectory(ref, raw_log) if raw_log else read_trajectory(ref)
            named = {(labels[k] if labels else p.stem): read_trajectory(p) for k, p in enumerate(est)}
            report = compare_trajectories(r, named, out, align=align)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        console.print(report.markdown)
        console.print(f"report in {out}")
