"""``run --view`` / ``--record``: the options checked, the Rerun observer made (lazily)."""

from __future__ import annotations

from pathlib import Path

from ..errors import ConfigError

_RRD_MAGIC = b"RRF"


def open_live_view(view: bool, record: Path | None):
    """A :class:`~submapslam.viz.rerun_view.RerunView` for ``--view`` (spawn a viewer) and/or
    ``--record FILE`` (an ``.rrd``), or None for neither. A ``--record`` file must end in
    ``.rrd``; an existing file is replaced only when it is a Rerun recording."""
    if not view and record is None:
        return None
    if view and _headless():  # the viewer would die printing its windowing errors: say it in one line
        raise ConfigError("--view needs a display (no DISPLAY or WAYLAND_DISPLAY here); use --record FILE.rrd "
                          "and open it with `rerun FILE.rrd` where there is one")
    if record is not None:
        if record.suffix != ".rrd":
            raise ConfigError(f"--record {record}: the recording file must end in .rrd")
        if record.is_dir():
            raise ConfigError(f"--record {record}: is a folder, give the .rrd file to write")
        if record.exists():
            with open(record, "rb") as fh:
                if not fh.read(len(_RRD_MAGIC)) == _RRD_MAGIC:
                    raise ConfigError(f"--record {record}: exists and is not a Rerun recording; not overwriting it")
        if not record.parent.is_dir():
            raise ConfigError(f"--record {record}: no such folder {record.parent}")
    from ..viz.rerun_view import RerunView

    return RerunView(spawn=view, record=record)


def _headless() -> bool:
    """Linux (or another X11/Wayland system) without a display to open a window on."""
    import os
    import sys

    if sys.platform in ("darwin", "win32"):
        return False
    return not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
