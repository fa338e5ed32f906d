"""CLI smoke tests: every command, and the one-line error contract."""

import json

import pytest
from typer.testing import CliRunner

from submapslam import __version__
from submapslam.cli import app

from .cli_errors import assert_one_error_line

runner = CliRunner()


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "log"
    r = runner.invoke(app, ["synth", "rectangle", "--out", str(out), "--laps", "1", "--max-scans", "150"])
    assert r.exit_code == 0, r.output
    assert "150 scans of rectangle" in r.output
    return out


def one_line_error(result, *needles):
    assert result.exit_code == 1
    text = result.output.strip()
    assert "Traceback" not in text
    last = text.splitlines()[-1]
    assert last.startswith("error:"), text
    for n in needles:
        assert n in last, last


def test_version_and_dump_config(tmp_path):
    r = runner.invoke(app, ["--version"])
    assert r.exit_code == 0 and __version__ in r.output
    r = runner.invoke(app, ["dump-config"])
    assert r.exit_code == 0 and "odometry:" in r.output and "loops:" in r.output
    bad = tmp_path / "bad.yaml"
    bad.write_text("loops:\n  min_fitnes: 0.5\n")
    one_line_error(runner.invoke(app, ["dump-config", "--config", str(bad)]), "bad.yaml", "loops.min_fitnes")


def test_run_eval_compare(small_log, tmp_path):
    out = tmp_path / "out"
    r = runner.invoke(app, ["run", str(small_log), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "150 scans" in r.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scans"] == 150
    r = runner.invoke(app, ["eval", str(out / "poses_tum.txt"), str(small_log / "groundtruth_tum.txt"),
                            "--json", str(tmp_path / "e.json")])
    assert r.exit_code == 0, r.output
    figures = json.loads((tmp_path / "e.json").read_text())
    assert figures["ate"]["n"] == 150 and figures["ate"]["rmse"] < 0.5
    r = runner.invoke(app, ["eval", str(out / "poses_tum.txt"), str(small_log / "groundtruth_tum.txt"),
                            "--align", "sim3"])
    assert r.exit_code == 0 and "ATE" in r.output
    rep = tmp_path / "report"
    r = runner.invoke(app, ["compare", str(small_log / "groundtruth_tum.txt"), str(out / "poses_tum.txt"),
                            str(small_log / "odometry_tum.txt"), str(small_log / "groundtruth_kitti.txt"),
                            "--out", str(rep), "--label", "submapslam", "--label", "wheel", "--label", "truth"])
    # KITTI poses carry no timestamps (line indices instead): nothing matches the reference times
    assert_one_error_line(r, "no timestamps match within 0.02 s")
    r = runner.invoke(app, ["compare", str(small_log / "groundtruth_tum.txt"), str(out / "poses_tum.txt"),
                            str(small_log / "odometry_tum.txt"), str(small_log / "groundtruth_tum.txt"),
                            "--out", str(rep), "--label", "submapslam", "--label", "wheel", "--label", "truth"])
    assert r.exit_code == 0, r.output
    assert (rep / "trajectories.png").stat().st_size > 1000 and (rep / "ate.png").exists()
    rows = json.loads((rep / "report.json").read_text())
    assert set(rows) == {"submapslam", "wheel", "truth"}
    assert rows["truth"]["ate_rmse"] < 1e-6 and 0 < rows["submapslam"]["ate_rmse"] < 0.5
    assert "| submapslam |" in (rep / "report.md").read_text()


def test_eval_with_relations(small_log, tmp_path):
    from submapslam.geometry import inverse, matrix_to_se2
    from submapslam.io.trajectory import read_tum

    gt = read_tum(small_log / "groundtruth_tum.txt")
    lines = []
    for a, b in ((0, 10), (20, 60), (50, 140)):
        x, y, yaw = matrix_to_se2(inverse(gt.poses[a]) @ gt.poses[b])
        lines.append(f"{gt.timestamps[a]:.6f} {gt.timestamps[b]:.6f} {x} {y} 0 0 0 {yaw}")
    rel = tmp_path / "rel.txt"
    rel.write_text("\n".join(lines) + "\n")
    r = runner.invoke(app, ["eval", str(small_log / "groundtruth_tum.txt"), str(small_log / "groundtruth_tum.txt"),
                            "--relations", str(rel), "--json", str(tmp_path / "r.json")])
    assert r.exit_code == 0, r.output
    assert "relations (3)" in r.output
    assert json.loads((tmp_path / "r.json").read_text())["relations"]["trans_mean"] < 1e-4
    r = runner.invoke(app, ["eval", str(small_log / "odometry_tum.txt"), str(small_log / "groundtruth_tum.txt"),
                            "--derive-relations", "--json", str(tmp_path / "d.json")])
    assert r.exit_code == 0, r.output
    derived = json.loads((tmp_path / "d.json").read_text())["relations"]
    assert derived["n"] > 100 and derived["trans_mean"] > 1e-4  # the wheel odometry's relations are off
    assert_one_error_line(runner.invoke(app, ["eval", str(small_log / "groundtruth_tum.txt"),
                                              str(small_log / "groundtruth_tum.txt"), "--relations", str(rel),
                                              "--derive-relations"]), "not both")


def test_input_errors_are_one_line(small_log, tmp_path):
    one_line_error(runner.invoke(app, ["run", str(tmp_path / "nope.clf"), "--out", str(tmp_path / "o")]),
                   "nope.clf", "no such file")
    junk = tmp_path / "junk.xyz"
    junk.write_text("hello\n")
    one_line_error(runner.invoke(app, ["run", str(junk), "--out", str(tmp_path / "o")]), "cannot tell the log format")
    one_line_error(runner.invoke(app, ["run", str(junk), "--format", "kitti9", "--out", str(tmp_path / "o")]),
                   "unknown format 'kitti9'")
    cfg = tmp_path / "c.yaml"
    cfg.write_text("submaps:\n  max_scanz: 3\n")
    one_line_error(runner.invoke(app, ["run", str(small_log), "--out", str(tmp_path / "o"), "--config", str(cfg)]),
                   "unknown config key 'submaps.max_scanz'")
    garbled = tmp_path / "g.clf"
    garbled.write_text("FLASER 3 1.0 1.0 1.0 0 0 0 0 0 0 5.0 host 1.0\nFLASER 3 1.0 x 1.0 0 0 0 0 0 0 5.1 host 1.1\n")
    one_line_error(runner.invoke(app, ["run", str(garbled), "--out", str(tmp_path / "o")]), "g.clf:2")
    one_line_error(runner.invoke(app, ["eval", str(junk), str(junk)]), "junk.xyz")
    one_line_error(runner.invoke(app, ["synth", "moon", "--out", str(tmp_path / "m")]), "unknown world 'moon'")


def test_truncated_log_writes_results_then_fails(small_log, tmp_path):
    text = (small_log / "log.clf").read_text()
    cut = tmp_path / "cut.clf"
    cut.write_text(text[: int(len(text) * 0.6)])
    out = tmp_path / "out"
    r = runner.invoke(app, ["run", str(cut), "--out", str(out)])
    one_line_error(r, "cut.clf", "results cover")
    assert (out / "poses_tum.txt").exists() and (out / "summary.json").exists()


def test_demo_command(tmp_path, monkeypatch):
    import submapslam.cli.demo as demo

    real = demo.run_demo

    def small_demo(out, **kw):
        kw["laps"] = 1
        return real(out, **kw)

    monkeypatch.setattr(demo, "run_demo", small_demo)
    r = runner.invoke(app, ["demo", "--out", str(tmp_path / "d")])
    assert r.exit_code == 0, r.output
    assert "submapslam" in r.output and "wheel odometry" in r.output
    report = json.loads((tmp_path / "d" / "demo_report.json").read_text())
    assert report["ate"]["submapslam"]["rmse"] < report["ate"]["wheel odometry"]["rmse"]
    # it ends with the report (against the world's ground truth) and a picture, and says where they are
    import matplotlib.image as mpimg
    import numpy as np

    page, picture = tmp_path / "d" / "report.html", tmp_path / "d" / "map.png"
    assert report["report"] == str(page) and report["picture"] == str(picture)
    assert str(page) in r.output and str(picture) in r.output and "submapslam report" in r.output
    assert "Error against groundtruth_tum.txt" in page.read_text()
    img = mpimg.imread(picture)
    assert img.shape[0] > 200 and float(np.std(img[..., :3])) > 0.02  # a drawing, not one colour
