"""A log or a results folder as bytes, for machines that share no filesystem (``batch`` on a
Ray cluster ships each log to a worker and each log's results back to the driver this way).

A bundle is an uncompressed tar archive (logs are mostly compressed already) holding one file
or one folder under its own name.
"""

from __future__ import annotations

import io
import shutil
import tarfile
import uuid
from pathlib import Path


def pack(path: str | Path) -> bytes:
    """The file or folder at ``path`` as a bundle (its name kept, symbolic links followed)."""
    path = Path(path)
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w", dereference=True) as archive:
        archive.add(path, arcname=path.name)
    return buffer.getvalue()


def unpack(bundle: bytes, into: str | Path) -> Path:
    """Extract ``bundle`` into the folder ``into`` (made if needed); returns the path of the file
    or folder it held. Members that would land outside ``into`` are refused (tar's data filter)."""
    into = Path(into)
    into.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(bundle), mode="r") as archive:
        top = {Path(m.name).parts[0] for m in archive.getmembers()}
        if len(top) != 1:
            raise ValueError(f"a bundle holds one file or folder, this one {len(top)}")
        archive.extractall(into, filter="data")
    return into / top.pop()


def replace_with(bundle: bytes, dest: str | Path) -> Path:
    """Make ``dest`` hold the folder in ``bundle`` (whatever its name there): extracted beside
    ``dest`` first, then swapped in, so ``dest`` is never half written."""
    dest = Path(dest)
    staging = dest.parent / f".{dest.name}.incoming-{uuid.uuid4().hex[:8]}"
    try:
        held = unpack(bundle, staging)
        old = None
        if dest.exists():
            old = dest.parent / f".{dest.name}.old-{uuid.uuid4().hex[:8]}"
            dest.rename(old)
        held.rename(dest)
        if old is not None:
            shutil.rmtree(old)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return dest
