"""A ``batch`` output folder: checked before any work, marked as ``batch``'s, and its record.

``DIR/batch.json`` (the record) holds the batch's settings (a hash of the config, the forced
format, the scan limit) and, per log as it ends, the log's fingerprint (path, size, SHA-256:
:func:`~submapslam.io.provenance.log_fingerprint`) and its outcome. ``batch --resume`` keeps a
log's results when the record says it ended well with the same settings, the log's bytes are
unchanged and its map is in ``DIR/<name>/map/``; it runs the others. The record is rewritten
atomically after each log, so an interrupted or failed batch can be resumed.

Folder rules, as for every command (:mod:`.output_folder`): a folder of the user's is never
written into; an earlier batch's results are replaced only with ``overwrite`` or continued with
``resume``; the results of another command are not mixed with a batch's.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from collections.abc import Iterable
from pathlib import Path

from ..errors import OutputError
from .output_folder import MARKER, check_inputs_apart, write_file_atomically, written_by
from .provenance import log_fingerprint

RECORD = "batch.json"
RECORD_VERSION = 1
MERGED = "merged"


def batch_settings(config_json: str, format: str | None, max_scans: int | None) -> dict:
    """What must match for a log's results to be kept: the config (``config_json``: the config as
    JSON, hashed), the forced format and the scan limit."""
    return {"config_sha256": hashlib.sha256(config_json.encode()).hexdigest(), "format": format,
            "max_scans": max_scans}


def prepare_batch_folder(out: str | Path, names: list[str], settings: dict, *,
                         inputs: Iterable[str | Path | None] = (), overwrite: bool = False,
                         resume: bool = False) -> dict:
    """Check ``out`` before any work and make it ready; return the record to keep up to date
    (with ``resume``, the earlier batch's, its settings replaced by ``settings``; the logs it
    records stay, for :func:`reusable` to judge).

    ``out`` may be new or empty, or hold an earlier batch's results (then ``overwrite`` or
    ``resume`` is needed, unless that batch stopped before any log ended). Each log's folder ``out/<name>`` and ``out/merged`` must not be
    folders of the user's. With ``overwrite`` the earlier results are removed (only folders
    this package wrote) when the new batch starts.
    """
    if overwrite and resume:
        raise OutputError("--overwrite replaces an earlier batch and --resume continues it: give one of them")
    path = Path(out).expanduser()
    check_inputs_apart(path, inputs)
    if path.exists() and not path.is_dir():
        raise OutputError(f"--out {out} is a file, not a folder")
    earlier = None
    if path.is_dir() and any(path.iterdir()):
        writer = written_by(path)
        if writer is None:
            raise OutputError(f"--out {out} is a folder that holds files of yours, not submapslam results: "
                              "choose a new or empty folder")
        if writer != "batch":
            what = "an earlier run" if writer == "earlier run" else f"an earlier `{writer}` command"
            raise OutputError(f"--out {out} holds the results of {what}, not of a batch: choose another folder")
        earlier = read_record(path)
        if not (overwrite or resume) and (earlier["logs"] or (path / MERGED).exists()):
            raise OutputError(f"--out {out} holds the results of an earlier batch: pass --resume to keep the logs "
                              "it finished and run the others, or --overwrite to replace them")
    elif resume:
        raise OutputError(f"--resume: {out} holds no earlier batch to continue")
    for sub in [*names, MERGED]:  # a folder of the user's inside: refused before any work
        _check_subfolder(path, sub)
    if overwrite and earlier is not None:
        for name in [*earlier["logs"], MERGED]:
            if (path / name).is_dir() and written_by(path / name) is not None:
                shutil.rmtree(path / name)
        earlier = None
    try:
        path.mkdir(parents=True, exist_ok=True)
        if not (path / MARKER).is_file():
            write_file_atomically(path / MARKER, json.dumps({"command": "batch"}) + "\n")
    except OSError as exc:
        raise OutputError(f"--out {out}: cannot create it ({exc.strerror or exc})") from None
    record = {"format_version": RECORD_VERSION, "settings": settings,
              "logs": {} if earlier is None else earlier["logs"]}
    if earlier is not None and earlier.get("settings") != settings:
        record["logs"] = {}  # other settings: nothing of the earlier batch can be kept
    write_record(path, record)
    return record


def _check_subfolder(out: Path, sub: str) -> None:
    """``out/sub`` (a log's results, or the merged map) may be absent, empty or ours, never the
    user's."""
    what = "the merged map" if sub == MERGED else f"the results of log {sub}"
    folder = out / sub
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"--out {out}: {folder} is a file where batch writes {what}: choose another folder")
    if folder.is_dir() and any(folder.iterdir()) and written_by(folder) is None:
        raise OutputError(f"--out {out}: {folder} holds files of yours where batch writes {what}: "
                          "choose another folder")


def read_record(out: str | Path) -> dict:
    """The record in ``out`` (an empty one when a batch ended before writing it)."""
    path = Path(out) / RECORD
    if not path.is_file():
        return {"format_version": RECORD_VERSION, "settings": None, "logs": {}}
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise OutputError(f"{path}: not a readable batch record ({exc})") from None
    if not isinstance(record, dict) or record.get("format_version") != RECORD_VERSION \
            or not isinstance(record.get("logs"), dict):
        raise OutputError(f"{path}: a batch record of another format version "
                          f"({record.get('format_version') if isinstance(record, dict) else '?'}, this is "
                          f"{RECORD_VERSION}): run the batch again with --overwrite")
    return record


def write_record(out: str | Path, record: dict) -> Path:
    """Write the record into ``out`` atomically."""
    return write_file_atomically(Path(out) / RECORD, json.dumps(record, indent=1) + "\n")


def recorded_fingerprint(results: str | Path) -> dict:
    """The fingerprint of the log a run's results were made from (its ``input.json``, written by
    the run itself: the log is not read again here); empty when there is none."""
    try:
        doc = json.loads((Path(results) / "input.json").read_text())
    except (OSError, ValueError):
        return {}
    return {k: doc.get(k) for k in ("kind", "size_bytes", "sha256", "hash_of")}


def reusable(record: dict, name: str, log_path: str | Path, out: str | Path) -> dict | None:
    """The recorded outcome of log ``name`` when its results in ``out/<name>`` can be kept: it
    ended well, the log at ``log_path`` is the same now (size and SHA-256), and its map is there.
    None otherwise."""
    entry = record["logs"].get(name)
    if not entry or not entry.get("ok") or not (Path(out) / name / "map" / "manifest.json").is_file():
        return None
    then = entry.get("fingerprint") or {}
    size = then.get("size_bytes")
    if Path(log_path).is_file() and Path(log_path).stat().st_size != size:
        return None  # changed (and not hashed again)
    now = log_fingerprint(log_path)
    return entry if (then.get("sha256"), size) == (now.get("sha256"), now.get("size_bytes")) else None
