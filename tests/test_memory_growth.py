"""summary.json's memory growth per km: the slope of the resident set from the first km on."""

from __future__ import annotations

import numpy as np
import pytest

from submapslam.process_stats import memory_growth_mb_per_km


def test_the_slope_past_the_first_km_leaves_the_start_out():
    km = np.linspace(0.0, 4.0, 81)
    rss = np.where(km < 1.0, 120 + 150 * km, 270 + 12 * (km - 1.0))  # imports and first submaps, then 12 MiB/km
    rss = rss + np.where(np.arange(len(km)) % 2, 8.0, -8.0)  # the spread between submap closes
    assert memory_growth_mb_per_km(list(zip(km, rss))) == pytest.approx(12.0, abs=0.5)


def test_a_flat_drive_grows_by_nothing():
    km = np.linspace(0.0, 3.0, 31)
    assert memory_growth_mb_per_km(list(zip(km, np.full_like(km, 300.0)))) == pytest.approx(0.0, abs=1e-9)


def test_too_short_a_drive_has_no_figure():
    assert memory_growth_mb_per_km([(0.1, 200.0), (0.5, 210.0), (1.4, 230.0)]) is None  # 1.0-1.4 km: too little
    assert memory_growth_mb_per_km([]) is None
    assert memory_growth_mb_per_km(None) is None
    # the samples past the first km alone set the span
    assert memory_growth_mb_per_km([(0.2, 200.0), (1.0, 250.0), (2.1, 261.0)]) == pytest.approx(10.0)


def test_the_report_states_the_growth_under_its_memory_chart():
    from submapslam.evaluation.html_report import _performance

    km = np.linspace(0.0, 3.0, 31)
    by_km = [[float(k), 250.0 + 7.0 * k] for k in km]
    summary = {"wall_time_s": {"odometry": 1.0}, "wall_time_total_s": 1.0, "memory_mb_by_km": by_km,
               "memory_growth_mb_per_km": memory_growth_mb_per_km(by_km)}
    assert "grows 7.0 MiB/km from the first km on" in _performance(summary)
    del summary["memory_growth_mb_per_km"]  # a run written before the figure: the chart alone
    assert "MiB/km" not in _performance(summary) and "resident memory" in _performance(summary)
