"""tools/bench_terrain.py on a tiny terrain log: the row it writes matches the run's own files."""

from __future__ import annotations

import csv
import json

from .conftest import load_tool, shared_data


def test_bench_terrain_tiny_log(tmp_path, monkeypatch):
    bench = load_tool("bench_terrain")
    monkeypatch.setattr(bench, "KITTI_GT", shared_data("trajectories", "kitti_gt", "00.txt.xz").parent)
    rc = bench.main(["--generate", "00:16:60", "--data-root", str(tmp_path / "data"), "--out", str(tmp_path / "out"),
                     "--json", str(tmp_path / "b.json"), "--markdown", str(tmp_path / "b.md")])
    assert rc == 0
    (row,) = json.loads((tmp_path / "b.json").read_text())
    assert row["log"] == "ter00_16_60" and row["scans"] == 60 and row["relief_m"] > 0
    out = tmp_path / "out" / "ter00_16_60"
    summary = json.loads((out / "summary.json").read_text())
    assert row["map_points"] == summary["map_points"] and row["map_dynamic_points"] == summary["map_dynamic_points"]
    assert 0 <= row["map_dynamic_pct"] < 100 and row["ate_m"] >= 0 and 0 < row["path_m"] < 60
    with open(out / "loops.csv", newline="") as fh:
        assert row["closures_accepted"] == sum(r["accepted"] == "1" for r in csv.DictReader(fh))
    assert "| ter00_16_60 | 60 |" in (tmp_path / "b.md").read_text()
    test = summary.get("ground_priors") or {}
    assert row["ground_priors"] == ("-" if not test else bench._ground_priors(test))


def test_ground_priors_in_a_few_words():
    bench = load_tool("bench_terrain")
    assert bench._ground_priors({}) == "-"
    assert bench._ground_priors({"level_ratio": 0.43, "level": True, "kept": True}) == "level (0.43), kept"
    assert bench._ground_priors({"level_ratio": 2.0, "level": False, "kept": False}) == "not level (2.0), dropped"
    assert bench._ground_priors({"level_ratio": None, "level": None, "kept": True}) == "untested (None), kept"


def test_a_world_that_cannot_be_generated_ends_in_one_line(tmp_path, monkeypatch):
    """A sensor synth does not know (7 rings) stops the bench with one line naming the spec and
    synth's own reason, not a traceback."""
    import pytest

    bench = load_tool("bench_terrain")
    monkeypatch.setattr(bench, "KITTI_GT", shared_data("trajectories", "kitti_gt", "00.txt.xz").parent)
    with pytest.raises(SystemExit) as err:
        bench.generate("00:7:5", tmp_path)
    assert "'00:7:5'" in str(err.value) and "synth failed" in str(err.value) and "\n" not in str(err.value)
    assert not (tmp_path / "ter00_7_5").exists()


def test_a_seed_in_the_spec_writes_another_world(tmp_path, monkeypatch):
    """``SEQ:RINGS[:SCANS][:sSEED]``: the seed (the city's layout and the noise) names the folder
    and changes the scans; a seed that is not a number stops with one line."""
    import numpy as np
    import pytest

    bench = load_tool("bench_terrain")
    monkeypatch.setattr(bench, "KITTI_GT", shared_data("trajectories", "kitti_gt", "00.txt.xz").parent)
    plain, seeded = bench.generate("00:16:3", tmp_path), bench.generate("00:16:3:s5", tmp_path)
    assert (plain.name, seeded.name) == ("ter00_16_3", "ter00_16_3_s5")
    first = sorted((plain / "scans").iterdir())[0].name
    assert (seeded / "scans" / first).read_bytes() != (plain / "scans" / first).read_bytes()
    assert np.array_equal(np.loadtxt(plain / "groundtruth_tum.txt")[:, 1:], np.loadtxt(seeded / "groundtruth_tum.txt")[:, 1:])
    with pytest.raises(SystemExit) as err:
        bench.generate("00:16:3:sx", tmp_path)
    assert "'00:16:3:sx'" in str(err.value) and "\n" not in str(err.value)


def test_rings_ending_in_kf_write_irregular_keyframes(tmp_path, monkeypatch):
    """``SEQ:16kf:SCANS``: the 16-ring world at irregular keyframes, its scans further apart in time
    than the 10 Hz world's and its meta.yaml saying so."""
    import numpy as np
    import yaml

    bench = load_tool("bench_terrain")
    monkeypatch.setattr(bench, "KITTI_GT", shared_data("trajectories", "kitti_gt", "00.txt.xz").parent)
    regular, keyframed = bench.generate("00:16:30", tmp_path), bench.generate("00:16kf:30", tmp_path)
    assert keyframed.name == "ter00_16kf_30"
    assert "keyframes" in yaml.safe_load((keyframed / "meta.yaml").read_text())
    assert "keyframes" not in yaml.safe_load((regular / "meta.yaml").read_text())
    gaps = [np.diff(np.loadtxt(log / "groundtruth_tum.txt")[:, 0]) for log in (regular, keyframed)]
    assert np.allclose(gaps[0], 0.1, atol=1e-3) and np.median(gaps[1]) > 0.15


def test_a_cut_with_lost_scans_is_scored_at_the_scans_it_kept(tmp_path, monkeypatch):
    """``cut_cloud_log.py --drop A:B`` leaves scans A to B-1 out, carries no wheel odometry, and
    ``evaluate`` matches the run's poses to the ground truth by time: the poses of a log whose
    middle is missing are not its first scans'. Scored as a prefix, a run placed exactly on the
    truth would show metres of error."""
    import numpy as np
    import pytest

    bench, cut_tool = load_tool("bench_terrain"), load_tool("cut_cloud_log")
    monkeypatch.setattr(bench, "KITTI_GT", shared_data("trajectories", "kitti_gt", "00.txt.xz").parent)
    src = bench.generate("00:16:40", tmp_path)
    dst = tmp_path / "cut"
    assert cut_tool.cut(src, dst, 0, 1, (cut_tool.parse_drop("10:20"),)) == 30
    assert not (dst / "odometry_tum.txt").exists() and len(list((dst / "scans").glob("*.ply"))) == 30
    times = np.loadtxt(dst / "times.txt")
    assert np.isclose(times[10] - times[9], 1.1, atol=1e-3)  # scans 10-19 are gone
    with pytest.raises(SystemExit, match="--drop '20:10'"):
        cut_tool.parse_drop("20:10")
    # a "run" that is the truth at the kept scans, with the files evaluate reads
    out = tmp_path / "run"
    out.mkdir()
    truth = np.loadtxt(src / "groundtruth_tum.txt")
    kept = truth[np.isin(np.round(truth[:, 0], 3), np.round(times, 3))]
    assert len(kept) == 30
    for name in ("poses_tum.txt", "odometry_tum.txt"):
        np.savetxt(out / name, kept, fmt="%.9f")
    (out / "summary.json").write_text(json.dumps({"scans": 30}))
    (out / "submaps.csv").write_text("id,first_scan,last_scan,n_scans,x,y,z,qx,qy,qz,qw\n")
    (out / "graph.g2o").write_text("")
    (out / "loops.csv").write_text("submap_i,submap_j,accepted,reason\n")
    figures = bench.evaluate(dst, out)
    assert figures["ate_m"] < 1e-6 and figures["odometry_ate_m"] < 1e-6
