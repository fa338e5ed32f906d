"""The real 2D CARMEN logs end to end at defaults, each against its corrected log (issue 25).

An accuracy guard, not a timing test: FR079 once went from 0.073 to 0.204 m and MIT CSAIL ran
worse than its own odometry while only Intel was measured. The thresholds sit a little above
what the code reaches (tools/bench_real2d.py, BENCHMARKS.md); the three runs take about 80-100 s
together on the 2-core CI machine. Skipped when ../shared/data is absent.
"""

import functools

import pytest

from submapslam.api import report_run, run_log
from submapslam.evaluation.derived_relations import derive_relations
from submapslam.evaluation.metrics import ate, relations_error
from submapslam.evaluation.scan_consistency import scan_matched_relations
from submapslam.io.scan_lookup import scans_at
from submapslam.io.trajectory import Trajectory, carmen_reference_trajectory
from submapslam.trajectory import Relations

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
# Intel 0.057-0.063, FR079 0.067-0.083, CSAIL 0.117-0.270 m (with the previous-scan check of stop 54,
# AVX2 and SSE here: Intel 0.060-0.063, FR079 0.072-0.077, CSAIL 0.097-0.116). Another CPU's SIMD
# kernels sum in another order, and a 2D run's discrete choices then part. Issue 25's targets, not
# met on every variant: Intel 0.06, FR079 0.07, CSAIL 0.10.
# The last two columns: the relations bound [m, deg] on the derived relations measured by scan
# matching (evaluation.scan_consistency.scan_matched_relations), issue 25's targets for Intel and
# FR079 and Cartographer's published 0.0319 m for CSAIL (the runs reach 0.008-0.017 m, 0.16-0.30 deg);
# and every how many derived relations are measured (in full: Intel's 1,145 take 14 s, FR079's 6,010 100 s).
LOGS = [
    ("intel.clf.bz2", "intel-corrected.log.gz", 0.073, (0.023, 0.45), 2),
    ("fr079.clf.bz2", "freiburg-079-corrected.log.gz", 0.095, (0.045, 0.45), 8),
    ("mit-csail.clf.bz2", "mit-csail-corrected.log.gz", 0.31, (0.0319, 0.45), 1),
]


@pytest.mark.parametrize(("log", "corrected", "bound", "relations_bound", "stride"), LOGS,
                         ids=[row[0].split(".")[0] for row in LOGS])
def test_real_log_reaches_its_accuracy_at_defaults(log, corrected, bound, relations_bound, stride, tmp_path):
    """ATE against the corrected log, and the relations error on its derived relations measured by
    matching their scans, where the run must also beat the corrected log itself (whose own error
    there is 0.022-0.026 m, 0.39-0.50 deg). MIT CSAIL's run (the shortest) also writes its files and
    its report against the corrected log, which must carry the map and evo's plots, drawn by
    headless Chromium (when installed)."""
    raw = shared_data("carmen", log)
    ref = carmen_reference_trajectory(shared_data("carmen", "corrected", corrected), raw)
    with_report = log.startswith("mit-csail")
    result, _ = run_log(raw, tmp_path / "run" if with_report else None)
    slam = ate(Trajectory(result.timestamps, result.poses), ref)
    odo = ate(Trajectory(result.timestamps, result.odometry_poses), ref)
    assert slam["n"] >= 0.99 * len(ref)  # every reference pose found its scan
    assert slam["rmse"] <= bound, f"{log}: ATE {slam['rmse']:.3f} m > {bound} m (odometry {odo['rmse']:.3f} m)"
    assert slam["rmse"] <= odo["rmse"] / 2  # the loops help: 3-10x on these logs and variants
    derived = derive_relations(ref)
    derived = Relations(derived.t_a[::stride], derived.t_b[::stride], derived.T_a_b[::stride])
    matched, counts = scan_matched_relations(ref, derived, functools.partial(scans_at, raw))
    assert counts["matched"] >= 0.4 * len(derived)
    run_rel = relations_error(Trajectory(result.timestamps, result.poses), matched)
    ref_rel = relations_error(ref, matched)
    assert run_rel["trans_mean"] <= relations_bound[0] and run_rel["rot_mean_deg"] <= relations_bound[1], run_rel
    assert run_rel["trans_mean"] < ref_rel["trans_mean"] and run_rel["rot_mean_deg"] < ref_rel["rot_mean_deg"]
    if with_report:
        page = report_run(tmp_path / "run", ref=shared_data("carmen", "corrected", corrected), raw_log=raw)
        html = page.read_text()
        assert f"{slam['rmse']:.4g}" in html  # the error table holds this ATE
        # the log's own scans judge the run and the corrected log alike: the corrected log is the less consistent
        assert 'id="scan-check"' in html and "no more consistent with the log's scans than this run" in html
        for ident in REFERENCE_FIGURES:
            assert_not_blank(figure_png(html, ident), ident)
        if CHROMIUM is not None:
            drawn, console = rendered_figures(page, tmp_path)
            assert console == [] and set(REFERENCE_FIGURES) <= drawn, (console, drawn)
