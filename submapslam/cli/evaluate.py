"""CLI commands ``eval`` and ``compare``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table

from ..errors import SubmapSlamError
from ._common import Overwrite, console, err_console, fail


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
        derive_relations: Annotated[bool, typer.Option(
            "--derive-relations", help="Relations error on relations derived from REF (pairs close in time and "
            "across loops), for references without a relations file.")] = False,
        scans: Annotated[Path | None, typer.Option(
            help="The log whose scans EST and REF place (e.g. the raw CARMEN log): also the loop-pair misfit of "
            "each, how far those scans part where REF comes back to a place (needs no ground truth).")] = None,
        match_relations: Annotated[bool, typer.Option(
            "--match-relations", help="Measure each relation by matching its two scans of --scans (the benchmark's "
            "method), keep those scan matching fixes, and score REF on them too.")] = False,
    ) -> None:
        """ATE (RMSE) and RPE of EST against REF; with --relations (or --derive-relations) the relations error;
        with --scans the loop-pair misfit of both."""
        from ..api import evaluate_files
        from ..io.output_folder import check_out_file, write_file_atomically

        try:
            if json_out is not None:
                check_out_file(json_out, inputs=[est, ref, relations, raw_log, scans], what="--json")
            figures = evaluate_files(est, ref, align=align, relations=relations, max_diff=max_diff, raw_log=raw_log,
                                     derive_relations=derive_relations, scans=scans, match_relations=match_relations)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        for warning in figures.get("warnings", []):
            err_console.print(f"[yellow]warning:[/yellow] {escape(warning)}", highlight=False, soft_wrap=True)
        a, p, rel = figures["ate"], figures["rpe"], figures["relations"]
        table = Table(title=f"{est.name} vs {ref.name} ({a['n']} poses, align {align})")
        table.add_column("metric")
        for col in ("rmse", "mean", "median", "std", "max"):
            table.add_column(col, justify="right")
        table.add_row("ATE [m]", *(f"{a[k]:.4f}" for k in ("rmse", "mean", "median", "std", "max")))
        table.add_row("RPE trans [m/frame]", *(f"{p[k]:.4f}" for k in ("rmse", "mean", "median", "std", "max")))
        table.add_row("RPE rot [deg/frame]", *(f"{p['rotation_' + k]:.4f}" for k in ("rmse", "mean", "median", "std", "max")))
        console.print(table)
        out = {"ate": {k: v for k, v in a.items() if k not in ("errors", "timestamps")}, "rpe": p,
               "warnings": figures.get("warnings", [])}
        if rel is not None:
            console.print(f"relations ({rel['n']}): translation {rel['trans_mean']:.4f} ± {rel['trans_std']:.4f} m, "
                          f"rotation {rel['rot_mean_deg']:.4f} ± {rel['rot_std_deg']:.4f} deg")
            out["relations"] = rel
            if "relations_matching" in figures:
                c, own = figures["relations_matching"], figures["reference_relations"]
                console.print(f"  measured by scan matching: {c['matched']} of {c['relations']} kept ({c['ambiguous']} "
                              f"ambiguous, {c['poor_fit']} poorly fitting); {ref.name} itself: "
                              f"{own['trans_mean']:.4f} ± {own['trans_std']:.4f} m, "
                              f"{own['rot_mean_deg']:.4f} ± {own['rot_std_deg']:.4f} deg", highlight=False)
                out["relations_matching"], out["reference_relations"] = c, own
        misfit = figures.get("loop_pair_misfit")
        if misfit is not None:
            console.print(f"loop-pair misfit ({misfit['compared']} of {misfit['pairs']} pairs of {scans.name}'s scans "
                          f"compared): median "
                          f"{misfit['estimate_median_m']:.4f} m under {est.name}, {misfit['reference_median_m']:.4f} m "
                          f"under {ref.name}; {misfit['estimate_worse']} / {misfit['reference_worse']} pairs "
                          f"{100 * misfit['margin_m']:.0f} cm worse under each", highlight=False)
            worst = misfit.get("at_worst")
            if worst is not None:
                console.print(f"  of them at {est.name}'s {100 * misfit['worst_share']:.0f} % largest errors "
                              f"({worst['compared']} pairs): median {worst['estimate_median_m']:.4f} m under "
                              f"{est.name}, {worst['reference_median_m']:.4f} m under {ref.name}; "
                              f"{worst['estimate_worse']} / {worst['reference_worse']} pairs worse under each",
                              highlight=False)
            out["loop_pair_misfit"] = misfit
        if json_out:
            try:
                write_file_atomically(json_out, json.dumps(out, indent=2) + "\n")
            except SubmapSlamError as exc:
                raise fail(exc) from None

    @app.command("compare")
    def compare_cmd(
        ref: Annotated[Path, typer.Argument(help="Reference trajectory.")],
        est: Annotated[list[Path], typer.Argument(help="Estimated trajectories (TUM/KITTI/CARMEN).")],
        out: Annotated[Path, typer.Option("--out", "-o", help="Report folder.")],
        label: Annotated[list[str] | None, typer.Option(help="Names for the estimates, in order.")] = None,
        align: Annotated[str, typer.Option(help="Alignment: se3, sim3, se2 or none.")] = "se3",
        raw_log: Annotated[Path | None, typer.Option(help="Raw CARMEN log, when REF is a corrected CARMEN log.")] = None,
        overwrite: Overwrite = False,
    ) -> None:
        """Side-by-side report (table + plots) of several trajectories against one reference."""
        from ..api import compare_files
        from ..io.trajectory_names import trajectory_labels

        labels = list(label or [])
        if labels and len(labels) != len(est):
            raise fail(SubmapSlamError(f"{len(labels)} labels for {len(est)} trajectories"))
        repeated = sorted({x for x in labels if labels.count(x) > 1})
        if repeated:
            raise fail(SubmapSlamError(f"each --label must be unique, repeated: {', '.join(repeated)}"))
        names = labels or trajectory_labels(est)  # runA/poses vs runB/poses: two poses_tum.txt never collide
        try:
            report = compare_files(ref, dict(zip(names, est, strict=True)), out, align=align, raw_log=raw_log,
                                   overwrite=overwrite)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        console.print(report.markdown)
        console.print(f"report in {out}")
