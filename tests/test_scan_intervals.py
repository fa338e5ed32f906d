"""submapslam.scan_intervals: the intervals between scans, and the motion model's guesses over them."""

from __future__ import annotations

import numpy as np

from submapslam.geometry import se2_to_matrix
from submapslam.scan_intervals import (
    ScanIntervals,
    bent,
    gap_steps,
    most_promising,
    paced,
    restart_steps,
)


def _intervals(times) -> ScanIntervals:
    out = ScanIntervals()
    for t in times:
        out.add(t)
    return out


def test_the_pace_is_the_newest_interval_over_the_one_before():
    intervals = _intervals([0.0, 0.1, 0.2, 1.2])
    assert np.isclose(intervals.last, 1.0) and np.isclose(intervals.before, 0.1)
    assert np.isclose(intervals.pace(), 10.0)
    assert _intervals([0.0, 0.1]).pace() is None  # one interval: nothing to compare
    still = _intervals([0.0, 0.1, 0.2, 0.2])  # a repeated time moves nothing on
    assert np.isclose(still.pace(), 1.0)


def test_a_steady_log_stays_steady_through_a_few_lost_scans_and_keyframes_do_not():
    ten_hz = list(np.arange(40) * 0.1)
    assert _intervals([*ten_hz, 5.0, 5.1]).steady()  # 1 s lost once: still a steady log
    rng = np.random.default_rng(0)
    keyframes = np.cumsum(rng.uniform(0.2, 0.5, 40))
    assert not _intervals(keyframes).steady()
    assert not _intervals([0.0, 0.1, 0.2]).steady()  # too few to say


def test_a_motion_is_paced_only_outside_the_jitter_and_inside_the_ratio():
    step = se2_to_matrix(1.0, 0.0, np.radians(2.0))
    assert paced(step, 1.05, 3.0) is step  # a 10 Hz log's jitter: as it was
    assert paced(step, None, 3.0) is step
    assert paced(step, 3.5, 3.0) is step  # a gap: searched, not predicted
    twice = paced(step, 2.0, 3.0)
    assert np.allclose(twice[:2, 3], [2.0, 0.0]) and np.isclose(np.degrees(np.arctan2(twice[1, 0], twice[0, 0])), 4.0)


def test_a_step_bent_into_a_quarter_circle_ends_on_its_chord():
    step = se2_to_matrix(np.pi / 2, 0.0, 0.0)  # an arc of length pi/2: radius 1
    quarter = bent(step, np.pi / 2)
    assert np.allclose(quarter[:2, 3], [1.0, 1.0]) and np.isclose(np.arctan2(quarter[1, 0], quarter[0, 0]), np.pi / 2)


def test_guesses_over_a_gap_span_the_paces_then_turn_and_may_stand():
    step = se2_to_matrix(0.5, 0.0, 0.0)
    guesses = gap_steps(step, 11.0, 1.0, (10.0, -10.0), standing=True)
    straight = 5  # 5 m more than one step, 1 m apart: 11, 9, 7, 5 and 3 steps
    assert len(guesses) == 3 * straight + 1 and np.allclose(guesses[-1], np.eye(4))
    assert np.isclose(guesses[0][0, 3], 5.5) and np.isclose(guesses[straight - 1][0, 3], 1.5)
    after = gap_steps(step, 0.1, 1.0, (), standing=True)  # the scan after a gap: the step at its pace, no stop
    assert len(after) == 1 and np.isclose(after[0][0, 3], 0.05)


def test_guesses_after_a_stop_go_from_the_pace_before_it_down_towards_none():
    step = se2_to_matrix(3.6, 0.0, 0.0)  # 3.6 m in 0.3 s before the stop; the scan after it 0.5 s on
    guesses = restart_steps(step, 0.5 / 0.3, 2.0, (10.0,))
    assert len(guesses) == 2 * 3  # 6 m, 4 m, 2 m; then each turned
    assert np.allclose([g[0, 3] for g in guesses[:3]], [6.0, 4.0, 2.0])
    assert not any(np.allclose(g, np.eye(4)) for g in guesses)  # no motion is the prediction's already
    assert np.isclose(np.degrees(np.arctan2(guesses[3][1, 0], guesses[3][0, 0])), 10.0)


def test_the_most_promising_keep_their_order():
    guesses = [np.full((4, 4), float(k)) for k in range(5)]
    fits = {0: 0.1, 1: 0.9, 2: 0.5, 3: 0.9, 4: 0.2}
    chosen = most_promising(guesses, lambda g: fits[int(g[0, 0])], 3)
    assert [int(g[0, 0]) for g in chosen] == [1, 2, 3]
