"""Closed submaps' grid scans (and 3D clouds) kept on disk instead of in memory, read back when
the grid is built (a loop test or the end reads a cloud).

A run keeps every scan's grid points (a 2D laser's whole scan, a 3D scan's obstacle slice) until
the final occupancy grid traces them: on a long log that is the part of the resident set that
grows with its length (Intel: ~70 MiB over 13,631 scans). :class:`ScanSpill` appends them to an
anonymous temporary file (deleted when the last reference goes, also after a crash) and hands
back a :class:`SpilledScans`, a read-only sequence that reads them back on access: the same
dtypes, shapes and bytes, so everything traced from them is the same to the bit. A 3D
submap's cloud (float16, ~15 MB/km of drive) goes the same way
(:meth:`~submapslam.submaps.Submap.keep_points_elsewhere`); a read comes from the page cache, not
this process's resident set.
"""

from __future__ import annotations

import os
import tempfile
import threading
from collections.abc import Iterator, Sequence

import numpy as np


class ScanSpill:
    """An append-only temporary file of arrays (``directory``: where; default the system's)."""

    def __init__(self, directory: str | None = None) -> None:
        self._file = tempfile.TemporaryFile(prefix="submapslam-scans-", dir=directory)
        self._end = 0
        self._lock = threading.Lock()

    def put(self, arrays: Sequence[np.ndarray]) -> SpilledScans:
        """Write ``arrays`` (each C-contiguous after the copy numpy makes if needed) in one block;
        the sequence that reads them back."""
        arrays = [np.ascontiguousarray(a) for a in arrays]
        sizes = np.array([a.nbytes for a in arrays], dtype=np.int64)
        blob = b"".join(a.tobytes() for a in arrays)
        with self._lock:
            start = self._end
            self._end += len(blob)
        view = memoryview(blob)
        done = 0
        while done < len(blob):  # pwrite may write less than asked
            done += os.pwrite(self._file.fileno(), view[done:], start + done)
        offsets = start + np.concatenate([[0], np.cumsum(sizes)[:-1]]) if len(arrays) else np.zeros(0, np.int64)
        return SpilledScans(self, offsets, sizes, [a.shape for a in arrays], [a.dtype for a in arrays])

    def read(self, offset: int, nbytes: int) -> bytearray:
        """``nbytes`` bytes from ``offset``."""
        out = bytearray(nbytes)
        view = memoryview(out)
        done = 0
        while done < nbytes:
            got = os.preadv(self._file.fileno(), [view[done:]], offset + done)
            if got <= 0:
                raise OSError(f"scan spill file ended at {offset + done} of {offset + nbytes}")
            done += got
        return out

    @property
    def nbytes(self) -> int:
        """Bytes written so far."""
        return self._end


class SpilledScans(Sequence):
    """One submap's scans as written by :meth:`ScanSpill.put`: ``len``, indexing (a fresh array a
    time) and iteration (one read for them all). Pickles as a plain list of the arrays."""

    def __init__(self, spill: ScanSpill, offsets: np.ndarray, sizes: np.ndarray, shapes: list[tuple],
                 dtypes: list[np.dtype]) -> None:
        self._spill = spill
        self._offsets, self._sizes = offsets, sizes
        self._shapes, self._dtypes = shapes, dtypes

    def __len__(self) -> int:
        return len(self._sizes)

    def lengths(self) -> list[int]:
        """Each scan's number of rows (its array's first dimension), without reading the file."""
        return [int(shape[0]) for shape in self._shapes]

    def _array(self, buffer, k: int) -> np.ndarray:
        return np.frombuffer(buffer, dtype=self._dtypes[k], count=int(np.prod(self._shapes[k]))).reshape(self._shapes[k])

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        k = range(len(self))[k]  # negative indices; IndexError beyond
        return self._array(self._spill.read(int(self._offsets[k]), int(self._sizes[k])), k)

    def __iter__(self) -> Iterator[np.ndarray]:
        if not len(self):
            return
        start = int(self._offsets[0])
        block = memoryview(self._spill.read(start, int(self._sizes.sum())))
        for k in range(len(self)):
            lo = int(self._offsets[k]) - start
            yield self._array(block[lo:lo + int(self._sizes[k])], k)

    def __reduce__(self):
        return list, (list(self),)

    def __repr__(self) -> str:
        return f"SpilledScans({len(self)} scans, {int(self._sizes.sum())} bytes on disk)"
