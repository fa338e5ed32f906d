"""A child Python process that answers messages in order, over its stdin and stdout.

Messages are pickles, each after its length (8 bytes, little-endian). The child is a fresh
interpreter (``python -m MODULE``): nothing of this process is copied into it or run again there,
not even a caller's script. :class:`ChildProcess` feeds it from a writer thread and reads its
answers in a reader thread, so that neither side waits for the other's pipe to drain: this process
queues work and goes on with its own, the child answers as it finishes.
"""

from __future__ import annotations

import os
import pickle
import queue
import struct
import subprocess
import sys
import threading
from pathlib import Path


def send(stream, message: object) -> None:
    """One message: its pickled length (8 bytes, little-endian), then the pickle."""
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(struct.pack("<Q", len(data)))
    stream.write(data)
    stream.flush()


def receive(stream) -> object:
    """One message, or raise EOFError when the other side has closed the pipe."""
    head = stream.read(8)
    if len(head) < 8:
        raise EOFError
    size = struct.unpack("<Q", head)[0]
    data = stream.read(size)
    if len(data) < size:
        raise EOFError
    return pickle.loads(data)


def own_peak_kib() -> int:
    """This process's peak resident set [KiB]: ``VmHWM``, the high-water mark of its own memory
    image. (``ru_maxrss`` of a child started by fork + exec also counts the parent's image it
    was forked from, hundreds of MiB it never used.)"""
    import resource

    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def usable_cores() -> int:
    """How many CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def child_streams():
    """In the child: ``(inbox, outbox)``, the binary streams of its messages. Anything a library
    prints goes to stderr from here on: stdout carries only the messages."""
    inbox, outbox = sys.stdin.buffer, os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    return inbox, outbox


class ChildProcess:
    """``python -m module`` with a writer thread feeding it and a reader thread collecting its
    answers: :meth:`put` never waits for the child, :meth:`get` waits for its next answer (None once
    it has ended or its output broke)."""

    def __init__(self, module: str, name: str) -> None:
        package_root = str(Path(__file__).resolve().parent.parent)
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(
            [package_root, *filter(None, [os.environ.get("PYTHONPATH")])]))
        self.process = subprocess.Popen([sys.executable, "-m", module], stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, env=env)
        self._outbox: queue.Queue = queue.Queue()
        self._inbox: queue.Queue = queue.Queue()
        self._writer = threading.Thread(target=self._feed, name=f"{name}-feeder", daemon=True)
        self._reader = threading.Thread(target=self._drain, name=f"{name}-reader", daemon=True)
        self._writer.start()
        self._reader.start()

    def put(self, message: object) -> None:
        """Queue ``message`` for the child (None: its input ends)."""
        self._outbox.put(message)

    def get(self) -> object | None:
        """The child's next answer, or None once it has ended (every later call: None too)."""
        answer = self._inbox.get()
        if answer is None:
            self._inbox.put(None)
        return answer

    @property
    def waiting(self) -> int:
        """Answers the child has sent that :meth:`get` has not yet taken."""
        return self._inbox.qsize()

    def _feed(self) -> None:
        try:
            while True:
                message = self._outbox.get()
                send(self.process.stdin, message)
                if message is None:
                    break
        except (BrokenPipeError, OSError, ValueError):  # the child has ended: get() says so
            pass

    def _drain(self) -> None:
        try:
            while True:
                self._inbox.put(receive(self.process.stdout))
        except Exception:  # noqa: BLE001 - the child has ended (or its output broke): get() says so
            self._inbox.put(None)

    def close(self, wait_s: float = 10.0) -> None:
        """End the child's input and wait for it (at most ``wait_s``, then it is stopped)."""
        self.put(None)
        try:
            self.process.wait(timeout=wait_s)
        except Exception:  # noqa: BLE001 - a child that does not end (or cannot be waited for) is stopped
            self.process.kill()
            self.process.wait()
        self._writer.join(timeout=1.0)
        self._reader.join(timeout=1.0)
        for stream in (self.process.stdin, self.process.stdout):
            try:
                stream.close()
            except OSError:
                pass
