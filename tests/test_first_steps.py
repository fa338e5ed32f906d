"""The first ten minutes of a new user (issue 28): what the demo and a run end with, and the
one-line answers to the inputs a newcomer gets wrong."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from submapslam.cli import app

from .cli_errors import assert_one_error_line
from .report_pages import CHROMIUM, chromium, figure_png

runner = CliRunner()


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    out = tmp_path_factory.mktemp("first") / "log"
    r = runner.invoke(app, ["synth", "rectangle", "--out", str(out), "--laps", "1", "--max-scans", "60"])
    assert r.exit_code == 0, r.output
    return out


@pytest.fixture(scope="module")
def small_run(small_log, tmp_path_factory):
    out = tmp_path_factory.mktemp("first") / "run"
    r = runner.invoke(app, ["run", str(small_log), "--out", str(out)])
    assert r.exit_code == 0, r.output
    return out, r.output


def _png_not_blank(path) -> None:
    import matplotlib.image as mpimg

    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 200
    assert float(np.std(img[..., :3])) > 0.02  # a drawing, not one colour


def test_run_ends_naming_report_and_files(small_run):
    out, output = small_run
    assert f"submapslam report {out}" in output
    assert "poses_tum.txt" in output and "summary.json" in output and "map." in output


def test_map_picture_never_overwrites_a_file_of_yours(small_run, tmp_path):
    from submapslam.api import map_picture
    from submapslam.errors import InputError

    out, _ = small_run
    mine = tmp_path / "mine.png"
    mine.write_text("my notes")
    with pytest.raises(InputError, match="not a PNG"):
        map_picture(out, mine)
    assert mine.read_text() == "my notes"
    png = map_picture(out, tmp_path / "p.png")
    _png_not_blank(png)
    assert map_picture(out, png) == png  # its own picture is replaced


def _labelled_log(tmp_path):
    """Two 3D scans 1 m apart along x: a static wall seen twice, a person seen in the first."""
    from submapslam.geometry import se2_array_to_matrices
    from submapslam.io.trajectory import Trajectory, write_tum

    from .labelled_scenes import write_wall_and_person_log

    log = tmp_path / "log"
    write_wall_and_person_log(log)
    # the same motion in another frame (a run's): 3 m to the side
    write_tum(tmp_path / "run_poses.txt",
              Trajectory(np.array([0.0, 0.1]), se2_array_to_matrices(np.array([[0.0, 3.0, 0.0], [1.0, 3.0, 0.0]]))))
    return log


def test_eval_map_scores_a_cleaned_map_in_the_frame_it_was_cleaned_in(tmp_path):
    log = _labelled_log(tmp_path)
    out = tmp_path / "clean"
    r = runner.invoke(app, ["clean", str(log), "--poses", str(tmp_path / "run_poses.txt"), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "frame" in r.output and "run_poses.txt" in r.output
    r = runner.invoke(app, ["eval-map", str(out / "map_static.ply"), str(log), "--json", str(tmp_path / "s.json")])
    assert r.exit_code == 0, r.output
    s = json.loads((tmp_path / "s.json").read_text())
    assert s["SA"] == 1.0 and "run_poses.txt" in s["frame"]  # not 0.0 from the log's ground-truth frame
    assert "frame: the poses it was cleaned at" in r.output
    # scoring it in another frame is allowed, with one warning line naming both
    r = runner.invoke(app, ["eval-map", str(out / "map_static.ply"), str(log), "--poses",
                            str(log / "groundtruth_tum.txt")])
    assert r.exit_code == 0
    warnings = [ln for ln in r.stderr.splitlines() if ln.startswith("warning:")]
    assert len(warnings) == 1 and "run_poses.txt" in warnings[0] and "groundtruth_tum.txt" in warnings[0]


def test_run_on_a_results_folder_is_one_red_line(small_run, tmp_path):
    out, _ = small_run
    for given in (out, out / "map.ply"):
        r = runner.invoke(app, ["run", str(given), "--out", str(tmp_path / "again")])
        assert_one_error_line(r, str(given), "results of `submapslam run`", "not a log")
    assert not (tmp_path / "again").exists()


@pytest.mark.parametrize("laps", ["-1", "0"])
def test_synth_laps_below_one_is_one_red_line(tmp_path, laps):
    r = runner.invoke(app, ["synth", "rectangle", "--laps", laps, "--out", str(tmp_path / "s")])
    assert_one_error_line(r, "--laps", laps)
    assert not (tmp_path / "s").exists()


def test_carmen_scan_count_is_exact_plain_and_close_compressed(small_log, tmp_path):
    import bz2

    from submapslam.io.carmen import CarmenReader

    clf = small_log / "log.clf"
    n = sum(1 for line in clf.read_text().splitlines() if line.startswith("FLASER "))
    assert CarmenReader(clf).estimated_len() == (n, True)
    # a longer compressed log (many copies of the text): estimated from a sample, within 15 %
    big = tmp_path / "big.clf.bz2"
    copies = 1 + (3 << 20) // clf.stat().st_size  # ~3 MB of text: more than the 2 MB sample
    big.write_bytes(bz2.compress(clf.read_bytes() * copies, compresslevel=1))
    count, exact = CarmenReader(big).estimated_len()
    assert not exact and abs(count - copies * n) < 0.15 * copies * n


def test_progress_has_a_total_and_an_eta(small_log):
    import time

    from submapslam.io.carmen import CarmenReader
    from submapslam.progress import CountColumn, ScanProgress

    reader = CarmenReader(small_log / "log.clf")
    with ScanProgress(reader, limit=40) as bar:
        for _ in range(100):  # the count runs beside the bar
            if bar.bar.tasks[0].total is not None:
                break
            time.sleep(0.02)
        bar(7)
        task = bar.bar.tasks[0]
        assert str(CountColumn().render(task)) == "7/40"
        assert any(type(c).__name__ == "TimeRemainingColumn" for c in bar.bar.columns)
        bar(45)  # a longer log than estimated: the total grows, never below what is done
        assert bar.bar.tasks[0].total == 45
    task.fields["estimated"] = True
    assert str(CountColumn().render(task)).startswith("45/~")


def test_ekf_recognises_a_synth_landmarks_folder_and_names_its_formats(small_log, tmp_path):
    lm = tmp_path / "lm"
    r = runner.invoke(app, ["synth", "landmarks", "--laps", "1", "--landmarks", "8", "--out", str(lm)])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["ekf", str(lm), "--out", str(tmp_path / "e")])  # the folder, not lm/landmarks.txt
    assert r.exit_code == 0, r.output
    assert "{" not in r.output and "'" not in r.output  # key: value lines, not a Python dict
    # a laser log, or a folder of something else: one line naming what ekf reads
    line = assert_one_error_line(runner.invoke(app, ["ekf", str(small_log / "log.clf"), "--out", str(tmp_path / "c")]),
                                 "carmen", "ekf reads", "MR.CLAM", "victoria_park")
    assert "unknown record" not in line
    # the report overlays the true landmarks the synthetic log knows
    from submapslam.io.run_folder import read_run_folder

    assert read_run_folder(tmp_path / "e").truth_landmarks.shape == (8, 2)
    r = runner.invoke(app, ["report", str(tmp_path / "e")])
    assert r.exit_code == 0, r.output
    assert "black crosses: the true landmarks" in (tmp_path / "e" / "report.html").read_text()
    (tmp_path / "empty").mkdir()
    assert_one_error_line(runner.invoke(app, ["ekf", str(tmp_path / "empty"), "--out", str(tmp_path / "x")]),
                          "not a landmark log", "synth landmarks")


def _warnings(result) -> list[str]:
    return [ln for ln in result.stderr.splitlines() if ln.startswith("warning:")]


def test_backwards_time_and_nan_ranges_are_one_line_each(small_log, tmp_path):
    lines = (small_log / "log.clf").read_text().splitlines()
    flaser = [i for i, ln in enumerate(lines) if ln.startswith("FLASER ")]
    tok = lines[flaser[20]].split()
    tok[-3] = f"{float(tok[-3]) - 5.0:.6f}"  # scan 20 is 5 s before scan 19
    tok[5] = tok[6] = "nan"  # two NaN beam ranges
    lines[flaser[20]] = " ".join(tok)
    log = tmp_path / "odd.clf"
    log.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    r = runner.invoke(app, ["run", str(log), "--out", str(out), "--max-scans", "30", "--no-loops"])
    assert r.exit_code == 0, r.output
    warnings = _warnings(r)
    assert any("run backwards 1 time(s)" in w and "scan 20" in w for w in warnings), r.stderr
    assert any("2 NaN beam range(s)" in w for w in warnings), r.stderr
    assert len(warnings) == 2
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["input_warnings"]) == 2 and summary["nan_ranges"] == 2


def test_an_all_nan_scan_is_one_line(small_log, tmp_path):
    import shutil

    from datasets_synth.writer import write_ply_xyzt

    log = tmp_path / "log"
    shutil.copytree(small_log, log, ignore=shutil.ignore_patterns("*.clf*", "labels"))
    write_ply_xyzt(log / "scans" / "000010.ply", np.full((50, 3), np.nan), np.zeros(50))
    r = runner.invoke(app, ["run", str(log), "--out", str(tmp_path / "out"), "--max-scans", "25", "--no-loops"])
    assert r.exit_code == 0, r.output
    warnings = _warnings(r)
    assert len(warnings) == 1 and "1 scan file(s) hold only NaN/inf points (first: 000010.ply)" in warnings[0]


def test_help_keeps_units_and_names_plain_types():
    r = runner.invoke(app, ["eval", "--help"])
    assert "tolerance [s]" in r.output
    r = runner.invoke(app, ["compare", "--help"])
    assert "list[" not in r.output and "<path>..." in r.output
    r = runner.invoke(app, ["run", "--help"])
    assert "<bool>" not in r.output and "--no-loops" in r.output


def test_output_is_not_wrapped_at_80_columns_when_piped(tmp_path):
    r = runner.invoke(app, ["synth", "rectangle", "--laps", "1", "--max-scans", "20", "--out", str(tmp_path / "s")])
    assert r.exit_code == 0, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and len(lines[0]) > 80 and "1 lap," in lines[0]


def test_batch_ctrl_c_says_what_is_kept(small_log, tmp_path, monkeypatch):
    import submapslam.fleet_api as fleet_api

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(fleet_api, "batch_logs", interrupted)
    r = runner.invoke(app, ["batch", str(small_log), "--out", str(tmp_path / "b"), "--no-ray"])
    assert r.exit_code == 130
    assert r.stderr.startswith("interrupted:") and "--resume" in r.stderr


def test_a_rejection_shows_the_digits_that_differ():
    from submapslam.registration.correspondence import below

    assert below("fitness", 0.4499, 0.45) == "fitness 0.4499 < 0.4500"
    assert below("fitness", 0.2, 0.45) == "fitness 0.20 < 0.45"


def test_eval_warns_when_the_estimate_covers_part_of_the_reference(small_log, tmp_path):
    from submapslam.io.trajectory import read_tum, write_tum

    est = read_tum(small_log / "odometry_tum.txt")
    write_tum(tmp_path / "short.txt", est.subset(np.arange(10)))
    r = runner.invoke(app, ["eval", str(tmp_path / "short.txt"), str(small_log / "groundtruth_tum.txt")])
    assert r.exit_code == 0, r.output
    warnings = _warnings(r)
    assert len(warnings) == 1 and "short.txt (10 poses) covers" in warnings[0] and "that part only" in warnings[0]
    r = runner.invoke(app, ["eval", str(small_log / "odometry_tum.txt"), str(small_log / "groundtruth_tum.txt")])
    assert not _warnings(r)


def test_new_poses_streams_each_scan_once_without_waiting(small_log):
    from submapslam import SubmapSLAM, load_config, open_log
    from submapslam.config import with_updates
    from submapslam.geometry import inverse

    slam = SubmapSLAM(with_updates(load_config(None), {"submaps": {"max_scans": 15}}, "test"))
    waited = []
    settle = slam._settle
    slam._settle = lambda: (waited.append(1), settle())[1]
    stamps, got = [], []
    for k, scan in enumerate(open_log(small_log)):
        slam.process_scan(scan)
        held = slam._start_refit()[0]  # the run's first scans come once its frame is settled
        before = len(waited)
        t, T = slam.new_poses()
        assert len(waited) == before  # never waits for the graph work
        new = 0 if k < held else held + 1 if k == held else 1  # O(new scans), each scan once
        assert T.shape == (new, 4, 4) and (new == 0 or t[-1] == scan.timestamp)
        stamps.extend(t)
        got.extend(T)
    assert slam.new_poses()[1].shape == (0, 4, 4)
    all_t, all_T = slam.trajectory()
    assert np.array_equal(all_t, stamps)
    # the live estimate of the newest scan is trajectory()'s once the graph work is in
    assert len(slam.submaps) >= 2
    slam._settle()
    C = slam._graph_builder.graph.pose(slam.submaps[-1].id) @ inverse(slam.submaps[-1].T_odom_anchor)
    assert np.allclose(C @ slam._odom_poses[-1], all_T[-1], atol=1e-9)
    assert np.linalg.norm(got[-1][:3, 3] - all_T[-1][:3, 3]) < 0.5
    slam.finish()


def test_a_garbled_bag_error_prints_no_raw_bytes(tmp_path):
    bag = tmp_path / "bad.bag"
    bag.write_bytes(bytes(np.random.default_rng(3).integers(0, 256, 100, dtype=np.uint8)))
    line = assert_one_error_line(runner.invoke(app, ["run", str(bag), "--out", str(tmp_path / "o")]), "bad.bag")
    assert "\\x" not in line and len(line) < 300


def test_dump_config_says_what_each_key_means_and_reads_back(tmp_path):
    from submapslam.config import dump_config, load_config

    r = runner.invoke(app, ["dump-config"])
    assert r.exit_code == 0
    lines = r.output.splitlines()
    at = next(i for i, ln in enumerate(lines) if ln.strip().startswith("max_range:"))
    assert lines[at - 1].strip().startswith("# drop points farther than this [m]")
    (tmp_path / "c.yaml").write_text(r.output)
    assert dump_config(load_config(tmp_path / "c.yaml")) == dump_config(load_config(None))
    plain = runner.invoke(app, ["dump-config", "--no-comments"]).output
    assert "#" not in plain and "odometry:" in plain


def test_view_without_a_display_is_one_line(small_log, tmp_path, monkeypatch):
    import sys

    if sys.platform in ("darwin", "win32"):
        pytest.skip("windows open without DISPLAY there")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    r = runner.invoke(app, ["run", str(small_log), "--out", str(tmp_path / "o"), "--view"])
    assert_one_error_line(r, "--view needs a display", "--record")
    assert not (tmp_path / "o").exists()


@pytest.fixture(scope="module")
def small_report(small_run, tmp_path_factory):
    out, _ = small_run
    page = tmp_path_factory.mktemp("first") / "r.html"
    r = runner.invoke(app, ["report", str(out), "--out", str(page)])
    assert r.exit_code == 0, r.output
    return page.read_text()


def test_report_evaluates_against_the_shipped_ground_truth_with_evo_plots(small_log, small_report):
    html = small_report
    assert "groundtruth_tum.txt (shipped with the log)" in html
    for ident in ("evo-xyz", "evo-ape", "evo-hist"):
        img = figure_png(html, ident)
        assert img.shape[0] > 150 and float(np.std(img[..., :3])) > 0.02, ident
    from submapslam.evaluation.run_figures import degenerate_alignment
    from submapslam.io.trajectory import read_tum

    straight = degenerate_alignment(read_tum(small_log / "groundtruth_tum.txt"), "se3")
    assert ("degenerate-alignment" in html) == (straight is not None)


def test_a_straight_reference_path_flags_the_alignment():
    from submapslam.evaluation.run_figures import degenerate_alignment
    from submapslam.geometry import se2_array_to_matrices
    from submapslam.trajectory import Trajectory

    line = Trajectory(np.arange(50.0), se2_array_to_matrices(np.c_[np.arange(50.0), np.zeros(50), np.zeros(50)]))
    assert "straight line" in degenerate_alignment(line, "se3")
    assert degenerate_alignment(line, "none") is None
    square = Trajectory(np.arange(4.0), se2_array_to_matrices(np.array([[0, 0, 0], [5, 0, 0], [5, 5, 0], [0, 5, 0.0]])))
    assert degenerate_alignment(square, "se3") is None


def test_the_loop_table_is_paginated_in_headless_chromium(tmp_path):
    import re

    from submapslam.evaluation import html_page as hp
    from submapslam.evaluation.html_report import _loop_table
    from submapslam.evaluation.run_record import RunRecord

    if CHROMIUM is None:
        pytest.skip("chromium not installed (apt-get install chromium)")
    loops = [{"submap_i": str(k), "submap_j": str(k + 3), "source": "spatial", "accepted": "1" if k % 3 else "0",
              "fitness": "0.5", "overlap": "0.5", "inlier_rmse": "0.05", "reason": "r"} for k in range(120)]
    page = tmp_path / "p.html"
    page.write_text(hp.page("t", "s", [("loops", _loop_table(RunRecord(folder="x", loops=loops)))]))
    proc, console = chromium(["--dump-dom", page.as_uri()], tmp_path)
    dom = proc.stdout
    assert not console
    body = re.search(r'<table id="loops".*?<tbody>(.*?)</tbody>', dom, re.S).group(1)
    rows = re.findall(r"<tr [^>]*>", body)
    assert len(rows) == 120 and sum('display: none' not in r for r in rows) == 50
    assert '<span class="count" id="lcount">120 shown</span>' in dom and "page 1 of 3" in dom


def test_the_map_view_is_large_with_layers_to_toggle(small_report):
    import re

    html = small_report
    base = figure_png(html, "map")
    assert base.shape[1] >= 1100  # about 1200 px wide, not 800
    for key, shown in (("accepted", True), ("rejected", False), ("submaps", False)):
        tag = re.search(rf'<img id="layer-{key}"[^>]*>', html).group(0)
        assert ("display:none" not in tag) == shown, key
        assert f"getElementById('layer-{key}')" in html  # its checkbox
        layer = figure_png(html, f"layer-{key}")
        assert layer.shape == base.shape  # stacked pixel for pixel on the map
        assert layer.shape[2] == 4 and float(np.mean(layer[..., 3] == 0)) > 0.5  # transparent around its lines
    anchors = figure_png(html, "layer-submaps")
    assert float(np.mean(anchors[..., 3] > 0)) > 1e-4  # the anchors are drawn


def test_a_run_worse_than_its_odometry_is_flagged():
    from submapslam.evaluation.html_report import worse_than_odometry

    rows = {"submapslam": {"ATE RMSE [m]": 0.30}, "odometry (before loop closure)": {"ATE RMSE [m]": 0.20}}
    assert "worse than its odometry" in worse_than_odometry(rows)
    rows["submapslam"]["ATE RMSE [m]"] = 0.10
    assert worse_than_odometry(rows) is None
    assert worse_than_odometry({"submapslam": {"ATE RMSE [m]": 0.3}}) is None


def test_synth_reports_progress_with_a_total(tmp_path):
    from datasets_synth import generate

    calls = []
    generate("rectangle", tmp_path / "s", laps=1, max_scans=30, progress=lambda done, total: calls.append((done, total)))
    assert calls and calls[-1] == (30, 30) and all(total == 30 for _, total in calls)


def test_report_evaluates_against_shipped_kitti_ground_truth(small_log, small_run, tmp_path, caplog):
    """A log that ships only KITTI poses (no stamps): line k is scan k, stamped as the reader
    stamps it, so the page carries the same ATE as against the TUM truth. A KITTI file of the
    wrong length is named in one warning and the page is still written."""
    import re
    import shutil

    from submapslam.api import evaluate_files

    log = tmp_path / "log"
    shutil.copytree(small_log, log)
    (log / "groundtruth_tum.txt").unlink()
    run = tmp_path / "run"
    shutil.copytree(small_run[0], run)
    prov = json.loads((run / "input.json").read_text())
    prov.update(path=str(log), absolute_path=str(log))
    (run / "input.json").write_text(json.dumps(prov))
    r = runner.invoke(app, ["report", str(run), "--out", str(tmp_path / "k.html")])
    assert r.exit_code == 0, r.output
    html = (tmp_path / "k.html").read_text()
    assert "groundtruth_kitti.txt (shipped with the log)" in html
    rmse = evaluate_files(run / "poses_tum.txt", small_log / "groundtruth_tum.txt")["ate"]["rmse"]
    assert re.search(rf"<td class=\"t\">submapslam</td><td>{rmse:.4g}</td>", html)
    lines = (log / "groundtruth_kitti.txt").read_text().splitlines()
    (log / "groundtruth_kitti.txt").write_text("\n".join(lines[:-5]) + "\n")
    r = runner.invoke(app, ["report", str(run), "--out", str(tmp_path / "short.html")])
    assert r.exit_code == 0, r.output
    assert "not evaluated" in caplog.text and f"{len(lines) - 5} poses for the {len(lines)} scans" in caplog.text
    assert "shipped with the log" not in (tmp_path / "short.html").read_text()
