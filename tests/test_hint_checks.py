"""Manual loop hints checked against the log: one message per hint the log cannot use."""

import numpy as np
from typer.testing import CliRunner

from submapslam.cli import app
from submapslam.io.hints import hint_problems, read_hint_file

from .test_input_checks import small_carmen_log


def test_each_unusable_hint_gets_one_message_naming_its_line(tmp_path):
    p = tmp_path / "hints.txt"
    p.write_text("# ok, then five unusable ones\n2 40\n10 99999\n10 10\n105.0 300.0\n102.0 102.01\n3 5\n"
                 "100.5 103.5\n")
    stamps = 100.0 + 0.1 * np.arange(50)  # 100.0 .. 104.9
    submaps = [list(range(0, 10)), list(range(10, 50))]
    problems = hint_problems(read_hint_file(p), stamps, submaps)
    assert len(problems) == 5, problems
    assert problems[0].startswith("hint on line 3 (10 99999): scan 99999 is beyond the log's 50 scans")
    assert problems[1] == "hint on line 4 (10 10): pairs a scan with itself"
    assert problems[2].startswith("hint on line 5 (105.000 300.000): timestamp 300.000 is outside the log")
    assert problems[3].startswith("hint on line 6") and "nearest to scan 20: pairs a scan with itself" in problems[3]
    assert problems[4].startswith("hint on line 7 (3 5): scans 3 and 5 are in the same submap (0)")
    # every hint usable: nothing to say
    assert hint_problems(read_hint_file(p)[:1], stamps, submaps) == []
    # a timestamp inside the log span but far from every scan (a gap in the log)
    gap = np.r_[stamps, 200.0 + 0.1 * np.arange(10)]
    p.write_text("150.0 100.5\n")
    (msg,) = hint_problems(read_hint_file(p), gap)
    assert "timestamp 150.000 is 45.1 s from the nearest scan" in msg


def test_run_warns_about_unusable_hints_without_verbose(tmp_path):
    log = small_carmen_log(tmp_path / "x.clf")
    hints = tmp_path / "h.txt"
    hints.write_text("10 99999\n4 4\n")
    r = CliRunner().invoke(app, ["run", str(log), "--out", str(tmp_path / "o"), "--hints", str(hints)])
    assert r.exit_code == 0, r.output
    warnings = [ln for ln in r.stderr.splitlines() if ln.startswith("warning:")]
    assert warnings == ["warning: hint on line 1 (10 99999): scan 99999 is beyond the log's 12 scans (indices 0..11)",
                        "warning: hint on line 2 (4 4): pairs a scan with itself"], r.stderr
    import json

    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["hint_problems"] == [w.removeprefix("warning: ") for w in warnings]


def test_a_hint_timestamp_before_the_log_is_not_paired_with_the_first_scan():
    """The hint reported as outside the log is not used either (it used to become scan 0)."""
    from submapslam.pipeline import _hint_scan

    stamps = 100.0 + 0.1 * np.arange(50)
    assert _hint_scan(50.0, False, stamps) is None
    assert _hint_scan(99.5, False, stamps) == 0  # within a second of the first scan: that scan
    assert _hint_scan(102.04, False, stamps) == 20
