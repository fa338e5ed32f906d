"""Output safety, one mechanism for every command that writes files.

An output folder (``--out``) is checked before any work: creatable and writable, not a file,
not an input of the run, not a folder of the user's, and holding an earlier result only when
the user said ``--overwrite``. The files are then written into a staging folder beside it
(``.NAME.partial-PID``) that is swapped in when everything is written, so a failed or
interrupted write never leaves a mix of old and new files, and an earlier good result survives
a failing re-run. Every folder written this way carries a marker file (:data:`MARKER`) naming
the command that wrote it: that is how a results folder is told from a folder of the user's.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from ..errors import OutputError

MARKER = ".submapslam-output"
"""File in every output folder: ``{"command": ..., "version": ...}`` (JSON)."""

_LEGACY_RESULT_FILES = ("summary.json", "report.json", "nees.json", "demo_report.json")
"""Files that mark a results folder written before the marker existed."""


def _resolved(path: str | Path) -> Path:
    return Path(path).expanduser().resolve()


def _is_within(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def check_inputs_apart(out: str | Path, inputs: Iterable[str | Path | None], what: str = "--out") -> None:
    """Refuse an output that is an input, lies inside an input folder, or contains an input
    (swapping it in would delete the input). ``inputs``: logs, maps, configs, trajectories."""
    target = _resolved(out)
    for given in inputs:
        if given is None:
            continue
        source = _resolved(given)
        if _is_within(target, source) or _is_within(source, target):
            how = "is" if target == source else ("is inside" if _is_within(target, source) else "contains")
            raise OutputError(f"{what} {out} {how} the input {given}: choose a folder apart from the inputs")


def _writable_parent(out: Path, what: str) -> None:
    """The nearest existing ancestor of ``out`` must be a folder we can write into."""
    parent = out.parent
    while not parent.exists():
        if parent == parent.parent:
            break
        parent = parent.parent
    if not parent.is_dir():
        raise OutputError(f"{what} {out}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{what} {out}: no permission to write in {parent}")


def written_by(folder: str | Path) -> str | None:
    """The command that wrote the results in ``folder`` (``"run"``, ...), ``"earlier run"`` for a
    results folder from before the marker existed, or None when it holds no results of ours."""
    folder = Path(folder)
    marker = folder / MARKER
    if marker.is_file():
        try:
            return str(json.loads(marker.read_text()).get("command", "submapslam"))
        except (OSError, ValueError, AttributeError):
            return "submapslam"
    if any((folder / name).is_file() for name in _LEGACY_RESULT_FILES):
        return "earlier run"
    return None


def check_out_folder(out: str | Path, *, inputs: Iterable[str | Path | None] = (), overwrite: bool = False,
                     what: str = "--out") -> None:
    """Raise :class:`~submapslam.errors.OutputError` (one line) unless ``out`` can take a new
    result: it does not exist yet (its parent is creatable and writable), or it is an empty folder,
    or it holds an earlier result of ours and ``overwrite`` is set. Nothing is created here."""
    path = Path(out).expanduser()
    check_inputs_apart(path, inputs, what)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{what} {out} is a file, not a folder")
    if path.is_dir():
        if not any(path.iterdir()):
            _writable_parent(path, what)
            return
        writer = written_by(path)
        if writer is None:
            raise OutputError(f"{what} {out} is a folder that holds files of yours, not submapslam results: "
                              "choose a new or empty folder")
        if not overwrite:
            earlier = "an earlier run" if writer == "earlier run" else f"an earlier `{writer}` command"
            raise OutputError(f"{what} {out} holds the results of {earlier}: pass --overwrite to replace them, "
                              "or choose another folder")
    _writable_parent(path, what)


def check_out_file(out: str | Path, *, inputs: Iterable[str | Path | None] = (), what: str = "--out") -> None:
    """Raise :class:`OutputError` unless the file ``out`` can be written: not a folder, not an
    input, its folder creatable and writable. An existing file is replaced atomically."""
    path = Path(out).expanduser()
    check_inputs_apart(path, inputs, what)
    if path.is_dir():
        raise OutputError(f"{what} {out} is a folder, not a file")
    _writable_parent(path, what)


def write_file_atomically(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` through a temporary file in the same folder (``os.replace``):
    readers see the old content or the new, never half of it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OutputError(f"{path}: cannot write ({exc.strerror or exc})") from None
    return path


@contextmanager
def staged_folder(out: str | Path, command: str, *, overwrite: bool = False,
                  inputs: Iterable[str | Path | None] = ()) -> Iterator[Path]:
    """Check ``out`` (:func:`check_out_folder`), yield a fresh staging folder beside it to write
    into, and on a clean exit swap it in as ``out`` (with the :data:`MARKER`). On an exception
    the staging folder is removed and ``out`` is left exactly as it was."""
    out = Path(out).expanduser()
    inputs = list(inputs)
    check_out_folder(out, inputs=inputs, overwrite=overwrite)
    staging = out.with_name(f".{out.name}.partial-{os.getpid()}")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir()
    except OSError as exc:
        raise OutputError(f"--out {out}: cannot create it ({exc.strerror or exc})") from None
    try:
        yield staging
        (staging / MARKER).write_text(json.dumps({"command": command, "version": _version()}) + "\n")
        _swap_in(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise


def _version() -> str:
    """The installed submapslam's version (the package facade is a layer above ``io``)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("submapslam")
    except PackageNotFoundError:
        return "unknown"


def _swap_in(staging: Path, out: Path) -> None:
    """Replace ``out`` by ``staging`` with two renames (the old folder is removed afterwards)."""
    old = None
    if out.exists():
        old = out.with_name(f".{out.name}.old-{os.getpid()}")
        shutil.rmtree(old, ignore_errors=True)
        os.rename(out, old)
    try:
        os.rename(staging, out)
    except OSError:
        if old is not None:
            os.rename(old, out)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
