"""The submaps' local grids made mostly in a child process, for the map fusion at a run's end.

Once the last scan is registered a run's second core has nothing to do, and the fusion's local
grids (:func:`~.global_map.local_grid`: every scan's rays traced into its submap's grid) are the
larger part of the end's work on one core (Intel: 6-9 s of ray tracing). :class:`GridsBeside`
sends two of every three submaps' scans to a child process (``python -m
submapslam.mapping.grid_process``) a few submaps ahead and makes the others here; the fusion
takes them in submap order. A local grid is the same to the bit wherever it is made (the same
code on the same scans), so the map is too. If the child cannot start or fails, the grids it had
are made here instead.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING

from ..child_process import ChildProcess, child_streams, own_peak_kib, receive, send
from ..process_stats import current_memory_mb
from .evidence_grid import EvidenceGrid, GridParams

if TYPE_CHECKING:
    from .global_map import LocalGridJob

log = logging.getLogger(__name__)


class GridsBeside:
    """Local grids of ``n`` submaps, all but every ``here_every``-th (``k % here_every == 0``)
    made in a child process.

    This process also fuses every grid into the global one, so the child makes the larger share:
    on FR079 (80 submaps) the fusion here takes 1.0 s, the submaps' extents 0.5 s, all local grids
    3.6 s; with every other grid made here, this process was the one waited for.
    ``job_of(k)``: submap ``k``'s :data:`LocalGridJob` (its scans read only when it is sent);
    ``ahead``: how many of the child's grids may be asked for before the fusion takes them (each
    waits, made, in this process's memory). :meth:`take` hands over submap ``k``'s grid;
    :meth:`close` ends the child and records its peak memory (:attr:`child_peak_mb`) and this
    process's resident set at the times it took a grid (:attr:`main_mb_while_child`)."""

    def __init__(self, n: int, job_of: Callable[[int], LocalGridJob], params: GridParams, ahead: int = 4,
                 here_every: int = 3) -> None:
        self._job_of = job_of
        self._for_child = iter([k for k in range(n) if k % here_every])
        self._sent: deque[int] = deque()  # submaps given to the child, in order, not yet taken
        self._ahead = max(1, ahead)
        self.child_peak_mb = 0.0
        self.main_mb_while_child = 0.0
        self.made_beside = 0  # grids the child made that the fusion took
        self._child: ChildProcess | None = None
        try:
            self._child = ChildProcess("submapslam.mapping.grid_process", "grids")
        except OSError as exc:  # no process could be started (limits, no interpreter): every grid here
            log.warning("the local grids are made in this process: their child process could not start (%s)", exc)
            return
        self._child.put(params)
        self._top_up()

    def _top_up(self) -> None:
        """Send the child's next submaps' jobs until ``ahead`` are with it."""
        while self._child is not None and len(self._sent) < self._ahead:
            k = next(self._for_child, None)
            if k is None:
                return
            self._child.put(self._job_of(k))
            self._sent.append(k)

    def take(self, k: int, make_here: Callable[[], EvidenceGrid | None]) -> EvidenceGrid | None:
        """Submap ``k``'s local grid (asked for in submap order): the child's when it was sent
        there, else ``make_here()``."""
        self.main_mb_while_child = max(self.main_mb_while_child, current_memory_mb())
        if not self._sent or self._sent[0] != k:
            return make_here()
        self._sent.popleft()
        answer = self._child.get() if self._child is not None else None
        if not (isinstance(answer, tuple) and answer[0] == "ok"):
            self._fail(answer)
            return make_here()
        self.made_beside += 1
        self._top_up()
        return answer[1]

    def _fail(self, answer: object) -> None:
        """The child failed (``answer``: its error, or None when it ended): the rest is made here."""
        why = answer[1] if isinstance(answer, tuple) and answer[0] == "error" else "it ended unexpectedly"
        log.warning("the local grids' child process failed (%s): the rest are made in this process", why)
        self._sent.clear()
        child, self._child = self._child, None
        if child is not None:
            child.process.kill()
            child.close(wait_s=1.0)

    def close(self) -> None:
        """End the child (grids still with it are dropped) and record its peak memory."""
        child, self._child = self._child, None
        if child is None:
            return
        child.put(None)
        while (answer := child.get()) is not None:
            if isinstance(answer, tuple) and answer[0] == "end":
                self.child_peak_mb = answer[1] / 1024.0
                break
        child.close()


def _serve() -> None:
    """The child: grid parameters first, then jobs until None, each answered with its local grid;
    last, its peak resident set [KiB]."""
    import signal

    from ..process_stats import single_threaded_blas
    from .global_map import job_grid

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it still writes its results
    single_threaded_blas(load_scipy=False)  # as in the run's own process: the same grids to the bit
    inbox, outbox = child_streams()
    try:
        params = receive(inbox)
        while (job := receive(inbox)) is not None:
            try:
                send(outbox, ("ok", job_grid(job, params)))
            except Exception as exc:  # noqa: BLE001 - handed to the parent, which makes the grid itself
                send(outbox, ("error", f"{exc.__class__.__name__}: {exc}"))
        send(outbox, ("end", own_peak_kib()))
    except (EOFError, BrokenPipeError):  # the parent is gone
        pass


if __name__ == "__main__":
    _serve()
