"""The Ray side of ``batch`` (:func:`~submapslam.fleet_api.batch_logs`): a local Ray instance
or a cluster (:class:`RayBatch`), each log's front end a task streaming its progress, the
merge's helpers (actors at the lowest priority, nice 19: its independent placement tests and the
merged grid's local grids, made ahead while the last logs run), the merge itself in a thread of
this process (at nice 10: below this process, above the tasks, which Ray runs at nice 15).

Ray is optional (``pip install 'submapslam[ray]'``): :func:`ray_module` is None without it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .errors import SubmapSlamError

if TYPE_CHECKING:
    from .config import GridParams
    from .mapping.evidence_grid import EvidenceGrid
    from .mapping.global_map import LocalGridJob
    from .topology.session_placement import VerifyMany


def ray_module():
    """The ``ray`` module, or None when it is not installed."""
    try:
        import ray
    except ImportError:
        return None
    return ray


class RayBatch:
    """``batch``'s Ray side: a local Ray instance (``num_cpus``) or the cluster at ``address``,
    started (unless Ray already runs) when made; :meth:`close` shuts down what was started here.

    :meth:`verifier` runs the merge's placement tests on its helper actors (one a CPU, no CPU
    slot of their own); :meth:`run` runs the logs' front ends as tasks with the merge beside
    them; :meth:`make_grids_ahead` makes the merged map's local grids on the same helpers while
    the last logs still run, and :meth:`local_grids` hands them to the fusion; :meth:`release`
    starts the shutdown in the background (beside the writing).
    """

    def __init__(self, ray, address: str | None = None, num_cpus: int | None = None,
                 grids_budget_bytes: int = 256 * 2**20, verbose: bool = False,
                 auth: tuple[dict[str, str], str] = ({}, "")) -> None:
        """``grids_budget_bytes``: the local grids made ahead are kept on the actors up to about
        this size; the others are made when the fusion asks for them. ``address``: a cluster's
        ``HOST:PORT`` or ``ray://HOST:PORT``, joined with ``auth``
        (:func:`~submapslam.ray_cluster.auth_settings`: the environment it needs, and in words);
        one line when it cannot be joined. Ray's own output is kept out of the terminal unless
        ``verbose``."""
        self.ray = ray
        self.client = address is not None and address.startswith("ray://")  # Ray Client
        self.started_here = not ray.is_initialized()
        self._environment = ExitStack()  # the authentication settings, while joined
        if self.started_here:
            self._join_or_start(address, num_cpus, verbose, auth)
        self.workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
        self._helpers: list = []  # the merge's helper actors (:class:`_MergeHelper`)
        self._made_ahead: dict[int, tuple] = {}  # submap key -> (helper holding its local grid, its make's ref)
        self._budget = grids_budget_bytes
        self._shutting_down: ThreadPoolExecutor | None = None
        # every Ray object reference and actor handle kept between calls, dropped before the
        # shutdown (one let go while Ray shuts down in the background ends the process)
        self._holding: list[dict | list] = [self._made_ahead, self._helpers]

    def _join_or_start(self, address: str | None, num_cpus: int | None, verbose: bool,
                       auth: tuple[dict[str, str], str]) -> None:
        """Start a local Ray, or join the cluster at ``address`` with the environment ``auth[0]``."""
        from .ray_cluster import connect_error, environment, quiet_fds

        self._environment.enter_context(environment(auth[0]))
        failure = None
        with quiet_fds(verbose) as said:
            try:
                _init_ray_beside_imports(self.ray, address, num_cpus)
            except Exception as exc:  # Ray's errors are many kinds of exception: one line each
                failure = exc
        if failure is not None:
            self._environment.close()
            if address is None:
                raise SubmapSlamError(f"Ray did not start here: {_last_line(failure)}") from None
            raise connect_error(address, failure, "".join(said)) from None

    def nodes_see(self, paths: list[str | Path], folder: str | Path, timeout_s: float = 120.0) -> bool:
        """Whether every node of the cluster sees each of ``paths`` as here (a file of the same
        size, or a folder) and can write into ``folder``: a task pinned to each node looks."""
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        ray = self.ray
        expected = [(str(Path(p).resolve()), Path(p).stat().st_size if Path(p).is_file() else None) for p in paths]
        look = ray.remote(num_cpus=0, max_retries=0)(sees_files)
        refs = [look.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False))
                .remote(expected, str(Path(folder).resolve())) for n in ray.nodes() if n.get("Alive")]
        return all(ray.get(refs, timeout=timeout_s))

    def ship(self, path: str | Path):
        """The log at ``path`` as a bundle in Ray's object store (its reference: a task given it
        receives the bytes)."""
        from .io.bundle import pack

        return self.ray.put(pack(path))

    def verifier(self) -> Callable[[dict], VerifyMany]:
        """For :class:`~submapslam.fleet.SessionMerger`: its placement tests on the helpers, each
        with a loop closer made from the merger's arguments (results in order). Each helper keeps
        its loop closer and the submaps between batches (put again only when submaps were added),
        so its prepared clouds stay warm."""
        ray = self.ray

        def bind(closer_args: dict) -> VerifyMany:
            helpers = self._start_helpers()
            for h in helpers:  # before any test: a helper runs its calls in order
                h.prepare.remote(closer_args)
            shared: dict = {}  # the submaps as last put: key (list identity, length) and reference
            self._holding.append(shared)

            def verify_many(items, submaps, map_poses):
                key = (id(submaps), len(submaps))
                if shared.get("key") != key:  # the merge appends submaps and never changes their points
                    shared.update(key=key, box=[ray.put(submaps)])  # in a list: passed as a reference
                bounds = np.linspace(0, len(items), min(len(helpers), len(items)) + 1).astype(int)
                futures = [h.verify.remote(key, shared["box"], map_poses, items[lo:hi])
                           for h, lo, hi in zip(helpers, bounds[:-1], bounds[1:])]
                return [rec for f in futures for rec in ray.get(f)]

            return verify_many

        return bind

    def run(self, front_end: Callable[..., dict], args: list[tuple], *,
            record: Callable[[int, dict | None, BaseException | None], None], merge_ready: Callable[[], None],
            progress: Callable[[int, int, int | None], None] | None = None, cpus_per_task: float = 1.0) -> None:
        """Run ``front_end(*a)`` for each ``a`` of ``args`` as a Ray task (started in the order
        given), ``record(k, value, error)`` each as it ends and ``merge_ready()`` after it in a
        thread at nice 10. Each task streams its progress (:func:`front_end_with_progress`, a
        Ray generator task), passed on as ``progress(k, scans done, scans in the log or None)``
        when given. Each task asks Ray for ``cpus_per_task`` CPUs (a 3D front end keeps
        about 1.6 busy); more than the largest node has is refused here, before any task starts
        (Ray would wait for such a node forever)."""
        ray = self.ray
        largest = max((n["Resources"].get("CPU", 0.0) for n in ray.nodes() if n.get("Alive")), default=0.0)
        if cpus_per_task > largest:
            raise SubmapSlamError(f"each log asks for {cpus_per_task:g} CPUs, but the largest Ray node has "
                                  f"{largest:g}: give fewer CPUs per log")
        if self.client:  # Ray Client has no streaming tasks: each log's task returns at its end
            task = ray.remote(num_cpus=cpus_per_task, max_retries=0)(front_end_at_once)
        else:
            task = ray.remote(num_cpus=cpus_per_task, max_retries=0)(front_end_with_progress)
        started = [task.remote(front_end, a) for a in args]
        # in the order given, as the merge takes them (the largest first was slower: the merge
        # then waited for the small logs before the large one; 55.1 s against 48.1 s)
        pending = {ref: k for k, ref in enumerate(started)}
        # the merge in a thread of its own at nice 10, below this process's waiting and progress
        # but above the tasks: Ray starts its workers at nice 15 (its worker_niceness), and the
        # merge chain is as critical as the logs still running (each log is merged only after
        # those before it). Measured, 3 interleaved pairs: with the workers at nice 0 (the merge
        # below them) the logs ended ~5 s sooner but the merge fell behind: 50.4, 48.3, 48.7 s
        # against 51.1, 47.4, 45.4 s as here.
        with ThreadPoolExecutor(max_workers=1, initializer=lower_thread_priority) as merging:
            merges = []
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                k = pending[ready[0]]
                try:
                    kind, *value = ray.get(ready[0] if self.client else next(ready[0]))
                    if kind == "progress":
                        if progress is not None:
                            progress(k, *value)
                        continue
                    value, error = value[0], None
                except Exception as exc:  # a failed log is reported; the others go on
                    value, error = None, exc
                del pending[ready[0]]
                record(k, value, error)
                merges.append(merging.submit(merge_ready))
            for m in merges:
                m.result()  # re-raises a merge's error

    def make_grids_ahead(self, jobs: list[LocalGridJob], params: GridParams) -> None:
        """Start making the local grids of ``jobs`` (submaps already in the merged map) on
        actors at the lowest priority: they use the cores the logs and the merge leave idle.
        Beyond the budget (estimated from each submap's extent) they are left for later."""
        from .mapping.global_map import local_extent

        makers = self._grid_makers()
        chosen = []
        for job in jobs:
            extent = local_extent(job[1], job[2])
            cells = 0 if extent is None else float(np.prod((extent[1] - extent[0]) / params.resolution + 3))
            if cells * 5 > self._budget:  # float32 log-odds and a uint8 free run a cell
                break
            self._budget -= int(cells * 5)
            chosen.append(job)
        params_ref = self.ray.put(params)
        for job in chosen:
            k = len(self._made_ahead) % makers
            self._made_ahead[job[0]] = (k, self._helpers[k].make.remote(job, params_ref))

    def local_grids(self, jobs: list[LocalGridJob], params: GridParams, window: int = 8) -> Iterator[EvidenceGrid | None]:
        """The local grids of ``jobs`` in their order: those made ahead from their actor, the
        others made now on the actors (``window`` requests ahead)."""
        makers = self._grid_makers()  # the count only: the generator's frame holds no actor handle
        helpers = self._helpers  # (emptied by :meth:`release`, as every handle must be)
        refs: dict = {"params": self.ray.put(params)}  # n -> the request for jobs[n]; held as the others
        self._holding.append(refs)

        def request(n: int) -> None:
            key = jobs[n][0]
            held = self._made_ahead.pop(key, None)
            if held is None:
                refs[n] = helpers[n % makers].take.remote(key, jobs[n], refs["params"])
            else:  # the made grid's reference as an argument: taken once it is made
                refs[n] = helpers[held[0]].take.remote(key, None, refs["params"], held[1])

        for n in range(min(window, len(jobs))):
            request(n)
        for n in range(len(jobs)):
            if n + window < len(jobs):
                request(n + window)
            grid = self.ray.get(refs.pop(n))
            if n == len(jobs) - 1:
                refs.clear()
            yield grid

    def _start_helpers(self) -> list:
        """The merge's helpers, one a CPU of the cluster, started at the first use. They take no
        CPU slot of their own: while logs still run they share the cores with them (at a lower
        priority), afterwards they use them all."""
        if not self._helpers:
            helper = self.ray.remote(num_cpus=0, max_restarts=0)(_MergeHelper)
            self._helpers.extend(helper.remote() for _ in range(self.workers))
        return self._helpers

    def _grid_makers(self, most: int = 4) -> int:
        """How many of the helpers make local grids (the first ones): at most ``most`` (the
        fusion, in one thread, takes no more)."""
        return min(most, len(self._start_helpers()))

    def release(self) -> None:
        """Start shutting down a Ray started here, in the background (1.4 s of waiting for its
        processes: beside the merged map's writing)."""
        for held in self._holding:
            held.clear()
        if self.started_here and self._shutting_down is None:
            self._shutting_down = ThreadPoolExecutor(max_workers=1)
            self._shutting_down.submit(self.ray.shutdown)

    def close(self) -> None:
        """Shut down a Ray started (or joined) here and wait for it."""
        self.release()
        if self._shutting_down is not None:
            self._shutting_down.shutdown(wait=True)
        self._environment.close()


def sees_files(expected: list[tuple[str, int | None]], folder: str) -> bool:
    """On a node: each ``(path, size or None for a folder)`` of ``expected`` is there as
    described, and ``folder`` is a folder it may write into."""
    import os

    for path, size in expected:
        p = Path(path)
        if not (p.is_dir() if size is None else (p.is_file() and p.stat().st_size == size)):
            return False
    return os.path.isdir(folder) and os.access(folder, os.W_OK)


def _last_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[-1] if text else type(exc).__name__


def front_end_at_once(front_end: Callable[..., dict], args: tuple) -> tuple:
    """``front_end(*args)`` as :func:`front_end_with_progress`'s last item, ``("done", value)``:
    the task for Ray Client, which does not stream."""
    return ("done", front_end(*args))


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


class _MergeHelper:
    """A Ray actor working for the merge at the lowest priority, in one process for both of its
    jobs: placement tests (a loop closer made by :meth:`prepare`, the submaps of the last batch,
    fetched again when the driver put new ones) and local grids
    (:func:`~submapslam.mapping.global_map.local_grid`) made ahead and kept until taken."""

    def __init__(self) -> None:
        import threading

        lower_thread_priority()  # nice 19 (Ray's 15 + 10), start-up (imports, 1-2 s) too: the logs come first
        self.niced: set[int] = {threading.get_native_id()}  # threads whose priority was lowered
        self.closer = None
        self.key = None
        self.submaps: list = []
        self.grids: dict[int, EvidenceGrid | None] = {}

    def _lower_priority(self) -> None:
        """The thread running this call at the helper's priority (the logs still running come first)."""
        import threading

        if threading.get_native_id() not in self.niced:
            lower_thread_priority()
            self.niced.add(threading.get_native_id())

    def prepare(self, closer_args: dict) -> None:
        """Make the loop closer that :meth:`verify` tests with."""
        from .topology.loop_closure import LoopCloser

        self._lower_priority()
        self.closer = LoopCloser(**closer_args)

    def verify(self, key: tuple, box: list, map_poses: dict, items: list) -> list:
        import ray

        from .topology.session_placement import verify_items

        self._lower_priority()
        if key != self.key:
            self.key, self.submaps = key, ray.get(box[0])
        return verify_items(self.closer, items, self.submaps, map_poses)

    def make(self, job: LocalGridJob, params: GridParams) -> None:
        from .mapping.global_map import job_grid

        self._lower_priority()
        self.grids[job[0]] = job_grid(job, params)

    def take(self, key: int, job: LocalGridJob | None, params: GridParams, made: None = None) -> EvidenceGrid | None:
        """The grid made ahead for ``key`` (``made``: that :meth:`make`'s result, so that Ray runs
        this after it), or ``job``'s made now."""
        if job is None:
            return self.grids.pop(key)
        from .mapping.global_map import job_grid

        self._lower_priority()
        return job_grid(job, params)
