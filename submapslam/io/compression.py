"""Open plain, gzip, bzip2 or xz text files by their suffix."""

from __future__ import annotations

import bz2
import gzip
import io
import lzma
import queue
import threading
import zlib
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


def count_line_starts(path: str | Path, prefix: bytes, sample_bytes: int = 2 << 20) -> tuple[int, bool]:
    """How many lines of ``path`` start with ``prefix``: ``(count, exact)``.

    A plain file is counted exactly (a byte scan, no parsing). A compressed one is counted in its
    first ``sample_bytes`` of text and scaled by the compressed bytes that text took (measured
    from the first text out, so the decompressor's look-ahead cancels): an estimate, ``exact``
    False, unless the sample is the whole file. Unreadable files count what was read.
    """
    path = Path(path)
    opener = _OPENERS.get(path.suffix.lower())
    needle = b"\n" + prefix
    count, tail, text = 0, b"\n", 0
    first: tuple[int, int, int] | None = None  # (compressed offset, text, count) after the first chunk
    try:
        with open(path, "rb") as raw:
            stream = raw if opener is None else opener(raw, "rb")
            while True:
                data = stream.read(1 << 16)
                if not data:
                    return count, True
                block = tail + data
                count += block.count(needle)
                tail = block[-len(needle) + 1:]
                text += len(data)
                if opener is None:
                    continue
                if first is None:
                    first = (raw.tell(), text, count)
                elif text >= sample_bytes and raw.tell() > first[0]:
                    c0, t0, n0 = first
                    per_byte = (count - n0) / (raw.tell() - c0)  # records per compressed byte
                    rest = path.stat().st_size - raw.tell()
                    return count + round(per_byte * rest), False
    except (OSError, EOFError, lzma.LZMAError, zlib.error, gzip.BadGzipFile, ValueError):
        return count, False
