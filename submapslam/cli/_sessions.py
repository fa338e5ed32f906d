"""The multi-session half of ``run``: several logs, or logs added to a map (``--map``)."""

from __future__ import annotations

from pathlib import Path

from rich.markup import escape

from ..errors import SubmapSlamError
from ._common import console, fail, plural


def print_sessions(session_map) -> None:
    """One line per session: placed (and by how many links) or kept in its own frame."""
    r = session_map.result
    for s in session_map.sessions:
        state = ("[green]placed[/green]" if s.placed else "[yellow]NOT placed[/yellow] (kept in its own frame)")
        console.print(f"session {escape(s.name)}: {s.scan_end - s.scan_start} scans, {s.submap_end - s.submap_start} "
                      f"submaps, {state}: {escape(s.note)}", highlight=False, markup=True)
    unplaced = [s.name for s in session_map.sessions if not s.placed]
    if unplaced:
        console.print(f"[yellow]{len(unplaced)} session(s) not placed in the map frame: {', '.join(unplaced)}; "
                      "poses_tum.txt and the map hold the placed sessions only[/yellow]", highlight=False, markup=True)
    console.print(f"{plural(r.n_scans, 'scan')} in {plural(session_map.n_sessions, 'session')}, "
                  f"{plural(r.n_submaps, 'submap')}", highlight=False)


def print_held(held: list) -> None:
    """The line saying that ``held`` (the map's own sessions) kept their poses (``--freeze-map``)."""
    if held:
        console.print(f"the map's {len(held)} session(s) kept their poses (--freeze-map): "
                      f"{', '.join(escape(s.name) for s in held)}", highlight=False)


def run_many(logs: list[Path], out: Path, *, map_dir: Path | None, freeze_map: bool = False, **options) -> None:
    """``run LOG1 LOG2 … [--map MAP [--freeze-map]]``: one map from every log, written into ``out``."""
    from ..fleet_api import run_sessions

    try:
        merged, _ = run_sessions(logs, out, map_dir=map_dir, freeze_map=freeze_map, progress=True, **options)
    except SubmapSlamError as exc:
        raise fail(exc) from None
    print_sessions(merged)
    if freeze_map:
        print_held(merged.sessions[:len(merged.sessions) - len(logs)])  # each log added one session
    console.print(f"results in {out} (per session: poses_tum_<session>.txt; sessions.csv; the map in {out}/map)")
    console.print(f"next: submapslam report {out}   (one HTML page: map, trajectory, loops, errors)")
