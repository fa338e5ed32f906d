"""The Ray side of ``batch`` (:func:`~submapslam.fleet_api.batch_logs`): a local Ray instance
or a cluster, each log's front end a task, the merge's independent placement tests on actors,
the merge itself in a thread of this process at a lower priority.

Ray is optional (``pip install 'submapslam[ray]'``): :func:`ray_module` is None without it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .topology.session_placement import VerifyMany


def ray_module():
    """The ``ray`` module, or None when it is not installed."""
    try:
        import ray
    except ImportError:
        return None
    return ray


def run_on_ray(ray, front_end: Callable[..., dict], args: list[tuple], *,
               record: Callable[[int, dict | None, BaseException | None], None],
               merge_ready: Callable[[], None], use_verifier: Callable[[Callable[[dict], VerifyMany]], None],
               finish: Callable[[], object], address: str | None = None,
               num_cpus: int | None = None,
               progress: Callable[[int, int, int | None], None] | None = None) -> Callable[[], None]:
    """Run ``front_end(*a)`` for each ``a`` of ``args`` as a Ray task (started in the order
    given), ``record(k, value, error)`` each as it ends and ``merge_ready()`` after it in a
    lower-priority thread; then ``finish()`` (the merge's last retries). ``use_verifier`` receives
    the placement-test runner on Ray actors before any task starts. With ``progress``, each task
    streams ``progress(k, scans done, scans in the log or None)`` while it runs
    (:func:`front_end_with_progress`, a Ray generator task).

    Starts a local Ray (``num_cpus``) or joins the cluster at ``address`` unless Ray is already
    running. Returns a function that waits for the shutdown of a Ray started here, which runs in
    the background meanwhile (1.4 s of waiting for its processes, beside the merged map's writing).
    """
    started_here = not ray.is_initialized()
    if started_here:
        _init_ray_beside_imports(ray, address, num_cpus)
    try:
        use_verifier(_ray_verifier(ray, int(ray.cluster_resources().get("CPU", 1))))
        if progress is None:
            task = ray.remote(num_cpus=1, max_retries=0)(front_end)
            started = [task.remote(*a) for a in args]
        else:
            task = ray.remote(num_cpus=1, max_retries=0)(front_end_with_progress)
            started = [task.remote(front_end, a) for a in args]
        # in the order given, as the merge takes them (the largest first was slower: the merge
        # then waited for the small logs before the large one; 55.1 s against 48.1 s)
        pending = {ref: k for k, ref in enumerate(started)}
        # the merge in a thread of its own, at a lower priority: the logs still running are the
        # critical path, the merge of those before them is not (it only has to keep up)
        with ThreadPoolExecutor(max_workers=1, initializer=lower_thread_priority) as merging:
            merges = []
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                k = pending[ready[0]]
                try:
                    value, error = ray.get(next(ready[0]) if progress is not None else ready[0]), None
                    if progress is not None:
                        if value[0] == "progress":
                            progress(k, *value[1:])
                            continue
                        value = value[1]
                except Exception as exc:  # a failed log is reported; the others go on
                    value, error = None, exc
                del pending[ready[0]]
                record(k, value, error)
                merges.append(merging.submit(merge_ready))
            for m in merges:
                m.result()  # re-raises a merge's error
        finish()  # its retries may test on the Ray actors
    except BaseException:
        if started_here:
            ray.shutdown()
        raise
    if not started_here:
        return lambda: None
    shutting_down = ThreadPoolExecutor(max_workers=1)
    shutting_down.submit(ray.shutdown)
    return lambda: shutting_down.shutdown(wait=True)


def front_end_with_progress(front_end: Callable[..., dict], args: tuple, every_s: float = 0.5) -> Iterator[tuple]:
    """``front_end(*args, on_progress=...)`` as a generator (a Ray generator task): yields
    ``("progress", scans done, scans in the log or None)`` at most every ``every_s`` seconds
    while it runs and the last count at its end, then ``("done", its value)``; its error is
    raised here."""
    import threading

    outcome: dict = {"progress": None}  # the newest (scans done, scans in the log) and the end
    finished = threading.Event()

    def run() -> None:
        try:
            outcome["value"] = front_end(*args, on_progress=lambda done, total: outcome.update(progress=(done, total)))
        except BaseException as exc:  # raised again in the generator, where Ray reports it
            outcome["error"] = exc
        finally:
            finished.set()

    worker = threading.Thread(target=run, name="front end", daemon=True)
    worker.start()
    sent = None
    while not finished.wait(every_s):
        now = outcome["progress"]
        if now is not None and now != sent:
            sent = now
            yield ("progress", *now)
    worker.join()
    if outcome["progress"] not in (None, sent):  # the last count, however short the run
        yield ("progress", *outcome["progress"])
    if "error" in outcome:
        raise outcome["error"]
    yield ("done", outcome["value"])


def _init_ray_beside_imports(ray, address: str | None, num_cpus: int | None) -> None:
    """Start (or join, with ``address``) Ray, importing meanwhile, in a thread, what the merge and
    the writing will need (about 1 s of imports hidden in Ray's 3 s start-up, which mostly waits
    for its processes; ``ray.init`` itself stays in the calling thread, where it sets signal
    handlers)."""
    with ThreadPoolExecutor(max_workers=1) as importing:
        imported = importing.submit(_import_merge_modules)
        ray.init(address=address, num_cpus=None if address else num_cpus, include_dashboard=False,
                 log_to_driver=False, configure_logging=False)
        imported.result()


def _import_merge_modules() -> None:
    from .io import map_store, session_results  # noqa: F401
    from .mapping import global_map  # noqa: F401
    from .topology import loop_closure, session_placement  # noqa: F401


def lower_thread_priority(step: int = 10) -> None:
    """Raise the calling thread's nice value by ``step`` (Linux, where it is per thread; nothing
    elsewhere or when not allowed)."""
    import os
    import sys
    import threading

    if sys.platform.startswith("linux"):
        try:
            tid = threading.get_native_id()
            os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + step))
        except OSError:
            pass


def _ray_verifier(ray, workers: int) -> Callable[[dict], VerifyMany]:
    """For :class:`~submapslam.fleet.SessionMerger`: runs a batch of placement tests on ``workers``
    Ray actors (:class:`_Verifier`), results in order. The actors take no CPU slot of their own:
    while logs still run they share the cores with them, afterwards they use them all. Each
    keeps its loop closer and the submaps between batches (put again only when submaps were
    added), so its prepared clouds stay warm."""
    actor_class = ray.remote(num_cpus=0, max_restarts=0)(_Verifier)

    def bind(closer_args: dict) -> VerifyMany:
        actors = [actor_class.remote(closer_args) for _ in range(max(1, workers))]
        shared: dict = {}  # the submaps as last put: key (list identity, length) and reference

        def verify_many(items, submaps, map_poses):
            key = (id(submaps), len(submaps))
            if shared.get("key") != key:  # the merge appends submaps and never changes their points
                shared.update(key=key, box=[ray.put(submaps)])  # in a list: passed as a reference
            bounds = np.linspace(0, len(items), min(len(actors), len(items)) + 1).astype(int)
            futures = [a.verify.remote(key, shared["box"], map_poses, items[lo:hi])
                       for a, lo, hi in zip(actors, bounds[:-1], bounds[1:])]
            return [rec for f in futures for rec in ray.get(f)]

        return verify_many

    return bind


class _Verifier:
    """A Ray actor for placement tests: a loop closer made from ``closer_args`` and the submaps
    of the last batch (fetched again when the driver put new ones)."""

    def __init__(self, closer_args: dict) -> None:
        import threading

        lower_thread_priority()  # its start-up (imports, 1-2 s) too: the logs still running come first
        self.niced: set[int] = {threading.get_native_id()}  # threads whose priority was lowered
        from .topology.loop_closure import LoopCloser

        self.closer = LoopCloser(**closer_args)
        self.key = None
        self.submaps: list = []

    def verify(self, key: tuple, box: list, map_poses: dict, items: list) -> list:
        import threading

        import ray

        from .topology.session_placement import verify_items

        if threading.get_native_id() not in self.niced:  # the logs still running come first
            lower_thread_priority()
            self.niced.add(threading.get_native_id())
        if key != self.key:
            self.key, self.submaps = key, ray.get(box[0])
        return verify_items(self.closer, items, self.submaps, map_poses)


