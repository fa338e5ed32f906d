"""Maps from several sessions: a second session with an unknown start is placed in the map,
what moved between sessions leaves the merged grid, a map survives save -> load -> save byte for
byte, a different building is not placed, and the CLI's ``run --map`` / several logs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from datasets_synth import generate
from submapslam import open_log
from submapslam.config import PipelineConfig
from submapslam.errors import InputError, SubmapSlamError
from submapslam.fleet import drop_sessions, merge_sessions, session_map_from_result, session_names
from submapslam.geometry import inverse
from submapslam.io.map_store import load_map, save_map
from submapslam.io.trajectory import read_tum
from submapslam.mapping.global_map import build_global_grid
from submapslam.pipeline import run
from submapslam.session_map import SessionMap

SIZE = (20.0, 12.0)  # a small rectangle of hallways: one lap is ~60 m
START_B = 120  # session B starts this many (thinned) scans into its drive: somewhere else


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    """Session A: one lap with six thin poles standing in the hallways; session B: the same
    building without the poles, starting elsewhere (its first scan is its own origin)."""
    root = tmp_path_factory.mktemp("sessions")
    log_a = generate("rectangle", root / "a", seed=0, laps=1, size=SIZE, poles=6)
    log_b = generate("rectangle", root / "b", seed=0, laps=2, size=SIZE)
    scans_a = list(open_log(log_a))[::2]
    scans_b = list(open_log(log_b))[::2][START_B:START_B + 260]
    cfg = PipelineConfig()
    res_a = run(scans_a, cfg, source=str(log_a))
    res_b = run(scans_b, cfg, source=str(log_b))
    map_a = session_map_from_result(res_a, "a")
    merged = merge_sessions(map_a, [session_map_from_result(res_b, "b")], cfg)
    truth_a = read_tum(log_a / "groundtruth_tum.txt").poses[::2]
    truth_b = read_tum(log_b / "groundtruth_tum.txt").poses[::2][START_B:START_B + 260]
    return {"root": root, "map_a": map_a, "merged": merged, "truth_a": truth_a, "truth_b": truth_b,
            "log_a": log_a, "log_b": log_b, "cfg": cfg,
            "res_a": res_a, "res_b": res_b}


def test_second_session_is_placed_in_the_first_ones_frame(sessions):
    merged = sessions["merged"]
    a, b = merged.sessions
    assert b.placed and b.links >= 2, b.note
    # the map frame is A's first scan: B's poses there must match the truth seen from it
    T0 = inverse(sessions["truth_a"][0])
    truth_b = T0 @ sessions["truth_b"]
    est_b = merged.result.poses[b.scans]
    err = np.linalg.norm(est_b[:, :3, 3] - truth_b[:, :3, 3], axis=1)
    assert err.mean() < 0.15, err.mean()
    # unplaced, B would sit at its own origin: meters away from where it really drove
    assert np.linalg.norm(truth_b[0, :3, 3]) > 3.0
    # each session keeps its own timestamps, in input order
    assert np.array_equal(merged.result.timestamps[b.scans], sessions["res_b"].timestamps)
    assert np.array_equal(merged.result.timestamps[a.scans], sessions["res_a"].timestamps)
    # A was already right: the merge does not move it away
    est_a = merged.result.poses[a.scans]
    truth_a = T0 @ sessions["truth_a"]
    assert np.linalg.norm(est_a[:, :3, 3] - truth_a[:, :3, 3], axis=1).mean() < 0.15


def test_a_frozen_map_does_not_move_and_the_new_session_is_placed_against_it(sessions):
    map_a, res_b = sessions["map_a"], sessions["res_b"]
    frozen = merge_sessions(map_a, [session_map_from_result(res_b, "b")], sessions["cfg"], freeze_base=True)
    a, b = frozen.sessions
    r, ra = frozen.result, map_a.result
    # the map comes out exactly as it went in: scan poses, anchors, covariances, its own edges
    assert np.array_equal(r.poses[a.scans], ra.poses)
    assert np.array_equal(r.submap_poses[a.submaps], ra.submap_poses)
    assert np.array_equal(r.submap_covariances[a.submaps], ra.submap_covariances)
    own = [e for e in r.edges if e[0] in a.submaps and e[1] in a.submaps]
    assert [(i, j, kind) for i, j, _, _, kind in own] == [(i, j, kind) for i, j, _, _, kind in ra.edges]
    assert all(np.array_equal(e[2], f[2]) for e, f in zip(own, ra.edges))
    # without freezing, the joint optimisation moves the first session (so the check above can fail)
    assert not np.array_equal(sessions["merged"].result.poses[a.scans], ra.poses)
    # B is placed against the held map as well as in the joint optimisation
    assert b.placed and b.links >= 2, b.note
    T0 = inverse(sessions["truth_a"][0])
    err = np.linalg.norm(r.poses[b.scans][:, :3, 3] - (T0 @ sessions["truth_b"])[:, :3, 3], axis=1)
    assert err.mean() < 0.15, err.mean()
    cross = [e for e in r.edges if (e[0] in a.submaps) != (e[1] in a.submaps)]
    assert cross and all(e[4] == "loop" for e in cross)  # B is tied to the map by its links


def test_dropping_a_session_takes_its_links_and_leaves_the_others_where_they_were(sessions, tmp_path):
    from dataclasses import replace

    merged = sessions["merged"]
    a, b = merged.sessions
    only_b = drop_sessions(merged, ["a"])
    (kept,) = only_b.sessions
    r, rm = only_b.result, merged.result
    assert kept.name == "b" and kept.placed and (kept.scan_start, kept.submap_start) == (0, 0)
    assert (kept.scan_end, kept.submap_end) == (b.scan_end - b.scan_start, b.submap_end - b.submap_start)
    # B stays where the merge put it, in A's frame, with its own timestamps and descriptors
    assert np.array_equal(r.poses, rm.poses[b.scans]) and np.array_equal(r.timestamps, rm.timestamps[b.scans])
    assert np.array_equal(r.submap_poses, rm.submap_poses[b.submaps])
    assert np.array_equal(r.submap_covariances, rm.submap_covariances[b.submaps])
    assert np.array_equal(only_b.descriptors, merged.descriptors[b.submaps])
    # every edge and loop test that touched A went with it; B's own are renumbered
    own = [(i - b.submap_start, j - b.submap_start, kind) for i, j, _, _, kind in rm.edges
           if i in b.submaps and j in b.submaps]
    touching = [e for e in rm.edges if e[0] in b.submaps or e[1] in b.submaps]
    assert [(i, j, kind) for i, j, _, _, kind in r.edges] == own and len(own) < len(touching)
    assert len(r.loops) == sum(lp.i in b.submaps and lp.j in b.submaps for lp in rm.loops)
    assert all(0 <= lp.i < kept.submap_end and 0 <= lp.j < kept.submap_end for lp in r.loops)
    assert r.path_length_m < rm.path_length_m
    # it saves and loads as any map
    save_map(only_b, tmp_path / "b")
    assert [s.to_dict() for s in load_map(tmp_path / "b").sessions] == [kept.to_dict()]
    # each refusal is one line
    for names, words in ((["c"], "no session c"), (["a", "b"], "no map")):
        with pytest.raises(SubmapSlamError, match=words) as exc:
            drop_sessions(merged, names)
        assert "\n" not in str(exc.value)
    unplaced_b = SessionMap(rm, [a, replace(b, placed=False)], merged.descriptors)
    with pytest.raises(SubmapSlamError, match="not in the map frame"):
        drop_sessions(unplaced_b, ["a"])
    assert merged.sessions == [a, b] and rm.n_scans == a.scan_end - a.scan_start + b.scan_end - b.scan_start


def test_poles_seen_only_in_the_first_session_leave_the_merged_grid(sessions):
    merged = sessions["merged"]
    from datasets_synth.worlds import rectangle

    poles = rectangle(seed=0, size=SIZE, poles=6).cylinders[:, :2]
    T0 = inverse(sessions["truth_a"][0])
    poles_map = (T0[:2, :2] @ poles.T).T + T0[:2, 3]

    def occupied_near(grid, xy, radius=0.15):
        p = grid.probabilities()
        rows, cols = np.nonzero(p > 0.65)
        res = grid.params.resolution
        centres = grid.origin + (np.stack([cols, rows], axis=1) + 0.5) * res
        return np.array([(np.linalg.norm(centres - q, axis=1) < radius).any() for q in xy])

    grid_a, _ = build_global_grid(sessions["map_a"].result)
    grid_ab, _ = build_global_grid(merged.placed_result())
    seen_a = occupied_near(grid_a, poles_map)
    assert seen_a.sum() >= 4  # session A's own map has the poles
    # session B drove past them and saw free space where they stood: gone from the merged map
    assert occupied_near(grid_ab, poles_map[seen_a]).sum() <= 1
    # the walls are still there
    assert (grid_ab.probabilities() > 0.65).sum() > 0.6 * (grid_a.probabilities() > 0.65).sum()
    # with session B dropped again, nothing says the poles left: they are back
    grid_dropped, _ = build_global_grid(drop_sessions(merged, ["b"]).placed_result())
    assert occupied_near(grid_dropped, poles_map[seen_a]).sum() >= seen_a.sum() - 1


def test_map_round_trip_is_byte_identical(sessions, tmp_path):
    merged = sessions["merged"]
    first = save_map(merged, tmp_path / "one")
    loaded = load_map(tmp_path / "one")
    second = save_map(loaded, tmp_path / "two")
    for name, path in first.items():
        assert path.read_bytes() == second[name].read_bytes(), name
    r0, r1 = merged.result, loaded.result
    assert np.array_equal(r0.poses, r1.poses) and np.array_equal(r0.timestamps, r1.timestamps)
    assert all(np.array_equal(p, q) and p.dtype == q.dtype for p, q in zip(r0.submap_points, r1.submap_points))
    assert [s.to_dict() for s in merged.sessions] == [s.to_dict() for s in loaded.sessions]
    assert len(r1.edges) == len(r0.edges) and r1.config == r0.config


def test_a_map_of_another_version_or_no_map_is_one_clear_line(sessions, tmp_path):
    save_map(sessions["map_a"], tmp_path / "m")
    manifest = json.loads((tmp_path / "m" / "manifest.json").read_text())
    for version, word in ((manifest["version"] + 1, "newer"), (0, "older")):
        (tmp_path / "m" / "manifest.json").write_text(json.dumps({**manifest, "version": version}))
        with pytest.raises(InputError, match=word) as exc:
            load_map(tmp_path / "m")
        assert "\n" not in str(exc.value)
    with pytest.raises(InputError, match="not a submapslam map"):
        load_map(sessions["log_a"])


def test_a_session_from_another_building_is_not_placed(sessions, tmp_path):
    # hallways 5 m wide instead of 3: look-alike corners and doors match here and there, but
    # those matches never agree with each other
    log = generate("rectangle", tmp_path / "other", seed=5, laps=1, size=(26.0, 18.0), width=5.0, max_scans=300)
    res = run(list(open_log(log))[::2], sessions["cfg"], source=str(log))
    merged = merge_sessions(sessions["map_a"], [session_map_from_result(res, "other")], sessions["cfg"])
    other = merged.sessions[1]
    assert not other.placed and other.links == 0
    assert "not placed" in other.note
    # it stays in its own frame: its poses are those of its own run
    assert np.allclose(merged.result.poses[other.scans], res.poses)
    assert merged.placed_result().n_scans == sessions["map_a"].result.n_scans


def test_session_names_are_log_names_without_extensions(tmp_path):
    (tmp_path / "drive").mkdir()
    assert session_names(["x/intel.clf.bz2", "y/intel.clf", str(tmp_path / "drive"), "merged.log"]) == \
        ["intel", "intel_2", "drive", "merged_2"]


def test_a_weak_candidate_confirmed_alongside_another_is_ambiguous_and_not_placed(sessions):
    # the hallway rectangle looks the same turned by 180 degrees: with few recognition hypotheses
    # (top 2 at descriptor distance <= 0.25) only 2 session submaps agree on a frame, and the rest of
    # B confirms that frame as well as the turned one; a weak candidate must then not place B
    cfg = sessions["cfg"].model_copy(deep=True)
    cfg.sessions.descriptor_top_k, cfg.sessions.descriptor_max_distance = 2, 0.25
    merged = merge_sessions(sessions["map_a"], [session_map_from_result(sessions["res_b"], "b")], cfg)
    b = merged.sessions[1]
    assert not b.placed and "ambiguous" in b.note, b.note
    assert not any(r.accepted for r in merged.result.loops if r.source == "session")
    # with more hypotheses, links from 4 session submaps agree: a strong candidate, placed right
    cfg.sessions.descriptor_max_distance = 0.3
    merged = merge_sessions(sessions["map_a"], [session_map_from_result(sessions["res_b"], "b")], cfg)
    b = merged.sessions[1]
    truth_b = inverse(sessions["truth_a"][0]) @ sessions["truth_b"]
    err = np.linalg.norm(merged.result.poses[b.scans][:, :3, 3] - truth_b[:, :3, 3], axis=1)
    assert b.placed and err.mean() < 0.15, (b.note, err.mean())


def test_a_wrong_candidate_placement_is_not_confirmed(sessions, tmp_path):
    # every single verified match of another building is a candidate (min_candidate_links 1):
    # the guided search around each finds too little of the session on the map
    log = generate("rectangle", tmp_path / "other", seed=5, laps=1, size=(26.0, 18.0), width=5.0, max_scans=300)
    res = run(list(open_log(log))[::2], sessions["cfg"], source=str(log))
    cfg = sessions["cfg"].model_copy(deep=True)
    cfg.sessions.min_candidate_links = 1
    merged = merge_sessions(sessions["map_a"], [session_map_from_result(res, "other")], cfg)
    other = merged.sessions[1]
    assert not other.placed and "candidate placement(s) tried" in other.note, other.note
    assert not any(r.accepted for r in merged.result.loops if r.source == "session")


def test_consistent_groups_are_ranked_by_distinct_session_submaps():
    from submapslam.config import SessionConfig
    from submapslam.geometry import se2_to_matrix
    from submapslam.topology.session_placement import consistent_groups, largest_consistent_group

    cfg = SessionConfig()
    F_a, F_b = se2_to_matrix(10.0, 0.0, 0.3), se2_to_matrix(-5.0, 8.0, 2.0)
    poses = [se2_to_matrix(float(k), 0.0, 0.0) for k in range(6)]
    # links 0-2 agree on F_a (session submaps 0, 1, 2), 3-4 on F_b (submaps 3, 3: one observation), 5 alone
    frames = [F_a, F_a, F_a, F_b, F_b, se2_to_matrix(0.0, 40.0, -1.0)]
    js = [0, 1, 2, 3, 3, 5]
    groups = consistent_groups(frames, poses, js, cfg)
    assert groups[0] == [0, 1, 2] and groups[1] == [3, 4] and groups[2] == [5]
    assert consistent_groups(frames, poses, js, cfg, min_support=2) == [[0, 1, 2]]
    assert largest_consistent_group(frames, poses, js, cfg) == [0, 1, 2]
    assert consistent_groups([], [], [], cfg) == []


def test_an_unplaced_session_is_not_tried_again_against_the_same_map(sessions, tmp_path, monkeypatch):
    from submapslam.topology.session_placement import SessionPlacer

    log = generate("rectangle", tmp_path / "other", seed=5, laps=1, size=(26.0, 18.0), width=5.0, max_scans=300)
    other = session_map_from_result(run(list(open_log(log))[::2], sessions["cfg"], source=str(log)), "other")
    b = session_map_from_result(sessions["res_b"], "b")
    tries: list[int] = []
    real = SessionPlacer.place

    def counted(self, submaps, map_ids, map_poses, map_desc, ids, *rest):
        tries.append(ids[0])
        return real(self, submaps, map_ids, map_poses, map_desc, ids, *rest)

    monkeypatch.setattr(SessionPlacer, "place", counted)
    merged = merge_sessions(sessions["map_a"], [other, b], sessions["cfg"])
    assert [s.placed for s in merged.sessions] == [True, False, True]
    first_other = merged.sessions[1].submap_start
    # "other" tried when added and once more after b was placed; b once; nothing twice against one map
    assert tries.count(first_other) == 2 and len(tries) == 3


def test_a_3d_session_does_not_join_a_2d_map_in_one_clear_line(sessions):
    from dataclasses import replace

    from submapslam.fleet import SessionMerger

    lidar = session_map_from_result(replace(sessions["res_b"], planar=False), "lidar")
    with pytest.raises(InputError, match="cannot join") as exc:
        merge_sessions(sessions["map_a"], [session_map_from_result(sessions["res_b"], "b"), lidar], sessions["cfg"])
    assert "\n" not in str(exc.value)
    merger = SessionMerger(sessions["map_a"], sessions["cfg"])
    with pytest.raises(InputError, match="cannot join"):
        merger.add(lidar)
    assert merger.finish().n_sessions == 1  # the map is as it was
