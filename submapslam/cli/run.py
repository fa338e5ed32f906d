"""CLI command ``run``: build a map and trajectory from a log."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from ..errors import SubmapSlamError
from ._common import Overwrite, console, err_console, fail, next_steps
from ._interrupt import EXIT_INTERRUPTED, quit_now, stop_requests


def register(app: typer.Typer) -> None:
    """Add ``run`` to ``app``."""

    @app.command()
    def run(
        logs: Annotated[list[Path] | None, typer.Argument(
            metavar="LOG...", help="Log: CARMEN file, folder of .bin/.ply/.pcd scans, synthetic log folder, "
            "ROS bag (.bag, ROS 2 folder, .mcap). Several logs: one map from all (one session each). "
            "Not needed with --resume.")] = None,
        out: Annotated[Path | None, typer.Option("--out", "-o", help="Output folder.")] = None,
        map_dir: Annotated[Path | None, typer.Option(
            "--map", help="Add the log(s) as new sessions to this map (a run's output folder).")] = None,
        freeze_map: Annotated[bool, typer.Option(
            "--freeze-map", help="With --map: the map does not move (its poses come out exactly as they "
            "were); the new sessions are placed and optimised against it.")] = False,
        resume: Annotated[Path | None, typer.Option(
            "--resume", help="Continue the interrupted run that writes into this folder, from its checkpoint "
            "(same log, options and config), to the result an uninterrupted run gives.")] = None,
        config: Annotated[Path | None, typer.Option("--config", "-c", help="YAML config (see dump-config).")] = None,
        format: Annotated[str | None, typer.Option("--format", "-f", help="Force the log format.")] = None,
        hints: Annotated[Path | None, typer.Option("--hints", help="Manual loop hints: 'a b' scan indices or timestamps per line.")] = None,
        max_scans: Annotated[int | None, typer.Option("--max-scans", min=1, help="Stop after N scans.")] = None,
        no_loops: Annotated[bool, typer.Option("--no-loops", help="Odometry and submaps only.")] = False,
        topic: Annotated[str | None, typer.Option("--topic", help="ROS bag: the PointCloud2/LaserScan topic to read.")] = None,
        odometry_topic: Annotated[str | None, typer.Option(
            "--odometry-topic", help="ROS bag: the nav_msgs/Odometry topic ('' for none).")] = None,
        base_frame: Annotated[str | None, typer.Option(
            "--base-frame", help="ROS bag: robot frame the points are moved into through /tf_static "
            "(default: the odometry's child_frame_id, else base_link).")] = None,
        overwrite: Overwrite = False,
        laser: Annotated[str | None, typer.Option(
            "--laser", help="CARMEN: the laser record to read: flaser, rlaser, robotlaser1, robotlaser2, "
            "rawlaser1..4 (default: FLASER, else the first kind the log holds).")] = None,
        skip_bad: Annotated[bool, typer.Option(
            "--skip-bad", help="CARMEN logs and scan folders: skip damaged records (scan files) and "
            "count them in summary.json instead of stopping at the first.")] = False,
        view: Annotated[bool, typer.Option("--view", help="Stream the run live to a Rerun viewer (needs rerun-sdk: the view extra).")] = False,
        record: Annotated[Path | None, typer.Option(
            "--record", help="Save the live view as a Rerun .rrd recording (works headless).")] = None,
    ) -> None:
        """Build a map and trajectory from LOG; write poses, graph, map and summary into OUT.

        OUT is checked before the log is read; the files appear in OUT only when all are written.
        OUT/map/ is the map itself: `run LOG2 --map OUT --out OUT2` adds LOG2 to it.
        Ctrl-C (or SIGTERM) stops after the current scan and still writes a complete result
        marked "interrupted" in summary.json; a second Ctrl-C quits at once.
        """
        from ..api import run_log
        from ._live_view import open_live_view

        logs = list(logs or [])
        if resume is not None:
            if out is not None and out.resolve() != resume.resolve():
                raise fail(f"--resume {resume} continues the run that writes into {resume}; --out {out} differs")
            given = [name for name, value in (("LOG", logs or None), ("--map", map_dir), ("--config", config),
                                              ("--hints", hints), ("--max-scans", max_scans), ("--format", format))
                     if value is not None]
            given += [flag for flag, on in (("--no-loops", no_loops), ("--freeze-map", freeze_map)) if on]
            if given:
                raise fail(f"{', '.join(given)} cannot change a resumed run: "
                           "it continues with the options it was started with")
            out = resume
        elif out is None:
            raise fail("--out is needed: the folder the results go into")
        elif not logs:
            raise fail("LOG is needed (or --resume OUT to continue an interrupted run)")
        if len(logs) > 1 or map_dir is not None or freeze_map:  # the sessions' path (it checks --freeze-map)
            from ._sessions import run_many

            return run_many(logs, out, map_dir=map_dir, freeze_map=freeze_map, config=config, format=format, hints=hints,
                            max_scans=max_scans, loops=not no_loops, overwrite=overwrite,
                            reader_options={"topic": topic, "odometry_topic": odometry_topic, "base_frame": base_frame,
                                            "laser": laser, "skip_bad": True if skip_bad else None})
        log = logs[0] if logs else None
        try:
            observer = open_live_view(view, record)
            try:
                with stop_requests("the run") as stop:
                    result, paths = run_log(log, out, config=config, format=format, hints=hints,
                                            max_scans=max_scans, loops=not no_loops, progress=True,
                                            reader_options={"topic": topic, "odometry_topic": odometry_topic,
                                                            "base_frame": base_frame, "laser": laser,
                                                            "skip_bad": True if skip_bad else None},
                                            overwrite=overwrite, stop=stop, resume=resume is not None,
                                            observer=observer)
            finally:
                if observer is not None:
                    observer.close()
        except SubmapSlamError as exc:
            raise fail(exc) from None
        except KeyboardInterrupt:
            quit_now(f"nothing written to {out}")
        if record is not None:
            console.print(f"live view recorded in {record} (open it with: rerun {record})")
        # summary.json is written last: its wall time and peak memory include the writing
        s = json.loads(paths["summary.json"].read_text()) if "summary.json" in paths else result.summary()
        console.print(
            f"{s['scans']} scans, {s['submaps']} submaps, {s['loop_candidates_tested']} loop candidates tested, "
            f"{s['loop_closures_accepted']} accepted; {s['wall_time_total_s']:.1f} s, peak {s['peak_memory_mb']:.0f} MiB"
        )
        consistency = s.get("consistency") or {}
        if consistency.get("disagrees_with_odometry"):
            err_console.print(f"[yellow]warning:[/yellow] {escape(consistency['message'])}", highlight=False,
                              soft_wrap=True)
        for problem in result.input_warnings:
            err_console.print(f"[yellow]warning:[/yellow] {escape(problem)}", highlight=False, soft_wrap=True)
        for problem in result.hint_problems:  # shown without -v: the user asked for these loops
            err_console.print(f"[yellow]warning:[/yellow] {escape(problem)}", highlight=False, soft_wrap=True)
        if s.get("skipped_records"):
            lines, files = s.get("skipped_record_lines", []), s.get("skipped_files", [])
            where = f"line(s) {', '.join(map(str, lines[:5]))}" if lines else f"{', '.join(files[:5])}"
            console.print(f"skipped {s['skipped_records']} damaged record(s): {where}"
                          f"{' ...' if s['skipped_records'] > 5 else ''}")
        for line in next_steps(out, paths):
            console.print(line)
        if result.failure:
            raise fail(f"{result.failure} (results cover the first {s['scans']} scans)")
        if result.interrupted:
            console.print(f"interrupted: the results cover the first {s['scans']} scans of the log; "
                          f"`submapslam run --resume {out}` continues the run")
            raise typer.Exit(EXIT_INTERRUPTED)
        if result.input_error:
            more = "" if skip_bad else "; --skip-bad skips damaged records"
            raise fail(f"{result.input_error} (results cover the {s['scans']} scans read before it{more})")
