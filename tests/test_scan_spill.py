import pickle

import numpy as np
import pytest

from submapslam.geometry import se2_to_matrix
from submapslam.mapping.evidence_grid import GridParams
from submapslam.mapping.global_map import local_grid
from submapslam.mapping.scan_spill import ScanSpill, SpilledScans


def _scans(rng, n=12):
    out = []
    for k in range(n):
        a = np.linspace(-np.pi, np.pi, 90 + k, endpoint=False)
        r = 2.0 + rng.random(len(a)) * 6.0
        pts = np.zeros((len(a), 3), np.float32)
        pts[:, 0], pts[:, 1] = r * np.cos(a), r * np.sin(a)
        out.append(pts)
    out[3] = np.zeros((0, 3), np.float32)  # an empty scan keeps its place
    return out


def test_spilled_scans_read_back_bit_for_bit():
    rng = np.random.default_rng(0)
    scans = _scans(rng)
    slices = [rng.normal(size=(k * 7, 3)).astype(np.float16) for k in range(5)]
    spill = ScanSpill()
    a, b = spill.put(scans), spill.put(slices)
    assert isinstance(a, SpilledScans) and len(a) == len(scans) and len(b) == len(slices)
    assert len(spill.put([])) == 0 and list(spill.put([])) == []
    for got, want in [(list(a), scans), ([a[k] for k in range(len(a))], scans), (list(b), slices)]:
        assert len(got) == len(want)
        for g, w in zip(got, want):
            assert g.dtype == w.dtype and g.shape == w.shape and g.tobytes() == w.tobytes()
    assert a.lengths() == [len(s) for s in scans] and b.lengths() == [len(s) for s in slices]
    assert a[-1].tobytes() == scans[-1].tobytes() and [x.shape for x in a[1:3]] == [s.shape for s in scans[1:3]]
    with pytest.raises(IndexError):
        a[len(scans)]
    back = pickle.loads(pickle.dumps(a))  # a result shipped elsewhere carries the arrays themselves
    assert isinstance(back, list) and all(g.tobytes() == w.tobytes() for g, w in zip(back, scans))


def test_a_spilled_submap_gives_the_same_grid_cells():
    rng = np.random.default_rng(1)
    scans = _scans(rng)
    no_returns = [np.zeros((0, 3), np.float32) if k % 2 else s[:5] * 3 for k, s in enumerate(scans)]
    poses = np.array([se2_to_matrix(0.1 * k, -0.05 * k, 0.02 * k) for k in range(len(scans))])
    params = GridParams(resolution=0.1)
    spill = ScanSpill()
    kept = local_grid(poses, scans, params, no_returns)
    spilled = local_grid(poses, spill.put(scans), params, spill.put(no_returns))
    assert np.array_equal(kept.origin, spilled.origin)
    assert kept.logodds.tobytes() == spilled.logodds.tobytes()


def test_a_run_spills_closed_submaps_and_builds_the_same_maps(tmp_path):
    """The pipeline keeps only the last few submaps' grid scans in memory; the maps built from the
    spilled ones equal those built from the same scans held as lists."""
    from dataclasses import replace

    from datasets_synth import generate
    from submapslam import open_log
    from submapslam.fleet import session_map_from_result
    from submapslam.io.map_store import save_map
    from submapslam.mapping.global_map import build_map_outputs
    from submapslam.pipeline import _LATER_SUBMAPS, run

    log = generate("rectangle", tmp_path / "log", seed=0, laps=1)
    result = run(open_log(log))
    n = len(result.submap_scan_points)
    assert n > _LATER_SUBMAPS + 1
    kinds = [isinstance(s, SpilledScans) for s in result.submap_scan_points]
    kept = _LATER_SUBMAPS + 1  # the last closed submap and those its graph work may still edit
    assert all(kinds[:n - kept]) and not any(kinds[n - kept:])
    held = replace(result, submap_scan_points=[list(s) for s in result.submap_scan_points],
                   submap_scan_no_returns=[list(s) for s in result.submap_scan_no_returns])
    a, b = build_map_outputs(result), build_map_outputs(held)
    assert a.points.tobytes() == b.points.tobytes()
    assert a.occupancy.tobytes() == b.occupancy.tobytes() and np.array_equal(a.origin, b.origin)
    assert pickle.loads(pickle.dumps(result)).submap_scan_points[0][0].tobytes() \
        == result.submap_scan_points[0][0].tobytes()
    # the map store reads the spilled scans back a submap at a time while it writes them: the same bytes
    written = [save_map(session_map_from_result(r, "s"), tmp_path / name) for r, name in ((result, "a"), (held, "b"))]
    for name in ("submaps.npz", "scans.npz"):
        assert written[0][name].read_bytes() == written[1][name].read_bytes()
