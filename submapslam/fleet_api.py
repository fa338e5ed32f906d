"""Library calls behind ``run LOG1 LOG2 … [--map MAP]`` and ``batch``: several logs, one map.

``run_sessions`` runs each log through the engine, places the sessions in one map (a loaded
``MAP`` first, when given) and writes the merged results. ``batch_logs`` runs each log's front
end as a Ray task (one after another without Ray, same results), writes each log's own results,
then merges them in this process.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .config import PipelineConfig, load_config
from .errors import SubmapSlamError
from .fleet_ray import ray_module
from .session_map import SessionMap

if TYPE_CHECKING:
    from .config import GridParams
    from .mapping.evidence_grid import EvidenceGrid
    from .mapping.global_map import LocalGridJob

log = logging.getLogger(__name__)


def _config(config: str | Path | PipelineConfig | None) -> PipelineConfig:
    return config if isinstance(config, PipelineConfig) else load_config(config)


def _check_freeze(map_dir: str | Path | None, freeze_map: bool) -> None:
    """``freeze_map`` holds the map given by ``map_dir``: without one it is one clear line."""
    if freeze_map and map_dir is None:
        raise SubmapSlamError("--freeze-map holds the map given by --map where it is: give --map MAP")


def run_sessions(
    logs: list[str | Path],
    out_dir: str | Path,
    *,
    map_dir: str | Path | None = None,
    config: str | Path | PipelineConfig | None = None,
    format: str | None = None,
    max_scans: int | None = None,
    loops: bool = True,
    progress: bool = False,
    reader_options: dict | None = None,
    hints: str | Path | None = None,
    overwrite: bool = False,
    freeze_map: bool = False,
) -> tuple[SessionMap, dict[str, Path]]:
    """Build one map from ``logs`` (added to the map at ``map_dir`` when given) into ``out_dir``.

    Each log is one session with its own timestamps, run from its own origin, then placed against
    the sessions already in the map frame (:func:`~submapslam.fleet.merge_sessions`). A map given
    by ``map_dir`` is read first, so a bad one fails before any log is run. ``hints`` apply to a
    single log only. ``freeze_map``: the map at ``map_dir`` does not move (its sessions' poses
    come out exactly as they were; the logs are placed and optimised against it). ``out_dir`` is
    checked before any work and written through a staging folder (:mod:`.io.output_folder`;
    ``overwrite`` replaces an earlier result). Returns the merged map and the written paths.
    """
    from .api import run_log
    from .fleet import merge_sessions, session_map_from_result, session_names
    from .io.map_store import load_map, read_manifest
    from .io.output_folder import check_out_folder, staged_folder

    if not logs:
        raise SubmapSlamError("no log given")
    _check_freeze(map_dir, freeze_map)
    inputs = [*logs, map_dir, hints, config if not isinstance(config, PipelineConfig) else None]
    check_out_folder(out_dir, inputs=inputs, overwrite=overwrite)
    base = None
    taken: list[str] = []
    if map_dir is not None:
        manifest = read_manifest(map_dir)  # one clear line for a folder that is not a map, before any work
        folder = Path(manifest["_folder"]).resolve()
        if Path(out_dir).resolve() in (folder, folder.parent):
            raise SubmapSlamError(f"--out {out_dir} would overwrite the map it extends ({map_dir}); "
                                  "write the extended map to a new folder")
        base = load_map(map_dir)
        taken = [s.name for s in base.sessions]
    cfg = _config(config) if config is not None or base is None else base.result.config
    names = session_names(logs, taken)
    if hints is not None and len(logs) > 1:
        raise SubmapSlamError("--hints applies to one log; give one log with --hints")
    runs = []
    for path, name in zip(logs, names):
        log.info("session %s: %s", name, path)
        result, _ = run_log(path, None, config=cfg, format=format, hints=hints, max_scans=max_scans, loops=loops,
                            progress=progress, reader_options=reader_options)
        runs.append(session_map_from_result(result, name))
    if base is None:
        base, runs = runs[0], runs[1:]
    merged = merge_sessions(base, runs, cfg, freeze_base=freeze_map) if runs else base
    with staged_folder(out_dir, "run", overwrite=overwrite, inputs=inputs) as staging:
        written = write_session_map(merged, staging)
    return merged, {name: Path(out_dir) / name for name in written}


def drop_sessions_from_map(map_dir: str | Path, names: list[str], out_dir: str | Path, *,
                           overwrite: bool = False) -> tuple[SessionMap, dict[str, Path]]:
    """The map at ``map_dir`` without the sessions ``names`` (:func:`~submapslam.fleet.drop_sessions`),
    written into ``out_dir`` as a multi-session run writes (the map rebuilt from the sessions
    kept; ``map_dir`` is only read). ``out_dir`` is checked before any work and written through a
    staging folder (``overwrite`` replaces an earlier result). Returns the map and the written paths."""
    from .fleet import drop_sessions
    from .io.map_store import load_map
    from .io.output_folder import check_out_folder, staged_folder

    if not names:
        raise SubmapSlamError("no session given: name the sessions to drop (sessions.csv lists a map's sessions)")
    check_out_folder(out_dir, inputs=[map_dir], overwrite=overwrite)
    kept = drop_sessions(load_map(map_dir), names)  # a folder that is not a map: one clear line
    with staged_folder(out_dir, "drop-sessions", overwrite=overwrite, inputs=[map_dir]) as staging:
        written = write_session_map(kept, staging)
    return kept, {name: Path(out_dir) / name for name in written}


def write_session_map(session_map: SessionMap, out_dir: str | Path,
                      local_grids: Callable[[list[LocalGridJob], GridParams], Iterable[EvidenceGrid | None]] | None = None,
                      on_fused: Callable[[], None] | None = None) -> dict[str, Path]:
    """Fuse the placed sessions' maps and write everything (:func:`~submapslam.io.session_results.
    write_session_results`). ``local_grids(jobs, params)``: the placed submaps' local grids made
    elsewhere, in order (``batch`` on Ray); ``on_fused`` is called once the maps are fused."""
    from .api import fuse_beside_map_store
    from .io.session_results import write_session_results
    from .mapping.global_map import build_map_outputs, grid_params, local_grid_jobs

    counts = [s.submap_end - s.submap_start for s in session_map.sessions if s.placed]
    starts = [int(k) for k in np.cumsum([0, *counts[:-1]])]  # in the placed sessions' result
    placed = session_map.placed_result()

    def fuse():
        made = None
        if local_grids is not None:  # a generator: nothing is asked for unless the grid is built
            ids = [i for s in session_map.sessions if s.placed for i in s.submaps]
            made = local_grids(local_grid_jobs(session_map.result, ids), grid_params(placed))
        maps = build_map_outputs(placed, session_starts=starts, local_grids=made)
        if on_fused is not None:
            on_fused()
        return maps

    maps, map_paths = fuse_beside_map_store(session_map, Path(out_dir) / "map", fuse)
    return write_session_results(session_map, out_dir, maps, map_paths)


# ---------------------------------------------------------------------- batch
@dataclass
class LogOutcome:
    """One log of a batch: its session name, where its results are, and how it went."""

    log: str
    name: str
    ok: bool = False
    error: str = ""
    scans: int = 0
    submaps: int = 0
    loops_accepted: int = 0
    seconds: float = 0.0
    placed: bool | None = None  # in the merged map (None: not merged)
    links: int = 0
    note: str = ""  # how the merge placed it, or why not
    kept: bool = False  # its results were kept from an earlier batch (``resume``), not made again


@dataclass
class BatchReport:
    """What ``batch`` did: per log, the merged map's folder, the wall time (and of it the front
    ends' share: from the start until every log's task finished), the executor."""

    logs: list[LogOutcome]
    merged_dir: Path | None
    wall_time_s: float
    executor: str  # "ray" | "sequential"
    merged: SessionMap | None = field(default=None, repr=False)
    front_end_s: float = 0.0


def front_end(log_path: str, name: str, out_dir: str, config: PipelineConfig, format: str | None = None,
              max_scans: int | None = None, on_progress: Callable[[int, int | None], None] | None = None,
              recorded_as: str | None = None) -> dict:
    """One log's task: run it, write its results and its one-session map into ``out_dir``;
    return a small summary dict (what travels back from a Ray worker). ``on_progress(scans
    done, scans in the log or None)`` after each scan; ``recorded_as``: the log's path as the
    results name it (:func:`~submapslam.api.run_log`)."""
    from .api import run_log

    t0 = time.perf_counter()
    result, _ = run_log(log_path, out_dir, config=config, format=format, max_scans=max_scans, session_name=name,
                        overwrite=True, on_progress=on_progress, recorded_as=recorded_as)
    return {"scans": result.n_scans, "submaps": result.n_submaps, "loops_accepted": result.loops_accepted,
            "seconds": time.perf_counter() - t0, "input_error": result.input_error}


def shipped_front_end(log_bundle, log_path: str, name: str, out_dir: str, config: PipelineConfig,
                      format: str | None = None, max_scans: int | None = None,
                      on_progress: Callable[[int, int | None], None] | None = None) -> dict:
    """:func:`front_end` on a machine that does not see the driver's files: the log arrives as
    a bundle (:mod:`.io.bundle`; bytes, or their Ray object reference), is run from a temporary
    folder, and its results folder goes back as a bundle (``"results"`` in the dict) for the
    driver to put at ``out_dir``. The results name ``log_path``, the driver's path of the log."""
    import tempfile

    from .io.bundle import pack, unpack

    if not isinstance(log_bundle, bytes):  # a reference inside the task's arguments is not resolved by Ray
        import ray

        log_bundle = ray.get(log_bundle)

    with tempfile.TemporaryDirectory(prefix="submapslam-shipped-") as tmp:
        log_copy = unpack(log_bundle, Path(tmp) / "log")
        results = Path(tmp) / "out" / Path(out_dir).name
        summary = front_end(str(log_copy), name, str(results), config, format, max_scans, on_progress=on_progress,
                            recorded_as=log_path)
        summary["results"] = pack(results)
    return summary


def batch_logs(
    logs: list[str | Path],
    out_dir: str | Path,
    *,
    address: str | None = None,
    use_ray: bool | None = None,
    config: str | Path | PipelineConfig | None = None,
    format: str | None = None,
    max_scans: int | None = None,
    on_done: Callable[[LogOutcome], None] | None = None,
    num_cpus: int | None = None,
    on_progress: Callable[[LogOutcome, int, int | None], None] | None = None,
    on_merged: Callable[[LogOutcome], None] | None = None,
    cpus_per_log: float = 1.0,
    overwrite: bool = False,
    resume: bool = False,
    map_dir: str | Path | None = None,
    freeze_map: bool = False,
    ship_logs: str = "auto",
    verbose: bool = False,
) -> BatchReport:
    """Run every log's front end (a Ray task each, or one after another) and merge them.

    Each log's results go to ``out_dir/<name>/`` (``name``: the log's file name without its
    extensions), the merged map to ``out_dir/merged/``. A log that fails is reported (``ok``
    False, ``error``) and left out of the merge; the others are kept. ``use_ray``: None = Ray
    when installed (or when ``address`` is given), False = sequential; ``address``: an existing
    Ray cluster (default: a local instance with ``num_cpus``); ``cpus_per_log``: the CPUs each
    log's task asks Ray for (2 lets two 3D logs share a 2-core node one at a time, or a 4-core
    node two at a time, instead of crowding it). ``on_done`` is called as each log
    finishes, ``on_progress(outcome, scans done, scans in the log or None)`` while it runs (from
    Ray: about twice a second), ``on_merged`` as each log joins the merged map (``placed`` and
    ``note`` then say how; a later session can still place one left in its own frame). The merge
    takes the logs in the order given, each as soon as it and the logs before it are done (beside
    the logs still running on Ray), so both executors give the same map. With ``map_dir`` (a
    map, as ``run --map`` takes) the logs are added to that map instead, each placed against it
    (the map itself is read before any work and never written); ``freeze_map`` holds it where it
    is (:class:`~submapslam.fleet.SessionMerger`'s ``freeze_base``).

    On a cluster (``address``: ``HOST:PORT`` or ``ray://HOST:PORT``, token authentication as
    the cluster asks: :mod:`.ray_cluster`) the workers read the logs and write ``out_dir/<name>/``
    themselves when every node sees them; ``ship_logs``: "auto" (ship when some node does not),
    "always" or "never" — shipped, each log's bytes travel through Ray's object store and its
    results come back to this process, which writes them (the same files). ``verbose``: Ray's
    own start-up output in the terminal.

    ``out_dir`` is checked before any work (:mod:`.io.batch_folder`): new or empty, or an
    earlier batch's, replaced with ``overwrite`` or continued with ``resume`` (a log whose
    results are there, ended well, from the same bytes and settings, is kept and merged
    again, ``kept``; the others run). ``out_dir/batch.json`` records each log as it ends.
    """
    from .fleet import SessionMerger, session_names
    from .io.batch_folder import (
        batch_settings,
        prepare_batch_folder,
        recorded_fingerprint,
        reusable,
        write_record,
    )
    from .io.map_store import load_map
    from .io.output_folder import staged_folder

    t0 = time.perf_counter()
    _check_freeze(map_dir, freeze_map)
    base = None if map_dir is None else load_map(map_dir)  # read before any work; a non-map is one line
    cfg = _config(config) if config is not None or base is None else base.result.config
    out = Path(out_dir)
    names = session_names(logs, [] if base is None else [s.name for s in base.sessions])
    outcomes = [LogOutcome(str(p), n) for p, n in zip(logs, names)]
    if not cpus_per_log > 0:
        raise SubmapSlamError(f"CPUs per log must be more than 0, not {cpus_per_log:g}")
    if ship_logs not in ("auto", "always", "never"):
        raise SubmapSlamError(f"--ship-logs is auto, always or never, not {ship_logs!r}")
    if ship_logs == "always" and use_ray is False:
        raise SubmapSlamError("logs are shipped to Ray workers: shipping them needs Ray (drop --no-ray)")
    auth: tuple[dict[str, str], str] = ({}, "")  # a cluster's authentication, found before Ray is imported
    if use_ray is not False and address is not None:
        from .ray_cluster import auth_settings

        auth = auth_settings(address)  # nothing answers, or a token is missing or refused: one line before any work
    ray = ray_module() if use_ray is not False else None
    if (use_ray or address) and ray is None:
        raise SubmapSlamError("Ray is not installed: pip install 'submapslam[ray]' (or run without --address)")
    settings = batch_settings(cfg.model_dump_json(), format, max_scans)
    batch_record = prepare_batch_folder(out, names, settings, overwrite=overwrite, resume=resume, inputs=[
        *logs, config if not isinstance(config, PipelineConfig) else None, map_dir])
    args = [(str(p), n, str(out / n), cfg, format, max_scans) for p, n in zip(logs, names)]
    merger: SessionMerger | None = None
    verify_elsewhere = None  # on Ray: the merge's independent placement tests on the workers too
    finished: set[int] = set()
    next_log = 0  # the merge takes the logs in the order given, each as soon as it and those before it are done

    def merge_ready() -> None:
        """Merge the logs that are done and whose predecessors are (in the order given)."""
        nonlocal merger, next_log
        while next_log in finished:
            o = outcomes[next_log]
            next_log += 1
            if not o.ok:
                continue
            session = load_map(out / o.name / "map")
            if merger is None and base is not None:
                merger = SessionMerger(base, cfg, verify_elsewhere, freeze_base=freeze_map)
                make_grids_ahead([s for s in merger.map.sessions if s.placed])
            if merger is None:
                merger = SessionMerger(session, cfg, verify_elsewhere)
            else:
                try:
                    merger.add(session)
                except SubmapSlamError as exc:  # e.g. a 2D log among 3D ones: its own results stay
                    o.error = f"not merged: {exc}"
                    continue
            merged_as = merger.map.sessions[-1]
            if merged_as.placed:
                make_grids_ahead([merged_as])
            if on_merged is not None:
                o.placed, o.links, o.note = merged_as.placed, merged_as.links, merged_as.note
                on_merged(o)

    def make_grids_ahead(placed: list) -> None:
        """On Ray: the local grids of these placed sessions' submaps made on idle cores meanwhile."""
        if side is not None:
            from .mapping.global_map import grid_params, local_grid_jobs

            r = merger.map.result
            side.make_grids_ahead(local_grid_jobs(r, [i for s in placed for i in s.submaps]), grid_params(r))

    def record(k: int, value: dict | None, error: BaseException | None) -> None:
        o = outcomes[k]
        if error is not None:
            o.ok, o.error = False, _one_line(error)
        else:
            o.ok = True
            o.scans, o.submaps, o.loops_accepted, o.seconds = (value["scans"], value["submaps"],
                                                               value["loops_accepted"], value["seconds"])
            o.error = value.get("input_error") or ""
        batch_record["logs"][o.name] = {"log": o.log, "fingerprint": recorded_fingerprint(out / o.name) if o.ok else {},
                                        "ok": o.ok, "error": o.error, "scans": o.scans, "submaps": o.submaps,
                                        "loops_accepted": o.loops_accepted, "seconds": round(o.seconds, 3)}
        write_record(out, batch_record)  # after each log: an interrupted batch can be resumed
        if on_done is not None:
            on_done(o)
        finished.add(k)

    todo = []  # the logs to run (with ``resume``, those whose results cannot be kept)
    for k, o in enumerate(outcomes):
        entry = reusable(batch_record, o.name, logs[k], out) if resume else None
        if entry is None:
            todo.append(k)
            continue
        o.ok, o.kept = True, True
        o.scans, o.submaps, o.loops_accepted, o.seconds = (entry["scans"], entry["submaps"], entry["loops_accepted"],
                                                           entry["seconds"])
        o.error = entry.get("error", "")
        if on_done is not None:
            on_done(o)
        finished.add(k)

    side = None  # on Ray: the instance, its actors and tasks (fleet_ray.RayBatch)
    if ray is not None and todo:
        from .fleet_ray import RayBatch

        side = RayBatch(ray, address, num_cpus, verbose=verbose, auth=auth)
    merged = merged_dir = None
    try:
        if side is not None:
            verify_elsewhere = side.verifier()
            # a cluster's workers run in folders of their own: they are given absolute paths (which
            # the results then name as the log)
            task, on_result = front_end, record
            task_args = [(str(Path(logs[k]).resolve()), args[k][1], str((out / args[k][1]).resolve()), *args[k][3:])
                         for k in todo]
            if ship_logs == "always" or (ship_logs == "auto" and address is not None
                                         and not side.nodes_see([logs[k] for k in todo], out)):
                task, on_result = shipped_front_end, partial(_unpack_results, out, outcomes, record)
                task_args = [(side.ship(logs[k]), *a) for k, a in zip(todo, task_args)]
            side.run(task, task_args, record=lambda j, value, error: on_result(todo[j], value, error),
                     merge_ready=merge_ready, cpus_per_task=cpus_per_log,
                     progress=None if on_progress is None else
                     lambda j, done, total: on_progress(outcomes[todo[j]], done, total))
        else:
            for k in todo:
                step = None if on_progress is None else partial(on_progress, outcomes[k])
                try:
                    value, error = front_end(*args[k], on_progress=step), None
                except Exception as exc:  # a failed log is reported; the others go on
                    value, error = None, exc
                record(k, value, error)
                merge_ready()
        merge_ready()  # the kept logs, when none ran after them
        if merger is not None:
            merger.finish()  # its retries may test on the Ray actors
        front_end_s = time.perf_counter() - t0
        if merger is not None:
            merged = merger.map
            merged_dir = out / "merged"
            # on Ray: the local grids made ahead, then Ray's shutdown beside the files' writing
            with staged_folder(merged_dir, "batch", overwrite=True) as staging:
                write_session_map(merged, staging, local_grids=None if side is None else side.local_grids,
                                  on_fused=None if side is None else side.release)
    finally:
        if side is not None:
            side.close()
    if merger is not None:
        by_name = {s.name: s for s in merged.sessions}
        for o in outcomes:
            if o.name in by_name:
                o.placed, o.links, o.note = by_name[o.name].placed, by_name[o.name].links, by_name[o.name].note
    return BatchReport(outcomes, merged_dir, time.perf_counter() - t0, "sequential" if side is None else "ray",
                       merged, front_end_s)


def _unpack_results(out: Path, outcomes: list[LogOutcome], record: Callable, k: int, value: dict | None,
                    error: BaseException | None) -> None:
    """A shipped log's results (:func:`shipped_front_end`) written to ``out/<name>/``, then
    recorded as a log run in place."""
    if value is not None:
        from .io.bundle import replace_with

        replace_with(value.pop("results"), out / outcomes[k].name)
    record(k, value, error)


def _one_line(exc: BaseException) -> str:
    """A task's error as one line (Ray wraps the worker's exception; its cause is what matters)."""
    cause = getattr(exc, "cause", None) or exc
    text = str(cause).strip().splitlines()
    return f"{type(cause).__name__}: {text[-1]}" if text and not isinstance(cause, SubmapSlamError) \
        else (text[-1] if text else type(cause).__name__)
