"""``run`` with several logs or ``--map``, and ``batch`` (Ray tasks or one after another)."""

from __future__ import annotations

import csv

import pytest
from typer.testing import CliRunner

from datasets_synth import generate
from submapslam.cli import app
from submapslam.errors import SubmapSlamError
from submapslam.fleet_api import batch_logs

runner = CliRunner()
SCANS = 200
BATCH_SCANS = 60  # batch tests: a few submaps per log are enough


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch")
    a = generate("rectangle", root / "hall.a", seed=0, laps=1, size=(20.0, 12.0), max_scans=SCANS)
    b = generate("rectangle", root / "hall.b", seed=1, laps=1, size=(20.0, 12.0), max_scans=SCANS)
    bad = root / "broken.clf"
    bad.write_text("FLASER 3 1.0 oops\n")
    return root, a, b, bad


def test_run_adds_a_session_to_a_saved_map(logs, tmp_path):
    _, a, _, _ = logs
    first = runner.invoke(app, ["run", str(a), "--out", str(tmp_path / "one")])
    assert first.exit_code == 0, first.output
    assert (tmp_path / "one" / "map" / "manifest.json").is_file()
    second = runner.invoke(app, ["run", str(a), "--map", str(tmp_path / "one"), "--out", str(tmp_path / "two")])
    assert second.exit_code == 0, second.output
    rows = list(csv.DictReader(open(tmp_path / "two" / "sessions.csv")))
    # the folder log keeps its name; the second session of the same log gets a suffix
    assert [r["session"] for r in rows] == ["hall.a", "hall.a_2"]
    assert rows[1]["placed"] == "1", rows[1]["note"]
    one = (tmp_path / "one" / "poses_tum.txt").read_text().splitlines()
    merged = (tmp_path / "two" / "poses_tum.txt").read_text().splitlines()
    assert len(merged) == 2 * len(one)  # both sessions, in input order, own timestamps
    assert [ln.split()[0] for ln in merged[len(one):]] == [ln.split()[0] for ln in one]
    assert (tmp_path / "two" / "poses_tum_hall.a_2.txt").is_file()


@pytest.fixture(scope="module")
def hall_map(logs, tmp_path_factory):
    """The map of one run of the first hall (``run LOG --out``)."""
    _, a, _, _ = logs
    out = tmp_path_factory.mktemp("map") / "one"
    assert runner.invoke(app, ["run", str(a), "--out", str(out)]).exit_code == 0
    return out


@pytest.fixture(scope="module")
def frozen_two(logs, hall_map, tmp_path_factory):
    """The second hall added to the first one's frozen map: the output folder and what it printed."""
    _, _, b, _ = logs
    two = tmp_path_factory.mktemp("frozen") / "two"
    res = runner.invoke(app, ["run", str(b), "--map", str(hall_map), "--freeze-map", "--out", str(two)])
    assert res.exit_code == 0, res.output
    return two, res.output


def test_run_freeze_map_keeps_the_maps_poses_line_for_line(logs, hall_map, frozen_two, tmp_path):
    _, _, b, _ = logs
    two, output = frozen_two
    assert "kept their poses (--freeze-map): hall.a" in output
    rows = list(csv.DictReader(open(two / "sessions.csv")))
    assert rows[1]["placed"] == "1", rows[1]["note"]
    one = (hall_map / "poses_tum.txt").read_text().splitlines()
    assert (two / "poses_tum_hall.a.txt").read_text().splitlines() == one
    assert (two / "poses_tum.txt").read_text().splitlines()[:len(one)] == one
    # without --map there is no map to hold: one red line, nothing written
    res = runner.invoke(app, ["run", str(b), "--freeze-map", "--out", str(tmp_path / "three")])
    assert res.exit_code == 1 and "give --map MAP" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "three").exists()


def test_drop_sessions_writes_the_map_without_them(frozen_two, tmp_path):
    two, _ = frozen_two
    before = (two / "map" / "scans.npz").read_bytes()
    res = runner.invoke(app, ["drop-sessions", str(two), "hall.a", "--out", str(tmp_path / "b_only")])
    assert res.exit_code == 0, res.output
    assert [r["session"] for r in csv.DictReader(open(tmp_path / "b_only" / "sessions.csv"))] == ["hall.b"]
    # hall.b where it was, now the whole trajectory; hall.a's trajectory and map gone
    assert (tmp_path / "b_only" / "poses_tum.txt").read_text() == (two / "poses_tum_hall.b.txt").read_text()
    assert not (tmp_path / "b_only" / "poses_tum_hall.a.txt").exists()
    assert (tmp_path / "b_only" / "map.pgm").is_file() and (tmp_path / "b_only" / "map" / "manifest.json").is_file()
    # the map is only read: never the output; a name it does not hold is one red line, nothing written
    res = runner.invoke(app, ["drop-sessions", str(two), "hall.b", "--out", str(two)])
    assert res.exit_code == 1 and "is the input" in res.output
    res = runner.invoke(app, ["drop-sessions", str(two), "hall.c", "--out", str(tmp_path / "x")])
    assert res.exit_code == 1 and "no session hall.c" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "x").exists() and (two / "map" / "scans.npz").read_bytes() == before


def test_run_with_a_folder_that_is_not_a_map_is_one_red_line(logs, tmp_path):
    _, a, _, _ = logs
    res = runner.invoke(app, ["run", str(a), "--map", str(a), "--out", str(tmp_path / "x")])
    assert res.exit_code == 1
    assert "not a submapslam map" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "x").exists()  # failed before any work


def test_run_never_overwrites_the_map_it_extends(logs, tmp_path):
    _, a, _, _ = logs
    assert runner.invoke(app, ["run", str(a), "--out", str(tmp_path / "m"), "--max-scans", "30"]).exit_code == 0
    before = (tmp_path / "m" / "map" / "scans.npz").read_bytes()
    res = runner.invoke(app, ["run", str(a), "--map", str(tmp_path / "m"), "--out", str(tmp_path / "m")])
    assert res.exit_code == 1 and "is the input" in res.output  # the map is an input: never the output
    assert (tmp_path / "m" / "map" / "scans.npz").read_bytes() == before
    res = runner.invoke(app, ["run", str(a), "--map", str(tmp_path / "m"), "--out", str(tmp_path / "m" / "x")])
    assert res.exit_code == 1 and "is inside the input" in res.output


@pytest.fixture(scope="module")
def sequential(logs, tmp_path_factory):
    _, a, b, bad = logs
    out = tmp_path_factory.mktemp("seq")
    seen, progress, merged = [], [], []
    report = batch_logs([a, bad, b], out, use_ray=False, on_done=seen.append, max_scans=BATCH_SCANS,
                        on_progress=lambda o, done, total: progress.append((o.name, done)),
                        on_merged=lambda o: merged.append((o.name, o.placed, o.note)))
    return out, report, seen, progress, merged


def test_batch_reports_a_failed_log_and_merges_the_others(sequential):
    out, report, seen, _, _ = sequential
    assert report.executor == "sequential"
    assert [o.name for o in report.logs] == ["hall.a", "broken", "hall.b"]
    assert [o.ok for o in report.logs] == [True, False, True]
    assert "broken.clf" in report.logs[1].error
    assert {o.name for o in seen} == {"hall.a", "broken", "hall.b"}
    for name in ("hall.a", "hall.b"):
        assert (out / name / "poses_tum.txt").is_file()
        assert (out / name / "map" / "manifest.json").is_file()
    rows = list(csv.DictReader(open(out / "merged" / "sessions.csv")))
    assert [r["session"] for r in rows] == ["hall.a", "hall.b"]
    assert not (out / "broken" / "poses_tum.txt").exists()


def test_batch_reports_each_log_as_it_runs_and_as_it_joins_the_map(sequential):
    _, report, _, progress, merged = sequential
    for o in (report.logs[0], report.logs[2]):
        counts = [done for name, done in progress if name == o.name]
        assert counts == list(range(1, o.scans + 1))  # after every scan
    assert not [done for name, done in progress if name == "broken"]  # its first line is broken: no scan
    # in the order given, the failed log left out; the first defines the frame
    assert [m[0] for m in merged] == ["hall.a", "hall.b"]
    assert merged[0][1] is True and "map frame" in merged[0][2]
    # 60 scans of the second hall give too few submaps to place it: said as it joins, and the same at the end
    assert merged[1][1] is False and merged[1][2].startswith("not placed")
    assert (report.logs[2].placed, report.logs[2].note) == merged[1][1:]


def test_batch_on_ray_gives_the_same_trajectories(logs, sequential, tmp_path):
    pytest.importorskip("ray")
    _, a, b, bad = logs
    seq_out, seq, _, _, _ = sequential
    # the same logs, the broken one among them: each log's task, then the merge in the order given
    # (each log as soon as it and those before it are done), whatever order the tasks end in
    progress = []
    par = batch_logs([a, bad, b], tmp_path / "ray", use_ray=True, num_cpus=2, max_scans=BATCH_SCANS,
                     on_progress=lambda o, done, total: progress.append((o.name, done)))
    assert par.executor == "ray" and [o.ok for o in par.logs] == [True, False, True]
    # each task streamed its scans done as it ran, the last count being all of them
    for o in (par.logs[0], par.logs[2]):
        counts = [done for name, done in progress if name == o.name]
        assert counts and counts == sorted(counts) and counts[-1] == o.scans == BATCH_SCANS
    assert "broken.clf" in par.logs[1].error
    for name in ("hall.a", "hall.b"):
        assert (tmp_path / "ray" / name / "poses_tum.txt").read_bytes() == (seq_out / name / "poses_tum.txt").read_bytes()
    for name in ("poses_tum.txt", "map.pgm", "map.ply"):  # the grid from local grids made on the Ray actors too
        assert (tmp_path / "ray" / "merged" / name).read_bytes() == (seq_out / "merged" / name).read_bytes(), name


def test_batch_adds_logs_to_a_map_and_can_hold_it_on_ray_as_without(logs, hall_map, tmp_path):
    _, _, b, _ = logs
    fleet = tmp_path / "fleet"
    res = runner.invoke(app, ["batch", str(b), "--map", str(hall_map), "--freeze-map", "--no-ray", "--out", str(fleet)])
    assert res.exit_code == 0, res.output
    assert "kept their poses (--freeze-map): hall.a" in res.output
    rows = list(csv.DictReader(open(fleet / "merged" / "sessions.csv")))
    assert [r["session"] for r in rows] == ["hall.a", "hall.b"]  # the map's session, then the log
    assert rows[1]["placed"] == "1", rows[1]["note"]
    assert (fleet / "hall.b" / "poses_tum.txt").is_file()  # the log's own results, as without --map
    one = (hall_map / "poses_tum.txt").read_text().splitlines()
    assert (fleet / "merged" / "poses_tum_hall.a.txt").read_text().splitlines() == one
    # the map is an input: never inside the output, whatever the option
    res = runner.invoke(app, ["batch", str(b), "--map", str(fleet / "merged"), "--out", str(fleet), "--resume",
                              "--no-ray"])
    assert res.exit_code == 1 and "contains the input" in res.output
    res = runner.invoke(app, ["batch", str(b), "--freeze-map", "--no-ray", "--out", str(tmp_path / "x")])
    assert res.exit_code == 1 and "give --map MAP" in res.output and not (tmp_path / "x").exists()
    res = runner.invoke(app, ["batch", str(b), "--map", str(b), "--no-ray", "--out", str(tmp_path / "x")])
    assert res.exit_code == 1 and "not a submapslam map" in res.output and not (tmp_path / "x").exists()
    # on Ray (the map's local grids made on the actors too): the same merged map
    pytest.importorskip("ray")
    par = batch_logs([b], tmp_path / "ray", use_ray=True, num_cpus=2, map_dir=hall_map, freeze_map=True)
    assert par.executor == "ray" and par.logs[0].placed
    for name in ("poses_tum.txt", "map.pgm", "map.ply"):
        assert (tmp_path / "ray" / "merged" / name).read_bytes() == (fleet / "merged" / name).read_bytes(), name


def test_batch_cli_prints_a_table_and_fails_on_a_missing_log(logs, tmp_path):
    _, a, _, _ = logs
    res = runner.invoke(app, ["batch", str(a), str(tmp_path / "nope.clf"), "--out", str(tmp_path / "o"), "--no-ray"])
    assert res.exit_code == 1 and "no such log" in res.output
    res = runner.invoke(app, ["batch", str(a), "--out", str(tmp_path / "o"), "--no-ray",
                                "--max-scans", str(BATCH_SCANS)])
    assert res.exit_code == 0, res.output
    assert "hall.a" in res.output and "sequential" in res.output
    assert (tmp_path / "o" / "merged" / "map" / "manifest.json").is_file()


def test_ray_local_grids_made_ahead_or_on_demand_equal_those_made_here(sequential):
    pytest.importorskip("ray")
    import numpy as np

    from submapslam.fleet_ray import RayBatch, ray_module
    from submapslam.io.map_store import load_map
    from submapslam.mapping.global_map import grid_params, job_grid, local_grid_jobs

    out, _, _, _, _ = sequential
    result = load_map(out / "hall.a" / "map").result
    params = grid_params(result)
    jobs = local_grid_jobs(result, range(result.n_submaps))
    assert len(jobs) >= 2
    side = RayBatch(ray_module(), num_cpus=2)
    try:
        side.make_grids_ahead(jobs[1::2], params)  # every other one ahead, the rest when asked for
        stream = side.local_grids(jobs, params, window=2)
        made = [next(stream) for _ in jobs]  # as the fusion takes them: the stream is left open
        # Ray's shutdown starts in the background, and a Ray reference let go meanwhile ends the
        # process: none may be left in the open stream (a frame the fusion drops later)
        side.release()
        assert not _ray_handles(stream.gi_frame.f_locals)
        del stream
    finally:
        side.close()
    for job, grid in zip(jobs, made, strict=True):
        here = job_grid(job, params)
        assert np.array_equal(grid.logodds, here.logodds) and np.array_equal(grid.origin, here.origin)
        assert np.array_equal(grid.free_run, here.free_run)


def _ray_handles(value, depth: int = 0) -> list:
    """Ray object references and actor handles in ``value`` (dicts, lists, tuples, closures)."""
    import ray

    if isinstance(value, (ray.ObjectRef, ray.actor.ActorHandle)):
        return [value]
    if depth > 4:
        return []
    if isinstance(value, dict):
        items = list(value.values())
    elif isinstance(value, (list, tuple)):
        items = list(value)
    elif callable(value) and getattr(value, "__closure__", None):
        items = [cell.cell_contents for cell in value.__closure__ if cell.cell_contents is not value]
    else:
        return []
    return [h for item in items for h in _ray_handles(item, depth + 1)]


def test_batch_cpus_per_log_beyond_any_node_is_one_line(logs, tmp_path):
    _, a, b, _ = logs
    with pytest.raises(SubmapSlamError, match="more than 0"):
        batch_logs([a, b], tmp_path / "zero", use_ray=False, cpus_per_log=0)
    pytest.importorskip("ray")
    # Ray would wait forever for a node with 3 CPUs: refused before any task starts
    res = runner.invoke(app, ["batch", str(a), str(b), "--out", str(tmp_path / "o"), "--num-cpus", "2",
                              "--cpus-per-log", "3"])
    assert res.exit_code == 1 and "the largest Ray node has 2" in res.output, res.output
    assert "Traceback" not in res.output
    assert not (tmp_path / "o" / "hall.a" / "poses_tum.txt").exists()


def test_batch_never_writes_into_a_folder_of_yours(logs, tmp_path):
    _, a, b, _ = logs
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    with pytest.raises(SubmapSlamError, match="files of yours"):
        batch_logs([a, b], mine, use_ray=False, max_scans=BATCH_SCANS)
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]  # refused before any work
    # a batch's folder, but with a folder of the user's where a log's results would go
    out = tmp_path / "out"
    assert batch_logs([a], out, use_ray=False, max_scans=BATCH_SCANS).logs[0].ok
    (out / "hall.b").mkdir()
    (out / "hall.b" / "poses_tum.txt").write_text("my poses")
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    res = runner.invoke(app, ["batch", str(a), str(b), "--out", str(out), "--no-ray", "--resume"])
    assert res.exit_code == 1 and "holds files of yours where batch writes the results of log hall.b" in res.output
    assert "Traceback" not in res.output
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == before  # nothing touched


def test_batch_resume_keeps_the_logs_it_finished_and_runs_the_others(logs, sequential, tmp_path):
    import json
    import shutil

    _, a, b, bad = logs
    seq_out, _, _, _, _ = sequential
    out = tmp_path / "o"
    shutil.copytree(seq_out, out)
    record = json.loads((out / "batch.json").read_text())
    assert {n: e["ok"] for n, e in record["logs"].items()} == {"hall.a": True, "broken": False, "hall.b": True}
    stamp = {n: (out / n / "poses_tum.txt").stat().st_mtime_ns for n in ("hall.a", "hall.b")}
    merged_before = (out / "merged" / "poses_tum.txt").read_bytes()
    # again into the same folder: the earlier results are not replaced unless asked
    with pytest.raises(SubmapSlamError, match="earlier batch: pass --resume"):
        batch_logs([a, bad, b], out, use_ray=False, max_scans=BATCH_SCANS)
    with pytest.raises(SubmapSlamError, match="give one of them"):
        batch_logs([a, bad, b], out, use_ray=False, max_scans=BATCH_SCANS, resume=True, overwrite=True)
    # resumed: the two finished logs are kept (not written again), the failed one runs again
    ran = []
    report = batch_logs([a, bad, b], out, use_ray=False, max_scans=BATCH_SCANS, resume=True,
                        on_progress=lambda o, done, total: ran.append(o.name))
    assert [(o.ok, o.kept) for o in report.logs] == [(True, True), (False, False), (True, True)]
    assert not ran  # the broken log fails before its first scan; no other ran
    assert {n: (out / n / "poses_tum.txt").stat().st_mtime_ns for n in stamp} == stamp
    assert report.logs[0].scans == BATCH_SCANS and "broken.clf" in report.logs[1].error
    assert (out / "merged" / "poses_tum.txt").read_bytes() == merged_before  # merged again, the same map
    # other settings: nothing can be kept
    report = batch_logs([a, b], out, use_ray=False, max_scans=BATCH_SCANS // 2, resume=True)
    assert [o.kept for o in report.logs] == [False, False]
    assert len((out / "hall.a" / "poses_tum.txt").read_text().splitlines()) == BATCH_SCANS // 2
    # replaced: the logs of the earlier batch that are not in this one go
    res = runner.invoke(app, ["batch", str(a), "--out", str(out), "--no-ray", "--overwrite", "--max-scans",
                              str(BATCH_SCANS)])
    assert res.exit_code == 0, res.output
    assert not (out / "hall.b").exists() and (out / "hall.a" / "poses_tum.txt").is_file()
    res = runner.invoke(app, ["batch", str(a), "--out", str(out), "--no-ray", "--resume", "--max-scans",
                              str(BATCH_SCANS)])
    assert res.exit_code == 0 and "kept hall.a" in res.output, res.output


def test_batch_resume_on_ray_runs_only_the_logs_not_kept(logs, sequential, tmp_path):
    pytest.importorskip("ray")
    import shutil

    _, a, b, bad = logs
    seq_out, _, _, _, _ = sequential
    out = tmp_path / "o"
    shutil.copytree(seq_out, out)
    shutil.rmtree(out / "hall.b" / "map")  # its map gone: it runs again, as a Ray task
    progress = []
    report = batch_logs([a, bad, b], out, use_ray=True, num_cpus=2, max_scans=BATCH_SCANS, resume=True,
                        on_progress=lambda o, done, total: progress.append(o.name))
    assert report.executor == "ray"
    assert [(o.ok, o.kept) for o in report.logs] == [(True, True), (False, False), (True, False)]
    assert set(progress) == {"hall.b"}  # the progress of the task reaches the right log
    assert (out / "hall.b" / "map" / "manifest.json").is_file()
    for name in ("hall.b/poses_tum.txt", "merged/poses_tum.txt"):
        assert (out / name).read_bytes() == (seq_out / name).read_bytes(), name
