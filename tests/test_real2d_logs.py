"""The real 2D CARMEN logs end to end at defaults, each against its corrected log (issue 25).

An accuracy guard, not a timing test: FR079 once went from 0.073 to 0.204 m and MIT CSAIL ran
worse than its own odometry while only Intel was measured. The thresholds sit a little above
what the code reaches (tools/bench_real2d.py, BENCHMARKS.md); the three runs take about 80-100 s
together on the 2-core CI machine. Skipped when ../shared/data is absent.
"""

import pytest

from submapslam.api import report_run, run_log
from submapslam.evaluation.metrics import ate
from submapslam.io.trajectory import Trajectory, carmen_reference_trajectory

from .conftest import shared_data
from .report_pages import (
    CHROMIUM,
    REFERENCE_FIGURES,
    assert_not_blank,
    figure_png,
    rendered_figures,
)

# log, corrected log, ATE bound [m]: ~15 % above the worst the code reaches over the numeric
# variants of BENCHMARKS.md ("The same code on other CPUs", "Ambiguous correlative peaks"):
# Intel 0.057-0.063, FR079 0.067-0.083, CSAIL 0.117-0.270 m. Another CPU's SIMD kernels sum in
# another order, and a 2D run's discrete choices then part. Issue 25's targets, not met on every
# variant: Intel 0.06, FR079 0.07, CSAIL 0.10.
LOGS = [
    ("intel.clf.bz2", "intel-corrected.log.gz", 0.073),
    ("fr079.clf.bz2", "freiburg-079-corrected.log.gz", 0.095),
    ("mit-csail.clf.bz2", "mit-csail-corrected.log.gz", 0.31),
]


@pytest.mark.parametrize(("log", "corrected", "bound"), LOGS, ids=[row[0].split(".")[0] for row in LOGS])
def test_real_log_reaches_its_accuracy_at_defaults(log, corrected, bound, tmp_path):
    """MIT CSAIL's run (the shortest) also writes its files and its report against the corrected
    log, which must carry the map and evo's plots, drawn by headless Chromium (when installed)."""
    raw = shared_data("carmen", log)
    ref = carmen_reference_trajectory(shared_data("carmen", "corrected", corrected), raw)
    with_report = log.startswith("mit-csail")
    result, _ = run_log(raw, tmp_path / "run" if with_report else None)
    slam = ate(Trajectory(result.timestamps, result.poses), ref)
    odo = ate(Trajectory(result.timestamps, result.odometry_poses), ref)
    assert slam["n"] >= 0.99 * len(ref)  # every reference pose found its scan
    assert slam["rmse"] <= bound, f"{log}: ATE {slam['rmse']:.3f} m > {bound} m (odometry {odo['rmse']:.3f} m)"
    assert slam["rmse"] <= odo["rmse"] / 2  # the loops help: 3-10x on these logs and variants
    if with_report:
        page = report_run(tmp_path / "run", ref=shared_data("carmen", "corrected", corrected), raw_log=raw)
        html = page.read_text()
        assert f"{slam['rmse']:.4g}" in html  # the error table holds this ATE
        for ident in REFERENCE_FIGURES:
            assert_not_blank(figure_png(html, ident), ident)
        if CHROMIUM is not None:
            drawn, console = rendered_figures(page, tmp_path)
            assert console == [] and set(REFERENCE_FIGURES) <= drawn, (console, drawn)
