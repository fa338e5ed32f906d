"""CLI: ekf --compare writes the comparison; ekf-nees writes the Monte Carlo study; errors are one line."""

import json

import typer
from typer.testing import CliRunner

from datasets_synth.landmarks import generate_landmark_log
from submapslam.cli.ekf import register

from .cli_errors import assert_one_error_line


def _app() -> typer.Typer:
    app = typer.Typer()
    register(app)
    return app


def test_ekf_compare_incremental_writes_comparison(tmp_path):
    path = generate_landmark_log(tmp_path / "syn.txt", seed=0, laps=1, sigma_range=0.02, odo_sigma=(0.005, 0.005, 0.002))
    out = tmp_path / "out"
    r = CliRunner().invoke(_app(), ["ekf", str(path), "--out", str(out), "--compare", "--incremental"])
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["comparison"]["ekf_vs_graph_landmark_max_m"] < 0.02
    assert summary["comparison"]["landmarks_shared"] == summary["features"]


def test_ekf_nees_command(tmp_path):
    out = tmp_path / "nees"
    r = CliRunner().invoke(_app(), ["ekf-nees", "--out", str(out), "--runs", "3", "--laps", "1", "--no-graph"])
    assert r.exit_code == 0, r.output
    doc = json.loads((out / "nees.json").read_text())
    lo, hi = doc["band_95"]
    assert lo < 3.0 < hi and doc["graph_mean_nees"] is None
    assert len(doc["ekf_mean_nees"]) > 100 and 0.0 <= doc["ekf_fraction_inside"] <= 1.0
    assert len(doc["ekf_fej_mean_nees"]) == len(doc["ekf_mean_nees"])
    assert (out / "nees.png").stat().st_size > 1000


def test_ekf_bad_log_is_one_red_line(tmp_path):
    bad = tmp_path / "bad.txt"
    bad.write_text("ODOMETRY 0 1 x 0 0 0.01 0 0 0.01 0 0.01\n")
    r = CliRunner().invoke(_app(), ["ekf", str(bad), "--out", str(tmp_path / "o")])
    assert_one_error_line(r, "bad.txt:1: malformed line")


def test_ekf_fej_divergence_is_one_line_and_writes_no_nan_results(tmp_path):
    from .conftest import shared_data

    out = tmp_path / "fej"
    r = CliRunner().invoke(_app(), ["ekf", str(shared_data("landmarks", "utias_mrclam7")), "--out", str(out), "--fej"])
    assert_one_error_line(r, "diverged at step", "first-estimates Jacobians")
    assert not (out / "landmarks.csv").exists()


def test_ekf_fej_on_a_synthetic_log_agrees_with_the_plain_filter(tmp_path):
    path = generate_landmark_log(tmp_path / "syn.txt", seed=0, laps=1, sigma_range=0.02, odo_sigma=(0.005, 0.005, 0.002))
    marks = {}
    for flag in ("--fej", "--no-fej"):
        out = tmp_path / flag
        r = CliRunner().invoke(_app(), ["ekf", str(path), "--out", str(out), flag])
        assert r.exit_code == 0, r.output
        assert json.loads((out / "summary.json").read_text())["jacobians"] == (
            "first estimates" if flag == "--fej" else "current estimates")
        rows = (out / "landmarks.csv").read_text().splitlines()[1:]
        marks[flag] = {int(r.split(",")[0]): tuple(map(float, r.split(",")[1:3])) for r in rows}
    assert marks["--fej"].keys() == marks["--no-fej"].keys() and len(marks["--fej"]) >= 10
    # small noise: both linearisations land on the same map within a few centimetres
    assert max(abs(a - b) for k in marks["--fej"] for a, b in zip(marks["--fej"][k], marks["--no-fej"][k])) < 0.05


def test_ekf_bad_credibility_rates_are_one_line(tmp_path):
    path = generate_landmark_log(tmp_path / "syn.txt", seed=0, laps=1)
    for option, value, message in (("--a", "0", "credibility learning rate a must be > 0, got 0.0"),
                                   ("--b", "-1", "credibility forgetting rate b must be > 0, got -1.0"),
                                   ("--remove-below", "2", "credibility remove_below must be in [0, 1], got 2.0")):
        out = tmp_path / option.strip("-")
        r = CliRunner().invoke(_app(), ["ekf", str(path), "--out", str(out), option, value])
        assert_one_error_line(r, message)
        assert not out.exists()


def test_ekf_unknown_log_format_is_one_line(tmp_path):
    path = generate_landmark_log(tmp_path / "syn.txt", seed=0, laps=1)
    r = CliRunner().invoke(_app(), ["ekf", str(path), "--out", str(tmp_path / "o"), "--format", "kitti"])
    assert_one_error_line(r, "syn.txt: unknown landmark log format 'kitti'; use mrclam, victoria, synth or cloud")


def test_ekf_reads_credibility_from_the_config_and_options_override_it(tmp_path):
    path = generate_landmark_log(tmp_path / "syn.txt", seed=0, laps=1)
    cfg = tmp_path / "c.yaml"
    cfg.write_text("ekf:\n  credibility:\n    a: -2\n")
    r = CliRunner().invoke(_app(), ["ekf", str(path), "--out", str(tmp_path / "o"), "--config", str(cfg)])
    assert_one_error_line(r, "credibility learning rate a must be > 0, got -2")
    cfg.write_text("ekf:\n  credibility:\n    a: 2.0\n")
    r = CliRunner().invoke(_app(), ["ekf", str(path), "--out", str(tmp_path / "o"), "--config", str(cfg),
                                    "--a", "0"])
    assert_one_error_line(r, "credibility learning rate a must be > 0, got 0.0")  # the option wins
    r = CliRunner().invoke(_app(), ["ekf", str(path), "--out", str(tmp_path / "o"), "--config", str(cfg)])
    assert r.exit_code == 0, r.output
    cfg.write_text("ekf:\n  credibilty: {}\n")
    r = CliRunner().invoke(_app(), ["ekf", str(path), "--out", str(tmp_path / "o2"), "--config", str(cfg)])
    assert_one_error_line(r, "c.yaml:2: unknown config key 'ekf.credibilty'")  # with its line
