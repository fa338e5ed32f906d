"""CLI command ``localize``: localise a log in a fixed map without changing the map."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..errors import SubmapSlamError
from ._common import OutFolder, Overwrite, console, err_console, fail


def register(app: typer.Typer) -> None:
    """Add ``localize`` to ``app``."""

    @app.command("localize")
    def localize_cmd(
        log: Annotated[Path, typer.Argument(help="Log to localise (any format `run` reads).")],
        map: Annotated[Path, typer.Option("--map", "-m", help="A `submapslam run` output folder (its map.ply) "
                                          "or a PLY/PCD point cloud, in the world frame.")],
        out: OutFolder,
        initial_pose: Annotated[str | None, typer.Option(
            "--initial-pose", help="\"x y yaw\" of the first scan in the map frame (yaw in rad); "
            "default: global search in the whole map (can fail where the map repeats itself).")] = None,
        format: Annotated[str | None, typer.Option("--format", "-f", help="Force the log format.")] = None,
        start: Annotated[int, typer.Option("--start", min=0, help="Skip the first N scans of the log.")] = 0,
        max_scans: Annotated[int | None, typer.Option("--max-scans", min=1, help="Stop after N scans.")] = None,
        min_fitness: Annotated[float | None, typer.Option(
            help="Consistency gate: inlier fraction among the scan points inside the mapped area below which a "
            "scan's fit is not believed (points in unmapped space do not count) [default: 0.75, or the "
            "config's localization.min_fitness].")] = None,
        lost_after: Annotated[int | None, typer.Option(
            min=1, help="Inconsistent scans in a row before the robot is lost and the global search runs again "
            "[default: 5, or the config's localization.lost_after].")] = None,
        config: Annotated[Path | None, typer.Option(
            "--config", "-c", help="YAML config: its localization section (see dump-config).")] = None,
        overwrite: Overwrite = False,
    ) -> None:
        """Localise every scan of LOG in a fixed map; write poses, per-scan fitness and a summary into OUT."""
        from ..api import localize_to_folder
        from ..config import load_config, with_overrides

        try:
            cfg = with_overrides(load_config(config).localization, "localize options",
                                 min_fitness=min_fitness, lost_after=lost_after)
            # a bar only on a terminal: its closing newline would break the one-line error
            result, _ = localize_to_folder(log, map, out, initial_pose=initial_pose, format=format, start=start,
                                           max_scans=max_scans, config=cfg, progress=err_console.is_terminal,
                                           overwrite=overwrite)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        except OSError as exc:
            raise fail(f"{getattr(exc, 'filename', '') or out}: {exc.strerror or exc}") from None
        s = result.summary()
        console.print(f"{s['scans']} scans, {s['lost_scans']} lost in {len(s['lost_spans'])} spans, "
                      f"{s['relocalisations']} relocalisations, {s['consistent_fraction']:.0%} consistent with the "
                      f"map; {s['wall_time_s']:.1f} s ({s['scans_per_s']} scans/s)")
        if "sigma_position_m" in s:
            console.print(f"1σ position {s['sigma_position_m']['median']:.3f} m median, {s['sigma_position_m']['max']:.3f} "
                          f"m largest; yaw {s['sigma_yaw_deg']['median']:.2f} deg median, "
                          f"{s['sigma_yaw_deg']['max']:.2f} deg largest (poses_cov.txt, uncertainty.png)")
        console.print(f"results in {out}")
        if not result.localised:
            found = "never found in the map" if s["initialised_at_scan"] < 0 else "found, but the map explains too few"
            raise fail(f"{log} was not localised in {map}: {found} ({s['consistent_fraction']:.0%} of the scans "
                       f"consistent, {cfg.min_consistent_fraction:.0%} needed); a log of another place, or give "
                       "--initial-pose")
