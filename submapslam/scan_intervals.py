"""The time between a log's scans, and the motion model's guesses that follow from it.

KISS-ICP's constant-velocity model predicts each scan one interval's motion on from the last,
whatever the time between them. Keyframes 0.2-0.5 s apart, dropped frames and stops break that.
:class:`ScanIntervals` keeps the recent intervals; :func:`paced` carries a motion on at its pace
over another interval, and :func:`gap_steps` lays out the guesses over a long one (the motion at
the paces between one interval's and the whole gap's, bent into turns). Numpy only; poses are
``(4, 4)`` steps in the frame of the last pose, times in seconds.
"""

from __future__ import annotations

import statistics
from collections import deque
from collections.abc import Callable

import numpy as np

from .geometry import blend_poses, blend_poses_many, se2_to_matrix

#: [share] intervals between scans that differ by less than this from the one the last motion spans
#: are taken as equal (a 10 Hz log's jitter): the motion is predicted as it was
PACE_TOLERANCE = 0.1
#: a log whose recent intervals (but for the longest and shortest tenth) lie within this factor of
#: each other runs at a steady rate
STEADY_RATE = 1.5


class ScanIntervals:
    """The intervals [s] between a log's scans, as they come (:meth:`add`)."""

    def __init__(self, history: int = 50) -> None:
        self._last_stamp: float | None = None
        self._recent: deque[float] = deque(maxlen=history)  # the last intervals, this scan's included
        self.last: float | None = None  # into the newest scan (what the motion into it will span)
        self.before: float | None = None  # the one before it (what the last motion spans)
        self.shortest: float | None = None  # of all so far

    def add(self, timestamp: float) -> None:
        """The next scan's ``timestamp`` [s]; an interval is counted only when time moved on."""
        previous, self._last_stamp = self._last_stamp, timestamp
        self.before = self.last
        if previous is not None and timestamp > previous:
            self.last = timestamp - previous
            self._recent.append(self.last)
            self.shortest = self.last if self.shortest is None else min(self.shortest, self.last)

    def usual(self) -> float | None:
        """The median of the recent intervals [s] (a sweep lasts no longer), or None."""
        return statistics.median(self._recent) if self._recent else None

    def pace(self) -> float | None:
        """The newest interval over the one before it, or None before there are two."""
        if self.last is None or self.before is None or self.before <= 0.0:
            return None
        return self.last / self.before

    def steady(self) -> bool:
        """Whether the intervals before the newest lie within :data:`STEADY_RATE` of each other but
        for a few long or short ones (lost scans): a log at a fixed rate, not keyframes."""
        recent = list(self._recent)[:-1]
        if len(recent) < 5:
            return False
        low, high = np.percentile(recent, [10.0, 90.0])
        return bool(high <= STEADY_RATE * low)


def paced(step: np.ndarray, pace: float | None, ratio: float) -> np.ndarray:
    """``step`` carried on at its pace over an interval ``pace`` times the one it spans (blended
    along its geodesic), when ``pace`` lies within :data:`PACE_TOLERANCE` of 1 and ``ratio``
    (bounds excluded); else ``step`` itself (the same object: one interval's motion)."""
    if pace is None or abs(pace - 1.0) <= PACE_TOLERANCE or not 1.0 / ratio < pace < ratio:
        return step
    return blend_poses(np.eye(4), step, pace)


def bent(step: np.ndarray, turn: float) -> np.ndarray:
    """``step`` ``(4, 4)`` bent into an arc of the same length that turns by ``turn`` [rad] more
    about its start's vertical: its x-y translation turned by half of it and shortened to the arc's
    chord, its rotation turned by all of it."""
    half = 0.5 * turn
    c, s = np.cos(half), np.sin(half)
    out = step.copy()
    out[:2, 3] = (np.sin(half) / half) * (np.array([[c, -s], [s, c]]) @ step[:2, 3])
    out[:3, :3] = se2_to_matrix(0.0, 0.0, turn)[:3, :3] @ step[:3, :3]
    return out


def _paces_down(step: np.ndarray, over: float, floor: float, spacing_m: float) -> np.ndarray:
    """The paces ``(K,)`` from ``over`` down towards ``floor`` (``floor`` left out), times the
    interval ``step`` spans, that move ``step``'s end ``spacing_m`` [m] apart."""
    reach = (over - floor) * float(np.linalg.norm(step[:3, 3]))
    return np.linspace(over, floor, int(np.ceil(reach / spacing_m)) + 1)[:-1]


def _paced_and_bent(step: np.ndarray, paces: np.ndarray, turns_deg: tuple[float, ...]) -> list[np.ndarray]:
    """``step`` ``(4, 4)`` at each of ``paces`` (blended along its geodesic), then the same bent by
    each of ``turns_deg`` (:func:`bent`)."""
    steps = list(blend_poses_many(np.eye(4), step, paces))
    return steps + [bent(s, np.radians(t)) for t in turns_deg for s in steps]


def gap_steps(step: np.ndarray, over: float, spacing_m: float, turns_deg: tuple[float, ...],
              standing: bool) -> list[np.ndarray]:
    """Guesses ``(4, 4)`` for a scan ``over`` times the interval ``step`` spans after the last:
    ``step`` carried on at its pace (``over < 1``: the scan after a gap), or at the paces from the
    whole interval's down towards one interval's, ``spacing_m`` [m] apart; then the same bent by
    each of ``turns_deg`` (:func:`bent`); and after a long interval with ``standing``, last, no
    motion (a stop)."""
    paces = np.array([over]) if over < 1.0 else _paces_down(step, over, 1.0, spacing_m)
    return _paced_and_bent(step, paces, turns_deg) + ([np.eye(4)] if standing and over > 1.0 else [])


def restart_steps(step: np.ndarray, over: float, spacing_m: float, turns_deg: tuple[float, ...]) -> list[np.ndarray]:
    """Guesses ``(4, 4)`` for the first scan after a stop: ``step``, the last motion before it,
    carried on at the paces from its own over this interval (``over`` times the one it spans)
    down towards none, ``spacing_m`` [m] apart; then the same bent by each of ``turns_deg``
    (:func:`bent`). A keyframed log pauses while the sensor stands and goes on where it moves
    again, often at the pace it had."""
    return _paced_and_bent(step, _paces_down(step, over, 0.0, spacing_m), turns_deg)


def most_promising(guesses: list[np.ndarray], fit: Callable[[np.ndarray], float], keep: int) -> list[np.ndarray]:
    """The ``keep`` of ``guesses`` with the highest ``fit``, in their order (on a tie the earlier)."""
    fits = [fit(g) for g in guesses]
    ranked = sorted(range(len(guesses)), key=lambda k: (-fits[k], k))[:keep]
    return [guesses[k] for k in sorted(ranked)]
