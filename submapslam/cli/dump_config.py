"""CLI command ``dump-config``: print the effective configuration as YAML."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..errors import SubmapSlamError
from ._common import console, fail


def register(app: typer.Typer) -> None:
    """Add ``dump-config`` to ``app``."""

    @app.command("dump-config")
    def dump_config_cmd(
        config: Annotated[Path | None, typer.Option("--config", "-c", help="Validate and print this file's effective config.")] = None,
        comments: Annotated[bool, typer.Option("--comments/--no-comments",
                                               help="Say above each key what it means.")] = True,
    ) -> None:
        """Print the effective configuration (defaults, or a file's values) as YAML, each key with
        a comment saying what it means."""
        from ..config import dump_config, load_config

        try:
            text = dump_config(load_config(config), comments=comments)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        console.print(text, end="", highlight=False, markup=False)
