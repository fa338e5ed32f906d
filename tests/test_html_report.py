"""`submapslam report`: the page of a small 2D and a small 3D synthetic run, checked as text and
rendered in headless Chromium (console clean, map not blank, the loop table holds loops.csv)."""

import csv
import hashlib
import json
import re
from html import escape as html_escape

import numpy as np
import pytest
from typer.testing import CliRunner

from datasets_synth import generate
from submapslam.api import evaluate_files, report_run, run_log
from submapslam.cli import app
from submapslam.observer import RunObserver

from .cli_errors import assert_one_error_line
from .report_pages import (
    REFERENCE_FIGURES,
    UNCERTAINTY_FIGURES,
    assert_layer_has_ink,
    assert_not_blank,
    chromium,
    figure_png,
    needs_chromium,
    rendered_figures,
)

runner = CliRunner()


@pytest.fixture(scope="module", params=["2d", "3d"])
def reported_run(request, tmp_path_factory):
    """(run folder, report path, log folder, "2d"/"3d") of a small synthetic run with its report
    against the truth."""
    root = tmp_path_factory.mktemp(f"report{request.param}")
    if request.param == "2d":  # one lap of the rectangle (436 scans): loop hypotheses are tested
        log = generate("rectangle", root / "log", seed=0, laps=1, speed=2.0)
    else:
        log = generate("outdoor", root / "log", seed=0, laps=1, blocks=(1, 1), max_scans=80)
    watcher = CountingObserver()
    result, _ = run_log(log, root / "run", observer=watcher)
    watcher.result = result
    page = report_run(root / "run", ref=log / "groundtruth_tum.txt")
    _WATCHERS[request.param] = watcher
    return root / "run", page, log, request.param


class CountingObserver(RunObserver):
    """What the engine told its observer, for comparison with the result."""

    def __init__(self):
        self.scans, self.submaps, self.loops, self.result = [], [], [], None
        self.scan_points: list[int] = []

    def on_scan(self, index, timestamp, T_odom_base, points):
        self.scans.append((index, timestamp))
        self.scan_points.append(len(points))

    def on_submap(self, submap_id, T_world_submaps, points, T_world_odom):
        self.submaps.append((submap_id, len(T_world_submaps)))

    def on_loop(self, record, T_world_i, T_world_j):
        self.loops.append((record.i, record.j, record.source))


_WATCHERS: dict[str, CountingObserver] = {}


def test_the_observer_hears_every_scan_submap_and_hypothesis(reported_run):
    _, _, _, kind = reported_run
    w = _WATCHERS[kind]
    r = w.result
    assert [i for i, _ in w.scans] == list(range(r.n_scans))
    np.testing.assert_allclose([t for _, t in w.scans], r.timestamps)
    assert min(w.scan_points) > 0  # each scan's raw points (a run with no observer drops them once registered)
    assert w.submaps == [(k, k + 1) for k in range(r.n_submaps)]  # in order, with every anchor so far
    assert sorted(w.loops) == sorted((lp.i, lp.j, lp.source) for lp in r.loops)


def _loops_csv(run):
    with open(run / "loops.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def test_page_holds_what_the_run_wrote(reported_run):
    run, page, log, kind = reported_run
    html = page.read_text()
    loops = _loops_csv(run)
    body = re.search(r'<table id="loops".*?<tbody>(.*?)</tbody>', html, re.S)
    rows = re.findall(r"<tr [^>]*>(.*?)</tr>", body.group(1)) if body else []
    assert len(rows) == len(loops)
    for row, lp in zip(rows, loops):  # same order, same pair, same reason
        cells = re.findall(r"<td[^>]*>(.*?)</td>", row)
        assert cells[0] == lp["submap_i"] and cells[1] == lp["submap_j"] and cells[7] == html_escape(lp["reason"])
    if kind == "2d":
        assert len(loops) > 0, "the 2D lap must test loop hypotheses"
    # the error table carries the ATE the eval command computes, for the run and its odometry
    for name, file in (("submapslam", "poses_tum.txt"), ("odometry (before loop closure)", "odometry_tum.txt")):
        rmse = evaluate_files(run / file, log / "groundtruth_tum.txt")["ate"]["rmse"]
        assert re.search(rf"<td class=\"t\">{re.escape(name)}</td><td>{rmse:.4g}</td>", html), name
    # provenance: the log folder's listing hash and its scans
    prov = json.loads((run / "input.json").read_text())
    listing = "\n".join(f"{p.relative_to(log).as_posix()}\t{p.stat().st_size}"
                        for p in sorted(q for q in log.rglob("*") if q.is_file()))
    assert prov["sha256"] == hashlib.sha256(listing.encode()).hexdigest() and prov["sha256"] in html
    assert prov["scans"] == json.loads((run / "summary.json").read_text())["scans"]
    assert "mapping:" in html and "loops:" in html  # the effective config
    # self-contained: nothing is fetched at view time
    assert not re.search(r'(src|href)="(https?:)?//', html)
    img = figure_png(html, "map")
    assert img.std() > 0.05 and np.mean(img[..., :3].min(axis=2) < 0.9) > 0.05  # not a blank canvas


@needs_chromium
def test_console_check_sees_a_broken_page(tmp_path):
    """The console check below can fail: a page with a script error is caught."""
    bad = tmp_path / "bad.html"
    bad.write_text("<html><body><script>undefinedFunction();</script></body></html>")
    _, console = chromium(["--dump-dom", bad.as_uri()], tmp_path)
    assert any("undefinedFunction" in ln for ln in console)


@needs_chromium
def test_report_renders_in_headlesschromium(reported_run, tmp_path):
    import matplotlib.image as mpimg

    run, page, _, _ = reported_run
    shot = tmp_path / "shot.png"
    proc, console = chromium(["--hide-scrollbars", "--window-size=1280,1600", f"--screenshot={shot}",
                               "--dump-dom", page.as_uri()], tmp_path)
    assert proc.returncode == 0 and shot.is_file(), proc.stderr[-2000:]
    assert console == [], console
    img = mpimg.imread(shot)[..., :3]
    band = img[300:1500]  # below the overview: the map figure
    assert np.mean(band.min(axis=2) < 0.9) > 0.05 and len(np.unique((band * 15).astype(int).reshape(-1, 3), axis=0)) > 20
    loops = _loops_csv(run)
    dom = proc.stdout
    if loops:  # the filter script ran and counts every row of loops.csv
        assert f'<span class="count" id="lcount">{len(loops)} shown</span>' in dom
        body = re.search(r'<table id="loops".*?<tbody>(.*?)</tbody>', dom, re.S).group(1)
        assert len(re.findall(r"<tr ", body)) == len(loops)
    else:
        assert "No loop hypotheses were tested" in dom


@needs_chromium
def test_report_draws_the_map_and_evo_plots_in_headless_chromium(reported_run, tmp_path):
    """Each plot of a report against the truth is embedded, not blank, and drawn by Chromium."""
    _, page, _, _ = reported_run
    html = page.read_text()
    for ident in REFERENCE_FIGURES:
        assert_not_blank(figure_png(html, ident), ident)
    drawn, console = rendered_figures(page, tmp_path)
    assert console == [], console
    assert set(REFERENCE_FIGURES) | set(UNCERTAINTY_FIGURES) <= drawn, drawn


def test_report_shows_the_uncertainty_of_every_scan(reported_run, tmp_path):
    """poses_cov.txt on the page: σ along the path (x, y, yaw; 3D also z, roll, pitch) with the
    largest σ the file holds, and 3σ ellipses of scans along the trajectory as a map layer; a run
    folder without poses_cov.txt gets neither."""
    import shutil

    from submapslam.io.trajectory import read_tum_cov

    run, page, _, kind = reported_run
    html = page.read_text()
    assert_not_blank(figure_png(html, "uncertainty-sigma"), "σ along the path")
    assert_layer_has_ink(figure_png(html, "layer-uncertainty"), "scan ellipses")
    _, covs = read_tum_cov(run / "poses_cov.txt")
    sig = np.sqrt(np.diagonal(covs, axis1=1, axis2=2))
    shown = re.search(r"largest σ x, y \[m\]</t[dh]><td[^>]*>([^<]+)</td>", html)
    assert shown, "the largest σ is not listed"
    np.testing.assert_allclose([float(v) for v in shown.group(1).split(",")], sig[:, 3:5].max(axis=0), rtol=1e-3)
    assert ("largest σ z [m]" in html) == (kind == "3d")
    n = int(re.search(r"scan poses with 3σ ellipses \((\d+) along the path", html).group(1))
    assert 20 <= n <= 120
    bare = tmp_path / "bare"
    shutil.copytree(run, bare, ignore=shutil.ignore_patterns("poses_cov.txt", "report.html", "map.ply"))
    html = report_run(bare).read_text()
    assert all(f'id="{ident}"' not in html for ident in UNCERTAINTY_FIGURES)


def test_report_never_overwrites_a_file_of_the_users(reported_run, tmp_path):
    run, page, _, kind = reported_run
    if kind != "2d":
        pytest.skip("the command's file checks do not depend on the run; checked on the 2D run")
    mine = tmp_path / "notes.html"
    mine.write_text("<html>my notes</html>")
    r = runner.invoke(app, ["report", str(run), "--out", str(mine)])
    assert_one_error_line(r, "not a submapslam report")
    assert mine.read_text() == "<html>my notes</html>"
    r = runner.invoke(app, ["report", str(run), "--out", str(page)])  # its own earlier page is replaced
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["report", str(tmp_path)])
    assert_one_error_line(r, "not a results folder")
    bad = tmp_path / "bad_tum.txt"
    bad.write_text("1.0 2.0 3.0\n")
    before = page.read_bytes()
    r = runner.invoke(app, ["report", str(run), "--ref", str(bad), "--out", str(page)])
    assert_one_error_line(r, "bad_tum.txt")
    assert page.read_bytes() == before  # nothing written when the reference is unreadable


def test_pose_nees_against_interpolated_truth():
    from submapslam.evaluation.ekf_nees import pose_nees_against_truth

    truth_t = np.arange(0.0, 10.0, 1.0)
    truth = np.stack([truth_t, 2 * truth_t, np.full_like(truth_t, np.pi - 0.05)], axis=1)
    t = np.array([-1.0, 0.5, 4.25, 9.0, 12.0])  # the first and last lie outside the truth
    err = np.array([0.1, -0.2, 0.1])  # yaw error across the +-pi seam
    est = np.stack([t, 2 * t, np.full_like(t, np.pi - 0.05)], axis=1) + err
    est[:, 2] = (est[:, 2] + np.pi) % (2 * np.pi) - np.pi
    covs = np.tile(np.diag([0.01, 0.04, 0.0025]), (len(t), 1, 1))
    times, nees = pose_nees_against_truth(t, est, covs, truth_t, truth)
    assert np.allclose(times, [0.5, 4.25, 9.0])
    assert np.allclose(nees, 0.1**2 / 0.01 + 0.2**2 / 0.04 + 0.1**2 / 0.0025)


def test_ekf_run_report_shows_landmarks_and_provenance(tmp_path):
    from datasets_synth.landmarks import generate_landmark_log
    from submapslam.api import run_ekf_log

    log = generate_landmark_log(tmp_path / "syn.txt", seed=0, laps=1)
    run_ekf_log(log, tmp_path / "ekf")
    html = report_run(tmp_path / "ekf").read_text()
    assert "Stochastic map: landmarks" in html and "Loop hypotheses" not in html
    assert hashlib.sha256(log.read_bytes()).hexdigest() in html  # a log file is hashed whole
    assert figure_png(html, "map").std() > 0.05
