"""Open plain, gzip, bzip2 or xz text files by their suffix."""

from __future__ import annotations

import bz2
import gzip
import io
import lzma
import queue
import threading
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


def open_text_prefetched(path: str | Path, chunk: int = 1 << 20) -> IO[str]:
    """:func:`open_text`, with a compressed file decompressed ahead in a background thread.

    Decompression (zlib, bz2, lzma) releases the GIL, so on a second core it overlaps with the
    caller's work on the lines. The text is the same; a read error (truncated or damaged
    archive) is raised where the caller reaches it, after the text decoded before it.
    """
    path = Path(path)
    opener = _OPENERS.get(path.suffix.lower())
    if opener is None:
        return open_text(path)
    raw = _PrefetchedStream(opener(path, "rb"), chunk)
    return io.TextIOWrapper(io.BufferedReader(raw), encoding="utf-8", errors="replace")


class _PrefetchedStream(io.RawIOBase):
    """Binary stream fed by a thread that reads ``chunk`` bytes at a time from ``source``."""

    def __init__(self, source: IO[bytes], chunk: int, depth: int = 8) -> None:
        self._source = source
        self._chunk = chunk
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._pending = memoryview(b"")
        self._done = False
        self._thread = threading.Thread(target=self._fill, name="decompress", daemon=True)
        self._thread.start()

    def _fill(self) -> None:
        try:
            # read1: one decompression step at a time, so the text before a damaged part
            # still arrives before the error
            read = getattr(self._source, "read1", self._source.read)
            while not self._stop.is_set():
                data = read(self._chunk)
                self._put(data)
                if not data:
                    return
        except BaseException as exc:  # handed to the reader, raised where it gets there
            self._put(exc)

    def _put(self, item) -> None:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        while not self._pending:
            if self._done:
                return 0
            item = self._queue.get()
            if isinstance(item, BaseException):
                self._done = True
                raise item
            if not item:
                self._done = True
                return 0
            self._pending = memoryview(item)
        n = min(len(buffer), len(self._pending))
        buffer[:n] = self._pending[:n]
        self._pending = self._pending[n:]
        return n

    def close(self) -> None:
        if not self.closed:
            self._stop.set()
            self._thread.join()
            self._source.close()
        super().close()


def base_suffix(path: str | Path) -> str:
    """Suffix ignoring a compression suffix: ``intel.clf.bz2`` -> ``.clf``."""
    path = Path(path)
    if path.suffix.lower() in _OPENERS:
        return Path(path.stem).suffix.lower()
    return path.suffix.lower()
