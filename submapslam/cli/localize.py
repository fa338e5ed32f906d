"""CLI command ``localize``: localise a log in a fixed map without changing the map."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from .cli_common import err_console, fail
from .errors import SubmapSlamError


def register(app: typer.Typer) -> None:
    """Add ``localize`` to ``app``."""

    @app.command("localize")
    def localize_cmd(
        log: Annotated[Path, typer.Argument(help="Log to localise (any format `run` reads).")],
        map: Annotated[Path, typer.Option("--map", "-m", help="A `submapslam run` output folder (its map.ply) "
                                          "or a PLY/PCD point cloud, in the world frame.")],
        out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")],
        initial_pose: Annotated[str | None, typer.Option(
            "--initial-pose", help="\"x y yaw\" of the first scan in the map frame (yaw in rad); "
            "default: global search in the whole map (can fail where the map repeats itself).")] = None,
        format: Annotated[str | None, typer.Option("--format", "-f", help="Force the log format.")] = None,
        start: Annotated[int, typer.Option("--start", min=0, help="Skip the first N scans of the log.")] = 0,
        max_scans: Annotated[int | None, typer.Option("--max-scans", min=1, help="Stop after N scans.")] = None,
        min_fitness: Annotated[float, typer.Option(help="Consistency gate: inlier fraction among the scan points "
                                                   "inside the mapped area below which a scan's fit is not "
                                                   "believed (points in unmapped space do not count).")] = 0.75,
        lost_after: Annotated[int, typer.Option(min=1, help="Inconsistent scans in a row before the robot is lost "
                                                "and the global search runs again.")] = 5,
    ) -> None:
        """Localise every scan of LOG in a fixed map; write poses, per-scan fitness and a summary into OUT."""
        from .api import _progress_bar
        from .io.localization_results import write_localization
        from .io.registry import open_log
        from .localization import LocalizationConfig, load_map, localize_log, parse_initial_pose

        try:
            T0 = parse_initial_pose(initial_pose)
            points = load_map(map)
            reader = open_log(log, format)
            try:
                total = max(0, len(reader) - start)  # type: ignore[arg-type]
                total = min(total, max_scans) if max_scans else total
            except TypeError:
                total = None
            cfg = LocalizationConfig(min_fitness=min_fitness, lost_after=lost_after)
            if err_console.is_terminal:
                with _progress_bar(total) as bar:
                    task = bar.add_task("localize", total=total)
                    result = localize_log(reader, points, T0, config=cfg, start=start, max_scans=max_scans,
                                          on_scan=lambda k: bar.update(task, completed=k + 1))
            else:  # no bar: its closing newline would break the one-line error
                result = localize_log(reader, points, T0, config=cfg, start=start, max_scans=max_scans)
            write_localization(result, out, extra={"log": str(log), "map": str(map), "map_points": len(points)})
        except SubmapSlamError as exc:
            raise fail(exc) from None
        except OSError as exc:
            raise fail(f"{getattr(exc, 'filename', '') or out}: {exc.strerror or exc}") from None
        s = result.summary()
        Console().print(f"{s['scans']} scans localised, {s['lost_scans']} lost in {len(s['lost_spans'])} spans, "
                        f"{s['relocalisations']} relocalisations; {s['wall_time_s']:.1f} s ({s['scans_per_s']} scans/s)")
        Console().print(f"results in {out}")
