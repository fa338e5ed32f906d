"""Synthetic landmark worlds for the stochastic map: point landmarks around a loop, noisy
odometry, range-bearing detections with misses, clutter and landmarks that disappear.

Written in gtsam's ``victoria_park.txt`` format (ODOMETRY / LANDMARK lines), so the same reader
loads real and synthetic landmark logs; a ``landmarks_truth.csv`` and ``poses_truth.txt`` hold
the ground truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .motion import loop_path

CLUTTER_ID_BASE = 100000  # clutter detections get unique ids from here (seen once, then forgotten)


def generate_landmark_log(out: str | Path, *, seed: int = 0, laps: int = 2, n_landmarks: int = 20,
                          size: tuple[float, float] = (20.0, 12.0), step: float = 0.5, max_range: float = 8.0,
                          sigma_range: float = 0.05, odo_sigma: tuple[float, float, float] = (0.02, 0.01, 0.005),
                          p_miss: float = 0.0, clutter_rate: float = 0.0, vanish_fraction: float = 0.0) -> Path:
    """Write ``out`` (a victoria_park-format file) and truth files beside it; return ``out``.

    ``vanish_fraction`` of the landmarks disappear from the world half way through the run.
    Bearing sigma is ``sigma_range / sqrt(10)`` (the convention of gtsam's loader).
    """
    rng = np.random.default_rng(seed)
    W, H = size
    waypoints = np.array([(0, 0), (W, 0), (W, H), (0, H)], dtype=float)
    path = loop_path(waypoints, laps, step)
    lm = np.c_[rng.uniform(-3, W + 3, n_landmarks), rng.uniform(-3, H + 3, n_landmarks)]
    vanish = set(rng.choice(n_landmarks, int(round(vanish_fraction * n_landmarks)), replace=False).tolist())
    Q = np.diag(np.square(odo_sigma))
    sigma_b = sigma_range / np.sqrt(10)
    lines = []
    half = len(path) // 2
    truth_lines = []
    for k in range(len(path)):
        x, y, th = path[k]
        truth_lines.append(f"{k} {x:.9f} {y:.9f} {th:.9f}")
        if k > 0:
            x0, y0, t0 = path[k - 1]
            c, s = np.cos(t0), np.sin(t0)
            u = np.array([c * (x - x0) + s * (y - y0), -s * (x - x0) + c * (y - y0), th - t0])
            un = u + rng.multivariate_normal(np.zeros(3), Q)
            q = Q
            lines.append(f"ODOMETRY {k - 1} {k} {un[0]:.9g} {un[1]:.9g} {un[2]:.9g} "
                         f"{q[0, 0]:.9g} 0 0 {q[1, 1]:.9g} 0 {q[2, 2]:.9g}")
        d = lm - [x, y]
        r = np.hypot(d[:, 0], d[:, 1])
        b = (np.arctan2(d[:, 1], d[:, 0]) - th + np.pi) % (2 * np.pi) - np.pi
        for i in np.nonzero(r < max_range)[0]:
            if (i in vanish and k >= half) or rng.random() < p_miss:
                continue
            rr = r[i] + rng.normal(0, sigma_range)
            bb = b[i] + rng.normal(0, sigma_b)
            lines.append(f"LANDMARK {k} {i} {rr * np.cos(bb):.9g} {rr * np.sin(bb):.9g} {sigma_range**2:.9g} 0 {sigma_range**2:.9g}")
        for c_ in range(rng.poisson(clutter_rate)):
            rr, bb = rng.uniform(1, 0.6 * max_range), rng.uniform(-np.pi, np.pi)
            lines.append(f"LANDMARK {k} {CLUTTER_ID_BASE + k * 10 + c_} {rr * np.cos(bb):.9g} {rr * np.sin(bb):.9g} "
                         f"{sigma_range**2:.9g} 0 {sigma_range**2:.9g}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    (out.parent / "landmarks_truth.csv").write_text(
        "id,x,y,vanishes\n" + "".join(f"{i},{p[0]:.9f},{p[1]:.9f},{int(i in vanish)}\n" for i, p in enumerate(lm)))
    (out.parent / "poses_truth.txt").write_text("\n".join(truth_lines) + "\n")
    return out
