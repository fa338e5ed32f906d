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


def open_log(path: str | Path, format: str | None = None) -> LogReader:
    """Open a log (file or folder) with the reader ``format`` or the first that sniffs it."""
    _ensure_builtin()
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file or directory")
    if format is not None:
        if format not in _READERS:
            raise UnknownFormatError(
                path, f"unknown format {format!r}; known formats: {', '.join(available_formats())}"
            )
        return _READERS[format][1](path)
    for _name, (sniff, factory) in _READERS.items():
        if sniff(path):
            return factory(path)
    raise UnknownFormatError(
        path,
        "cannot tell the log format from the path; use --format with one of: "
        + ", ".join(available_formats()),
    )


def _ensure_builtin() -> None:
    from . import carmen, cloud_folder, rosbag  # noqa: F401  (importing registers the readers)
