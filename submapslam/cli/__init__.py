"""Command-line interface: a typer app, one module per command. Each command validates its
input, makes one library call and prints; library errors become one red line and exit code 1.
"""

from __future__ import annotations

import logging
from typing import Annotated

import typer

from .. import __version__
from ..process_stats import one_malloc_arena
from ._common import console

app = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode="rich",
                  help="submapslam: submap-based SLAM for 2D laser and 3D LiDAR logs.")


def _plain_help() -> None:
    """Help text is shown as written: "tolerance [s]" keeps its unit (Typer reads help as rich
    markup, where "[s]" is a tag; the help here uses none, so it is escaped first). The type
    column says ``<path>...`` for a list of paths (not ``<list[Path]>``) and nothing for a flag
    (not ``<bool>``). Typer has no setting for either, so its functions are wrapped."""
    import inspect
    import re

    from rich.markup import escape
    from typer import core, rich_utils

    make_text = getattr(rich_utils, "_make_rich_text", None)
    if make_text is not None and not getattr(make_text, "_escaped", False):
        def make_rich_text(*, text: str, style: str = "", markup_mode):
            if markup_mode == "rich":  # a paragraph's lines join and wrap to the terminal (not lists)
                text = escape(re.sub(r"(?<!\n)\n(?!\n|\s|[-*] )", " ", inspect.cleandoc(text)))
            return make_text(text=text, style=style, markup_mode=markup_mode)
        make_rich_text._escaped = True  # type: ignore[attr-defined]
        rich_utils._make_rich_text = make_rich_text

    def relabel(original):
        def display_type_rich(self, ctx):
            label = original(self, ctx)
            if getattr(self, "is_flag", False) and not getattr(self, "metavar", None):
                return None
            m = re.fullmatch(r"<list\[(\w+)\]>", label or "")
            return f"<{m.group(1).lower()}>..." if m else label
        return display_type_rich

    for cls in (getattr(core, "TyperArgument", None), getattr(core, "TyperOption", None)):
        if cls is not None and hasattr(cls, "display_type_rich") and not getattr(cls, "_relabelled", False):
            cls.display_type_rich = relabel(cls.display_type_rich)
            cls._relabelled = True


_plain_help()


def _version(value: bool) -> None:
    if value:
        console.print(f"submapslam {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="Print the version and exit.")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log progress details.")] = False,
) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")


def _register_commands() -> None:
    from . import (
        batch,
        clean,
        demo,
        drop_sessions,
        dump_config,
        ekf,
        eval_map,
        evaluate,
        localize,
        report,
        run,
        synth,
    )

    for module in (run, dump_config, demo, evaluate, synth, ekf, localize, report, eval_map, clean, batch,
                   drop_sessions):
        module.register(app)


_register_commands()


def main() -> None:
    """Console-script entry point (a process of our own: one malloc arena for all its threads)."""
    one_malloc_arena()
    app()


__all__ = ["app", "main"]
