"""CLI command ``drop-sessions``: a map without some of its sessions."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..errors import SubmapSlamError
from ._common import OutFolder, Overwrite, console, fail


def register(app: typer.Typer) -> None:
    """Add ``drop-sessions`` to ``app``."""

    @app.command("drop-sessions")
    def drop_sessions_cmd(
        map_dir: Annotated[Path, typer.Argument(metavar="MAP", help="A map: a run's output folder (a batch's DIR/merged), or its map/.")],
        names: Annotated[list[str], typer.Argument(metavar="SESSION...", help="Names of the sessions to drop "
                                                    "(the map's sessions.csv lists them).")],
        out: OutFolder,
        overwrite: Overwrite = False,
    ) -> None:
        """Write MAP without the SESSIONs into OUT: the other sessions keep their poses, the map is
        rebuilt from them, and OUT/map/ can be extended again with `run --map`. MAP is only read."""
        from ..fleet_api import drop_sessions_from_map
        from ._sessions import print_sessions

        try:
            kept, _ = drop_sessions_from_map(map_dir, names, out, overwrite=overwrite)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        print_sessions(kept)
        console.print(f"dropped {', '.join(names)}; results in {out} (the map in {out}/map)",
                      highlight=False, markup=False)
