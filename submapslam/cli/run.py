"""CLI command ``run``: build a map and trajectory from a log."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from ..errors import SubmapSlamError
from ._common import OutFolder, console, fail


def register(app: typer.Typer) -> None:
    """Add ``run`` to ``app``."""

    @app.command()
    def run(
        logs: Annotated[list[Path], typer.Argument(
            metavar="LOG...", help="Log: CARMEN file, folder of .bin/.ply/.pcd scans, synthetic log folder, "
            "ROS bag (.bag, ROS 2 folder, .mcap). Several logs: one map from all (one session each).")],
        out: OutFolder,
        map_dir: Annotated[Path | None, typer.Option(
            "--map", help="Add the log(s) as new sessions to this map (a run's output folder).")] = None,
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
        """Build a map and trajectory from LOG; write poses, graph, map and summary into OUT.

        OUT/map/ is the map itself: `run LOG2 --map OUT --out OUT2` adds LOG2 to it."""
        from ..api import run_log

        if len(logs) > 1 or map_dir is not None:
            from ._sessions import run_many

            return run_many(logs, out, map_dir=map_dir, config=config, format=format, hints=hints,
                            max_scans=max_scans, loops=not no_loops,
                            reader_options={"topic": topic, "odometry_topic": odometry_topic, "base_frame": base_frame})
        log = logs[0]
        try:
            result, paths = run_log(log, out, config=config, format=format, hints=hints,
                                    max_scans=max_scans, loops=not no_loops, progress=True,
                                    reader_options={"topic": topic, "odometry_topic": odometry_topic,
                                                    "base_frame": base_frame})
            from ._sessions import save_run_map

            save_run_map(result, log, out)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        # summary.json is written last: its wall time and peak memory include the writing
        s = json.loads(paths["summary.json"].read_text()) if "summary.json" in paths else result.summary()
        console.print(
            f"{s['scans']} scans, {s['submaps']} submaps, {s['loop_candidates_tested']} loop candidates tested, "
            f"{s['loop_closures_accepted']} accepted; {s['wall_time_total_s']:.1f} s, peak {s['peak_memory_mb']:.0f} MiB"
        )
        console.print(f"results in {out}")
        if result.input_error:
            raise fail(f"{result.input_error} (results cover the {s['scans']} scans read before it)")
