"""Ctrl-C and SIGTERM for long commands: the first asks the work to stop and keep what it has,
the second quits at once."""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from ._common import err_console

EXIT_INTERRUPTED = 130
"""Exit status of a command stopped by SIGINT (128 + 2, the shell's convention)."""


@contextmanager
def stop_requests(what: str) -> Iterator[threading.Event]:
    """While inside, the first SIGINT/SIGTERM sets the yielded event (the work stops after the
    current step and writes a complete result); a second one leaves through KeyboardInterrupt.
    The previous handlers are restored on exit. Only the main thread can install handlers:
    elsewhere the event is returned and never set."""
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum: int, frame) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()
        err_console.print(f"[yellow]{signal.Signals(signum).name}:[/yellow] {what} stops after the current scan "
                          "and writes what it has (press Ctrl-C again to quit at once, keeping nothing)",
                          highlight=False)

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def quit_now(message: str) -> None:
    """Print ``message`` and end the process with :data:`EXIT_INTERRUPTED` without waiting for
    worker threads (a second Ctrl-C means now)."""
    err_console.print(f"[red]interrupted:[/red] {message}", highlight=False)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(EXIT_INTERRUPTED)
