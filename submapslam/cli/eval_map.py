"""CLI command ``eval-map``: DynamicMap scores (SA, DA, AA) of a map against a labelled log."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from ..errors import SubmapSlamError
from ._common import console, err_console, fail


def register(app: typer.Typer) -> None:
    """Add ``eval-map`` to ``app``."""

    @app.command("eval-map")
    def eval_map_cmd(
        map_path: Annotated[Path, typer.Argument(metavar="MAP", help="Map to score: a .ply/.pcd cloud (world frame) "
                                                                     "or a map_server .yaml/.pgm grid.")],
        log: Annotated[Path, typer.Argument(help="Labelled log folder (scans/ + labels/NNNNNN.label, SemanticKITTI).")],
        poses: Annotated[Path | None, typer.Option(help="Poses the log's scans are placed at, one per scan (TUM "
                                                        "or KITTI), in the map's frame; default: for a map "
                                                        "`clean` wrote, the poses it was cleaned at, else the "
                                                        "log's groundtruth_tum.txt.")] = None,
        voxel: Annotated[float, typer.Option(help="Ground-truth voxel [m] (grids: their own cell size).")] = 0.1,
        radius: Annotated[float, typer.Option(help="A voxel is kept when the map has a point this close [m].")] = 0.15,
        json_out: Annotated[Path | None, typer.Option("--json", help="Write the scores as JSON.")] = None,
    ) -> None:
        """Static accuracy SA (static voxels kept), dynamic accuracy DA (moving voxels removed) and
        AA = sqrt(SA DA), the DynamicMap benchmark's scores (Zhang et al., ITSC 2023)."""
        from ..api import evaluate_map_file

        if json_out is not None and json_out.exists():
            raise fail(f"{json_out} exists; not overwriting it")
        try:
            s = evaluate_map_file(map_path, log, poses=poses, voxel=voxel, radius=radius)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        console.print(f"{map_path.name}: SA {s['SA']:.4f} ({s['static_kept']}/{s['static_voxels']} static "
                      f"{'cells' if s['grid'] else 'voxels'} kept)  DA {s['DA']:.4f} ({s['dynamic_removed']}/"
                      f"{s['dynamic_voxels']} dynamic removed)  AA {s['AA']:.4f}  "
                      f"[{s['mixed_voxels_not_scored']} mixed not scored, voxel {s['voxel']} m, radius {s['radius']} m]",
                      highlight=False)
        console.print(f"frame: {s['frame']}", highlight=False)
        for w in s["warnings"]:
            err_console.print(f"[yellow]warning:[/yellow] {escape(w)}", highlight=False, soft_wrap=True)
        if json_out is not None:
            json_out.write_text(json.dumps(s, indent=2) + "\n")
