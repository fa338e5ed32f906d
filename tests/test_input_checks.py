"""Input problems found by trying the tool as a new user would (issue 12): each gives a correct
result or one clear line."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from submapslam.cli import app
from submapslam.errors import InputError
from submapslam.io.ply import write_ply
from submapslam.io.registry import open_log

from .cli_errors import assert_one_error_line
from .conftest import REPO
from .test_carmen_records import flaser_line, robotlaser_line

runner = CliRunner()


def room_ranges(n=181, pose=(0.0, 0.0, 0.0)):
    """Ranges of a FLASER scan in a 10 m x 6 m room centred on the origin, from ``pose``."""
    x, y, t = pose
    out = []
    for a in np.linspace(-math.pi / 2, math.pi / 2, n) + t:
        c, s = math.cos(a), math.sin(a)
        d = min(((5 - x) / c if c > 1e-9 else (-5 - x) / c if c < -1e-9 else 1e9),
                ((3 - y) / s if s > 1e-9 else (-3 - y) / s if s < -1e-9 else 1e9))
        out.append(d)
    return out


def small_carmen_log(path, n=12, record="FLASER"):
    lines = []
    for k in range(n):
        pose = (-1.0 + 0.1 * k, 0.0, 0.0)
        ranges = room_ranges(pose=pose)
        if record == "FLASER":
            lines.append(flaser_line(ranges, pose, ts=100.0 + 0.1 * k))
        else:
            lines.append(robotlaser_line(ranges, robot=pose, laser_offset=(0, 0, 0), ts=100.0 + 0.1 * k))
    path.write_text("# CARMEN log\n" + "".join(lines))
    return path


def bin_folder(root, n=4):
    (root / "scans").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for k in range(n):
        pts = np.c_[rng.uniform(-10, 10, (500, 3)), np.zeros(500)].astype(np.float32)
        pts.tofile(root / "scans" / f"{k:06d}.bin")
    return root


def test_a_stray_ply_beside_the_scans_folder_does_not_make_a_one_scan_log(tmp_path):
    root = bin_folder(tmp_path / "log")
    write_ply(root / "preview.ply", np.zeros((10, 3)))
    reader = open_log(root)
    assert len(reader) == 4 and reader.scan_dir == root / "scans"


def test_header_only_scan_files_are_refused_up_front(tmp_path):
    for k in range(3):
        write_ply(tmp_path / f"{k}.ply", np.zeros((0, 3)))
    with pytest.raises(InputError, match="none of the 3 scan files holds a point"):
        open_log(tmp_path)
    write_ply(tmp_path / "3.ply", np.ones((5, 3)))  # one scan with points: a log
    assert len(open_log(tmp_path)) == 4


def test_odd_size_bin_names_its_real_size_and_can_be_skipped(tmp_path):
    root = bin_folder(tmp_path / "log")
    bad = root / "scans" / "000002.bin"
    bad.write_bytes(bad.read_bytes()[:-6])
    size = bad.stat().st_size
    with pytest.raises(InputError, match=rf"000002\.bin: size {size} bytes is not a whole number of 16-byte"):
        list(open_log(root))
    reader = open_log(root, skip_bad=True)
    scans = list(reader)
    assert [s.index for s in scans] == [0, 1, 2]
    assert reader.log_info["skipped_records"] == 1 and reader.log_info["skipped_files"] == ["000002.bin"]
    r = runner.invoke(app, ["run", str(root), "--out", str(tmp_path / "o"), "--skip-bad", "--no-loops"])
    assert r.exit_code == 0, r.output
    assert "skipped 1 damaged record(s): 000002.bin" in r.stdout
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["skipped_files"] == ["000002.bin"]


def test_forced_formats_that_do_not_fit_the_path_say_why(tmp_path):
    log = small_carmen_log(tmp_path / "x.clf", n=2)
    r = runner.invoke(app, ["run", str(log), "--format", "cloud_folder", "--out", str(tmp_path / "o")])
    assert_one_error_line(r, "x.clf", "is a file, not a folder of scans")
    folder = bin_folder(tmp_path / "log")
    r = runner.invoke(app, ["run", str(folder), "--format", "carmen", "--out", str(tmp_path / "o")])
    line = assert_one_error_line(r, "is a folder, not a CARMEN log file")
    assert "compressed" not in line
    scan = folder / "scans" / "000000.bin"
    r = runner.invoke(app, ["run", str(scan), "--format", "carmen", "--out", str(tmp_path / "o")])
    assert_one_error_line(r, "000000.bin:1: binary data, not a text CARMEN log")


def test_run_reports_the_record_read_and_takes_laser_and_skip_bad(tmp_path):
    log = small_carmen_log(tmp_path / "fr.log", record="ROBOTLASER1")
    out = tmp_path / "out"
    r = runner.invoke(app, ["run", str(log), "--out", str(out), "--no-loops"])
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scans"] == 12 and summary["laser_record"] == "ROBOTLASER1" and summary["skipped_records"] == 0
    r = runner.invoke(app, ["run", str(log), "--out", str(tmp_path / "o2"), "--laser", "flaser"])
    assert_one_error_line(r, "no FLASER lines", "it holds ROBOTLASER1")
    r = runner.invoke(app, ["run", str(log), "--out", str(tmp_path / "o3"), "--laser", "sick"])
    assert_one_error_line(r, "unknown CARMEN laser 'sick'")
    lines = log.read_text().splitlines(keepends=True)
    lines[5] = lines[5][:40] + "\n"  # one damaged record (line 6)
    damaged = tmp_path / "damaged.log"
    damaged.write_text("".join(lines))
    r = runner.invoke(app, ["run", str(damaged), "--out", str(tmp_path / "o4"), "--no-loops"])
    assert_one_error_line(r, "damaged.log:6", "--skip-bad")
    r = runner.invoke(app, ["run", str(damaged), "--out", str(tmp_path / "o5"), "--no-loops", "--skip-bad"])
    assert r.exit_code == 0, r.output
    summary = json.loads((tmp_path / "o5" / "summary.json").read_text())
    assert summary["scans"] == 11 and summary["skipped_records"] == 1 and summary["skipped_record_lines"] == [6]


def test_an_input_error_is_printed_once(tmp_path):
    """In a real process (logging configured by the CLI): the error line, not also a warning."""
    log = small_carmen_log(tmp_path / "x.clf", n=6)
    text = log.read_text()
    log.write_text(text[: len(text) - 300])
    r = subprocess.run([sys.executable, "-m", "submapslam", "run", str(log), "--out", str(tmp_path / "o"),
                        "--no-loops"], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert r.returncode == 1
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "x.clf:7" in lines[0], r.stderr


def test_one_scan_file_given_as_the_log_names_its_folder(tmp_path):
    root = bin_folder(tmp_path / "log")
    one = root / "scans" / "000001.bin"
    r = runner.invoke(app, ["run", str(one), "--out", str(tmp_path / "o")])
    assert_one_error_line(r, "000001.bin: is one scan; a log of scans is the folder holding them", str(one.parent))


def test_ekf_on_a_missing_log_is_one_line(tmp_path):
    r = runner.invoke(app, ["ekf", str(tmp_path / "nope"), "--out", str(tmp_path / "o")])
    assert_one_error_line(r, "nope: no such file or directory")


def test_a_nan_in_an_mrclam_table_is_one_line(tmp_path):
    import shutil

    from submapslam.io.landmark_logs import read_landmark_log

    from .conftest import shared_data

    src = shared_data("landmarks", "utias_mrclam7")
    folder = tmp_path / "mrclam"
    shutil.copytree(src, folder)
    measurements = folder / "Robot1_Measurement.dat"
    lines = measurements.read_text().splitlines(keepends=True)
    k = next(i for i, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")) + 3
    fields = lines[k].split()
    lines[k] = " ".join([fields[0], fields[1], "nan", *fields[3:]]) + "\n"
    measurements.write_text("".join(lines))
    with pytest.raises(InputError, match=rf"Robot1_Measurement\.dat:{k + 1}: NaN/inf value"):
        read_landmark_log(folder)
