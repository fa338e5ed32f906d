"""CLI command ``clean``: remove what moved from a log, given one pose per scan."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..errors import SubmapSlamError
from ._common import OutFolder, Overwrite, console, fail


def register(app: typer.Typer) -> None:
    """Add ``clean`` to ``app``."""

    @app.command("clean")
    def clean_cmd(
        log: Annotated[Path, typer.Argument(help="Log: folder of scans, CARMEN file, ROS bag (any format run reads).")],
        poses: Annotated[Path, typer.Option("--poses", help="T_world_base per scan, in scan order: TUM or KITTI.")],
        out: OutFolder,
        format: Annotated[str | None, typer.Option("--format", "-f", help="Force the log format.")] = None,
        voxel: Annotated[float, typer.Option(help="Voxel [m] of the evidence and of the output maps (<= 0.1 "
                                                  "keeps the DynamicMap benchmark's resolution).")] = 0.1,
        overwrite: Overwrite = False,
    ) -> None:
        """Split the scans into a static map and what moved (free-space evidence by ray casting):
        OUT/map_static.ply, OUT/map_dynamic.ply and OUT/summary.json, in the frame of POSES
        (`eval-map OUT/map_static.ply LOG` scores them in that frame)."""
        from ..api import clean_log
        from ..mapping.dynamic_removal import RemovalParams

        if voxel <= 0:
            raise fail(f"--voxel must be > 0, not {voxel}")
        try:
            s = clean_log(log, poses, out, format=format, params=RemovalParams(voxel=voxel), progress=True,
                          overwrite=overwrite)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        console.print(f"{s['scans']} scans: {s['points_kept']} points kept, {s['points_removed']} removed "
                      f"({s['voxels_removed']} of {s['voxels_kept'] + s['voxels_removed']} voxels); "
                      f"{s['wall_time_s']:.1f} s, peak {s['peak_memory_mb']:.0f} MiB -> {out}", highlight=False)
        console.print(f"frame: the maps are in the frame of {poses}; `eval-map` scores them there", highlight=False)
