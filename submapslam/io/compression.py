"""Open plain, gzip, bzip2 or xz text files by their suffix."""

from __future__ import annotations

import bz2
import gzip
import lzma
from pathlib import Path
from typing import IO

_OPENERS = {".gz": gzip.open, ".bz2": bz2.open, ".xz": lzma.open}


def open_text(path: str | Path) -> IO[str]:
    """Open ``path`` for reading text, decompressing ``.gz``/``.bz2``/``.xz`` on the fly."""
    path = Path(path)
    opener = _OPENERS.get(path.suffix.lower())
    if opener is None:
        return open(path, encoding="utf-8", errors="replace")
    return opener(path, "rt", encoding="utf-8", errors="replace")


def base_suffix(path: str | Path) -> str:
    """Suffix ignoring a compression suffix: ``intel.clf.bz2`` -> ``.clf``."""
    path = Path(path)
    if path.suffix.lower() in _OPENERS:
        return Path(path.stem).suffix.lower()
    return path.suffix.lower()
