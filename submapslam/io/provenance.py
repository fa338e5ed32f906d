"""Where a run's input came from: ``input.json`` (file, size, SHA-256, scans, time span).

A report can then say which log a run was made from, and whether a file of the same name is
still the same file.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

_CHUNK = 1 << 20


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def log_fingerprint(log_path: str | Path) -> dict:
    """What identifies the log at ``log_path``: its path, kind, size and SHA-256.

    A file is hashed whole (SHA-256 of its bytes); a folder (cloud folder, ROS 2 bag) by its
    listing, names and sizes of every file in it (``hash_of: "listing"``), since hashing
    gigabytes of scans would cost more than the run.
    """
    path = Path(log_path)
    doc: dict = {"path": str(path), "absolute_path": str(path.resolve())}
    if path.is_file():
        doc.update(kind="file", size_bytes=path.stat().st_size, sha256=_sha256_file(path), hash_of="content")
    elif path.is_dir():
        files = sorted(p for p in path.rglob("*") if p.is_file())
        listing = "\n".join(f"{p.relative_to(path).as_posix()}\t{p.stat().st_size}" for p in files)
        doc.update(kind="folder", files=len(files), size_bytes=sum(p.stat().st_size for p in files),
                   sha256=hashlib.sha256(listing.encode()).hexdigest(), hash_of="listing")
    return doc


def input_provenance(log_path: str | Path, timestamps: np.ndarray, recorded_as: str | None = None) -> dict:
    """Provenance of the log at ``log_path`` (:func:`log_fingerprint`) and the ``(N,)``
    timestamps of the scans read from it; ``recorded_as``: the path to record instead, when
    ``log_path`` is a copy of that log (its bytes are the same, so is the fingerprint)."""
    doc = log_fingerprint(log_path)
    if recorded_as is not None:
        doc.update(path=recorded_as, absolute_path=recorded_as)
    stamps = np.asarray(timestamps, dtype=np.float64)
    doc["scans"] = int(len(stamps))
    if len(stamps):
        doc.update(first_timestamp=float(stamps[0]), last_timestamp=float(stamps[-1]),
                   duration_s=round(float(stamps[-1] - stamps[0]), 3))
    return doc


def write_provenance(out_dir: str | Path, provenance: dict) -> Path:
    """Write ``input.json`` into ``out_dir``; return its path."""
    path = Path(out_dir) / "input.json"
    path.write_text(json.dumps(provenance, indent=2) + "\n")
    return path
