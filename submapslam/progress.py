"""Progress bars for long work: done of a total (exact, or ``~`` an estimate) with an ETA.

The total comes from ``len(reader)`` when a reader knows it cheaply, else from its
``estimated_len()`` (e.g. a CARMEN log's records counted in a sample of the file), worked out in
a background thread so the bar starts at once and gains its total a moment later.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from rich.progress import ProgressColumn, Task
from rich.text import Text


def reader_total(reader: object) -> tuple[int | None, Callable[[], tuple[int, bool]] | None]:
    """``(exact scan count or None, estimator or None)`` of a log reader: ``len(reader)`` when it
    is cheap, else its ``estimated_len`` (returning ``(count, exact)``) to call later."""
    try:
        return len(reader), None  # type: ignore[arg-type]
    except TypeError:
        return None, getattr(reader, "estimated_len", None)


def clip_total(total: int | None, start: int = 0, limit: int | None = None) -> int | None:
    """The scans a run will see of ``total``: after skipping ``start``, at most ``limit``."""
    if total is None:
        return None
    total = max(0, total - start)
    return min(total, limit) if limit is not None else total


class CountColumn(ProgressColumn):
    """``done/total``; ``done/~total`` for an estimate, ``done/?`` while unknown."""

    def render(self, task: Task) -> Text:
        done = int(task.completed)
        if task.total is None:
            return Text(f"{done}/?", style="progress.download")
        mark = "~" if task.fields.get("estimated") else ""
        return Text(f"{done}/{mark}{int(task.total)}", style="progress.download")


def progress_bar(total: int | None = None, label: str = "scans", console=None):
    """A transient rich progress bar (on stderr unless ``console``): bar, done/total, elapsed, ETA.

    Redrawn 4 times a second, and not at all when the console is not a terminal (a log file or
    a pipe shows nothing of a transient bar, and each redraw takes the GIL from the run)."""
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    console = console or Console(stderr=True)
    return Progress(TextColumn(f"[bold]{label}"), BarColumn(), CountColumn(), TimeElapsedColumn(),
                    TextColumn("eta"), TimeRemainingColumn(), console=console, transient=True,
                    refresh_per_second=4, disable=not console.is_terminal)


class ScanProgress:
    """A progress bar over a log's scans: ``with ScanProgress(reader) as p: ... p(done)``.

    ``start`` and ``limit`` are the scans skipped and the most that will be read (``--max-scans``).
    """

    def __init__(self, reader: object, *, label: str = "scans", start: int = 0, limit: int | None = None) -> None:
        total, self._estimator = reader_total(reader)
        self._start, self._limit = start, limit
        self.bar = progress_bar(label=label)
        self.task = self.bar.add_task(label, total=clip_total(total, start, limit), estimated=False)
        self._lock = threading.Lock()

    def __enter__(self) -> ScanProgress:
        self.bar.__enter__()
        if self._estimator is not None:
            threading.Thread(target=self._estimate, name="count-scans", daemon=True).start()
        return self

    def __exit__(self, *exc) -> None:
        self.bar.__exit__(*exc)

    def _estimate(self) -> None:
        try:
            n, exact = self._estimator()
        except Exception:  # an estimate is a nicety: the reading proper reports a bad file
            return
        with self._lock:
            done = int(self.bar.tasks[0].completed) if self.bar.tasks else 0
            total = clip_total(n, self._start, self._limit)
            if total is not None:
                binding = self._limit is None or total < self._limit  # else --max-scans sets it
                self.bar.update(self.task, total=max(total, done), estimated=not exact and binding)

    def __call__(self, done: int) -> None:
        """``done`` scans so far (an estimated total grows when the log turns out longer)."""
        with self._lock:
            task = self.bar.tasks[0]
            if task.total is not None and done > task.total:
                self.bar.update(self.task, completed=done, total=done)
            else:
                self.bar.update(self.task, completed=done)
