"""CLI command ``batch``: many logs, each log's front end a Ray task, then one merged map."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from ..errors import SubmapSlamError
from ._common import OutFolder, console, err_console, fail
from ._interrupt import EXIT_INTERRUPTED


def live_progress():
    """A rich progress view, a row per running log (scans done; of how many when the reader
    knows). On the results' console, so that the lines printed meanwhile stay above it;
    transient, and quiet when that is not a terminal."""
    from rich.progress import (
        BarColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from ..progress import CountColumn

    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), CountColumn(), TextColumn("scans"),
                    TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(), console=console, transient=True)


def register(app: typer.Typer) -> None:
    """Add ``batch`` to ``app``."""

    @app.command()
    def batch(
        logs: Annotated[list[Path], typer.Argument(metavar="LOG...", help="Logs (any format `run` reads).")],
        out: OutFolder,
        address: Annotated[str | None, typer.Option(
            "--address", help="A Ray cluster: the head's HOST:PORT (as `ray start --head` printed it) or "
                              "ray://HOST:10001 (Ray Client). Default: a local Ray instance. A cluster with "
                              "token authentication is joined with RAY_AUTH_TOKEN, RAY_AUTH_TOKEN_PATH or "
                              "~/.ray/auth_token.")] = None,
        ship_logs: Annotated[str, typer.Option(
            "--ship-logs", help="auto, always or never: send each log through Ray's object store and its "
                                "results back here, for clusters without a shared filesystem (auto: when some "
                                "node does not see the logs or OUT).")] = "auto",
        verbose: Annotated[bool, typer.Option("--verbose", help="Show Ray's own start-up output.")] = False,
        no_ray: Annotated[bool, typer.Option("--no-ray", help="Run the logs one after another in this process.")] = False,
        config: Annotated[Path | None, typer.Option("--config", "-c", help="YAML config (see dump-config).")] = None,
        format: Annotated[str | None, typer.Option("--format", "-f", help="Force the log format.")] = None,
        max_scans: Annotated[int | None, typer.Option("--max-scans", help="Stop each log after N scans.")] = None,
        num_cpus: Annotated[int | None, typer.Option("--num-cpus", help="CPUs of the local Ray instance.")] = None,
        cpus_per_log: Annotated[float, typer.Option(
            "--cpus-per-log", help="CPUs each log's task asks Ray for (a 3D log keeps about 1.6 busy).")] = 1.0,
        overwrite: Annotated[bool, typer.Option(
            "--overwrite", help="Replace an earlier batch's results in OUT.")] = False,
        resume: Annotated[bool, typer.Option(
            "--resume", help="Continue the batch in OUT: keep each log it finished (same log bytes and "
                             "settings), run the others (failed, new, changed), merge them all again.")] = False,
        map_dir: Annotated[Path | None, typer.Option(
            "--map", help="Add the logs to this map (a run's output folder or a map/ folder) instead of "
                          "starting a new one.")] = None,
        freeze_map: Annotated[bool, typer.Option(
            "--freeze-map", help="With --map: the map does not move (its poses come out exactly as they were).")] = False,
    ) -> None:
        """Run every LOG (a Ray task each; without Ray one after another), then merge them into one map.

        Each log's results go to OUT/<log name without extensions>/, the merged map to OUT/merged/
        (with --map: that map and the logs), and OUT/batch.json records each log as it ends (what
        --resume reads)."""
        from rich.table import Table

        from ..fleet_api import batch_logs

        missing = [str(p) for p in logs if not p.exists()]
        if missing:
            raise fail(f"no such log: {', '.join(missing)}")

        with live_progress() as view:  # a row per log: scans done as it runs (on a terminal)
            rows: dict[str, int] = {}

            def row(name: str) -> int:
                if name not in rows:
                    rows[name] = view.add_task(name, total=None)
                return rows[name]

            def running(o, scans: int, total: int | None) -> None:
                view.update(row(o.name), completed=scans, total=total)

            def done(o) -> None:
                view.update(row(o.name), visible=False)
                if o.kept:
                    console.print(f"[green]kept[/green] {o.name}: {o.scans} scans, {o.submaps} submaps, "
                                  f"{o.loops_accepted} loops (from the earlier batch)", highlight=False, markup=True)
                elif o.ok:
                    console.print(f"[green]done[/green] {o.name}: {o.scans} scans, {o.submaps} submaps, "
                                  f"{o.loops_accepted} loops, {o.seconds:.1f} s", highlight=False, markup=True)
                else:
                    console.print(f"[red]failed[/red] {escape(o.name)}: {escape(o.error)}", highlight=False, markup=True)

            def merged(o) -> None:
                console.print(f"[cyan]merged[/cyan] {escape(o.name)}: {escape(o.note)}", highlight=False, markup=True)

            try:
                report = batch_logs(logs, out, address=address, use_ray=False if no_ray else None, config=config,
                                    format=format, max_scans=max_scans, on_done=done, num_cpus=num_cpus,
                                    cpus_per_log=cpus_per_log, overwrite=overwrite, resume=resume,
                                    map_dir=map_dir, freeze_map=freeze_map, on_progress=running, on_merged=merged,
                                    ship_logs=ship_logs, verbose=verbose)
            except SubmapSlamError as exc:
                raise fail(exc) from None
            except KeyboardInterrupt:
                err_console.print(f"[red]interrupted:[/red] the logs finished so far are kept in {escape(str(out))} "
                                  "(batch.json); the same command with --resume runs the others and merges",
                                  highlight=False, soft_wrap=True)
                raise typer.Exit(EXIT_INTERRUPTED) from None
        table = Table(title=f"batch: {len(logs)} logs ({report.executor}), {report.wall_time_s:.1f} s "
                            f"(front ends {report.front_end_s:.1f} s, merge and writing the rest)")
        for col in ("log", "status", "scans", "submaps", "loops", "seconds", "merged", "results"):
            table.add_column(col)
        for o in report.logs:
            merged = "-" if o.placed is None else ("placed" if o.placed else "own frame")
            table.add_row(o.name, ("kept" if o.kept else "ok") if o.ok else f"failed: {o.error}", str(o.scans), str(o.submaps),
                          str(o.loops_accepted), f"{o.seconds:.1f}", merged, str(Path(out) / o.name))
        console.print(table)
        if report.merged_dir is not None:
            if freeze_map:
                from ._sessions import print_held

                ours = {o.name for o in report.logs}
                print_held([s for s in report.merged.sessions if s.name not in ours])  # the map's own sessions
            console.print(f"merged map in {report.merged_dir}")
        failed = [o.name for o in report.logs if not o.ok]
        if failed:
            raise fail(f"{len(failed)} of {len(logs)} logs failed: {', '.join(failed)} (the others are kept)")
