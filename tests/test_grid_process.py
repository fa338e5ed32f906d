"""The map fusion's local grids half in a child process (mapping/grid_process.py): the same grid to
the bit, whoever made each local grid, and a child that fails or cannot start costs nothing but time."""

import numpy as np
import pytest

from submapslam.geometry import se2_to_matrix
from submapslam.mapping import grid_process
from submapslam.mapping.evidence_grid import GridParams
from submapslam.mapping.global_map import build_map_outputs, local_grid
from submapslam.mapping.grid_process import GridsBeside


def _jobs(n=9):
    """``n`` submaps' jobs: a few scans each of a room at drifting poses."""
    rng = np.random.default_rng(3)
    jobs = []
    for s in range(n):
        scans = []
        for _ in range(6):
            a = np.linspace(-np.pi, np.pi, 120 + s, endpoint=False)
            r = 3.0 + rng.random(len(a)) * 2.0
            pts = np.zeros((len(a), 3), np.float32)
            pts[:, 0], pts[:, 1] = r * np.cos(a), r * np.sin(a)
            scans.append(pts)
        poses = np.array([se2_to_matrix(0.1 * k, 0.03 * s, 0.02 * k) for k in range(len(scans))])
        no_returns = [pts[:4] * 4 for pts in scans] if s % 3 == 0 else None
        jobs.append((s, poses, scans, no_returns))
    return jobs


def _here(job, params):
    return lambda: local_grid(job[1], job[2], params, job[3])


@pytest.mark.parametrize("bad", [False, True], ids=["child", "child-fails"])
def test_grids_made_beside_are_those_made_here(bad):
    """Two of every three submaps' grids come from the child, bit for bit those made here; a child
    that fails on a job (here: a malformed one) hands the rest back, and the grids are still all right."""
    params = GridParams(resolution=0.05, free_scan_stride=2)
    jobs = _jobs()
    sent = []

    def job_of(k):
        sent.append(k)
        return ("not a job",) if bad and k == 2 else jobs[k]

    beside = GridsBeside(len(jobs), job_of, params, ahead=2)
    try:
        got = [beside.take(k, _here(job, params)) for k, job in enumerate(jobs)]
    finally:
        beside.close()
    for job, grid in zip(jobs, got):
        want = _here(job, params)()
        assert np.array_equal(grid.origin, want.origin) and grid.logodds.tobytes() == want.logodds.tobytes()
    assert sent[:2] == [1, 2] and all(k % 3 for k in sent)  # not submaps 0, 3, 6: sent a couple ahead
    if bad:
        assert beside.made_beside == 1  # submap 1, then the failure: the rest made here
    else:
        assert beside.made_beside == 6 and beside.child_peak_mb > 10.0  # submaps 1, 2, 4, 5, 7, 8


def test_a_child_that_cannot_start_leaves_every_grid_here(monkeypatch):
    def no_process(*args, **kwargs):
        raise OSError("no more processes")

    monkeypatch.setattr(grid_process, "ChildProcess", no_process)
    params = GridParams(resolution=0.05)
    jobs = _jobs(4)
    beside = GridsBeside(len(jobs), lambda k: jobs[k], params)
    got = [beside.take(k, _here(job, params)) for k, job in enumerate(jobs)]
    beside.close()
    assert beside.made_beside == 0 and all(g is not None for g in got)


def test_a_runs_maps_are_the_same_with_the_grid_child(tmp_path):
    """A planar run's map fusion, with and without the child: the same grid and cloud; the child
    made two of every three local grids, and its memory is in what the fusion reports."""
    import json

    from datasets_synth import generate
    from submapslam.api import run_log
    from submapslam.child_process import usable_cores

    log = generate("rectangle", tmp_path / "rect", seed=0, laps=1)
    result, _ = run_log(log, tmp_path / "out")
    assert len(result.submap_poses) >= 8
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    by_process = summary["peak_memory_mb_by_process"]
    if usable_cores() > 1:  # a planar run on two cores fuses with the child by default; its memory counts
        assert by_process["grids"] > 10.0 and by_process["main_while_grids"] > 10.0
        assert summary["peak_memory_mb"] >= by_process["main_while_grids"] + by_process["grids"] - 0.11
    else:
        assert "grids" not in by_process
    alone = build_map_outputs(result, grid_process=False)
    beside = build_map_outputs(result, grid_process=True)
    assert alone.grid_process is None
    n = len(result.submap_poses)
    assert beside.grid_process["grids"] == n - (n + 2) // 3 and beside.grid_process["peak_mb"] > 10.0
    np.testing.assert_array_equal(beside.occupancy, alone.occupancy)
    np.testing.assert_array_equal(beside.points, alone.points)
