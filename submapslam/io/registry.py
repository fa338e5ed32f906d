"""Log reader registry: format sniffing and ``open_log``.

A reader is a class with ``name``, ``sniff(path) -> bool`` (cheap; looks at the name and a few
bytes) and ``__iter__`` yielding :class:`~submapslam.io.scan.Scan` objects in log order.
``len(reader)`` gives the number of scans when it is cheap to know, else raises TypeError.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Protocol

from ..errors import InputError, UnknownFormatError
from .scan import Scan


class LogReader(Protocol):
    name: str
    path: Path

    def __iter__(self) -> Iterator[Scan]: ...


ReaderFactory = Callable[[Path], LogReader]
_READERS: dict[str, tuple[Callable[[Path], bool], ReaderFactory]] = {}


def register_reader(name: str, sniff: Callable[[Path], bool], factory: ReaderFactory) -> None:
    """Register a reader under ``name``; ``sniff`` decides whether it can read a path."""
    _READERS[name] = (sniff, factory)


def available_formats() -> list[str]:
    _ensure_builtin()
    return sorted(_READERS)


def open_log(path: str | Path, format: str | None = None, **options: object) -> LogReader:
    """Open a log (file or folder) with the reader ``format`` or the first that sniffs it.

    ``options`` go to the reader (e.g. ``topic=`` and ``odometry_topic=`` for ROS bags); options
    that are ``None`` are left out, and one the reader does not take is an :class:`InputError`.
    """
    _ensure_builtin()
    path = Path(path)
    options = {k: v for k, v in options.items() if v is not None}
    if not path.exists():
        raise InputError(path, "no such file or directory")
    _refuse_results_folder(path)
    if format is not None:
        if format not in _READERS:
            raise UnknownFormatError(
                path, f"unknown format {format!r}; known formats: {', '.join(available_formats())}"
            )
        return _make(format, _READERS[format][1], path, options)
    for name, (sniff, factory) in _READERS.items():
        if sniff(path):
            return _make(name, factory, path, options)
    from .cloud_folder import SCAN_SUFFIXES

    if path.is_file() and path.suffix.lower() in SCAN_SUFFIXES:
        raise UnknownFormatError(path, f"is one scan; a log of scans is the folder holding them ({path.parent})")
    raise UnknownFormatError(
        path,
        "cannot tell the log format from the path; use --format with one of: "
        + ", ".join(available_formats()),
    )


def _refuse_results_folder(path: Path) -> None:
    """A folder (or a file in one) that a submapslam command wrote as results is no log: one line
    naming the command (a ``synth`` folder is a log)."""
    from .output_folder import written_by

    folder = path if path.is_dir() else path.parent
    command = written_by(folder)
    if command is None or command == "synth" or (command == "earlier run" and not (folder / "poses_tum.txt").is_file()):
        return
    if command == "demo" and (folder / "log").is_dir():
        raise InputError(path, f"is the demo's folder, not a log; its log is {folder / 'log'}")
    raise InputError(path, f"holds the results of `submapslam {command}`, not a log "
                     "(give the log it was made from; `run LOG --map OUT` adds a log to a run's map)")


def _make(name: str, factory: ReaderFactory, path: Path, options: dict[str, object]) -> LogReader:
    if options:
        import inspect

        accepted = inspect.signature(factory).parameters
        unknown = sorted(k for k in options if k not in accepted)
        if unknown:
            raise InputError(path, f"option {', '.join(unknown)} does not apply to {name} logs")
    return factory(path, **options)  # type: ignore[call-arg]


def _ensure_builtin() -> None:
    from . import carmen, cloud_folder, rosbag  # noqa: F401  (importing registers the readers)
