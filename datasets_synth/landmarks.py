"""Synthetic landmark worlds for the stochastic map: point landmarks around a loop, noisy
odometry, range-bearing detections with misses, clutter, landmarks that disappear and new ones
that appear.

Written in gtsam's ``victoria_park.txt`` format (ODOMETRY / LANDMARK lines), so the same reader
loads real and synthetic landmark logs. Beside it, the ground truth:

* ``poses_truth.txt``: ``k x y theta`` of the robot at the end of step ``k`` (world frame);
* ``landmarks_truth.csv``: ``id,x,y,vanishes,appears,first_step,end_step`` — each landmark's
  position, whether it leaves the world or enters it during the run, and the steps it exists:
  ``first_step <= k < end_step`` (the LANDMARK lines use the same ids);
* ``landmarks_meta.yaml``: the sensor range (``max_range_m``) and the world's settings.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from submapslam.errors import SubmapSlamError

from .motion import loop_path

CLUTTER_ID_BASE = 100000  # clutter detections get unique ids from here (seen once, then forgotten)


def generate_landmark_log(out: str | Path, *, seed: int = 0, laps: int = 2, n_landmarks: int = 20,
                          size: tuple[float, float] = (20.0, 12.0), step: float = 0.5, max_range: float = 8.0,
                          sigma_range: float = 0.05, odo_sigma: tuple[float, float, float] = (0.02, 0.01, 0.005),
                          p_miss: float = 0.0, clutter_rate: float = 0.0, vanish_fraction: float = 0.0,
                          appear: int = 0, appear_clearance: float = 1.5) -> Path:
    """Write ``out`` (a victoria_park-format file) and truth files beside it; return ``out``.

    ``vanish_fraction`` of the ``n_landmarks`` disappear from the world half way through the run
    (at step ``N // 2``); ``appear`` new landmarks (ids ``n_landmarks ...``) enter it at the
    same step, each at least ``appear_clearance`` [m] from every other landmark (so that a new
    landmark is not the old one back). The run without ``appear`` draws the same random numbers
    as before the option existed. Bearing sigma is ``sigma_range / sqrt(10)`` (the convention of
    gtsam's loader).
    """
    rng = np.random.default_rng(seed)
    W, H = size
    waypoints = np.array([(0, 0), (W, 0), (W, H), (0, H)], dtype=float)
    path = loop_path(waypoints, laps, step)
    lm = np.c_[rng.uniform(-3, W + 3, n_landmarks), rng.uniform(-3, H + 3, n_landmarks)]
    vanish = set(rng.choice(n_landmarks, int(round(vanish_fraction * n_landmarks)), replace=False).tolist())
    if appear:
        lm = np.vstack([lm, _new_landmarks(lm, appear, (-3, -3, W + 3, H + 3), appear_clearance,
                                           np.random.default_rng([seed, 5077]))])
    Q = np.diag(np.square(odo_sigma))
    sigma_b = sigma_range / np.sqrt(10)
    lines = []
    half = len(path) // 2
    first = np.where(np.arange(len(lm)) >= n_landmarks, half, 0)
    end = np.array([half if i in vanish else len(path) for i in range(len(lm))])
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
            if not first[i] <= k < end[i] or rng.random() < p_miss:
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
        "id,x,y,vanishes,appears,first_step,end_step\n"
        + "".join(f"{i},{p[0]:.9f},{p[1]:.9f},{int(i in vanish)},{int(i >= n_landmarks)},{first[i]},{end[i]}\n"
                  for i, p in enumerate(lm)))
    (out.parent / "poses_truth.txt").write_text("\n".join(truth_lines) + "\n")
    (out.parent / "landmarks_meta.yaml").write_text(
        f"# written by datasets_synth.landmarks beside {out.name}\nmax_range_m: {max_range}\nsteps: {len(path)}\n"
        f"change_step: {half}\nseed: {seed}\nlaps: {laps}\nlandmarks: {n_landmarks}\nvanished: {len(vanish)}\n"
        f"appeared: {appear}\np_miss: {p_miss}\nclutter_rate: {clutter_rate}\n")
    return out


def _new_landmarks(existing: np.ndarray, n: int, box: tuple[float, float, float, float], clearance: float,
                   rng: np.random.Generator) -> np.ndarray:
    """``n`` points ``(n, 2)`` uniform in ``box`` ``(xmin, ymin, xmax, ymax)``, each at least
    ``clearance`` [m] from ``existing`` ``(K, 2)`` and from each other (rejection sampling)."""
    placed = [p for p in np.asarray(existing, dtype=np.float64).reshape(-1, 2)]
    out: list[np.ndarray] = []
    for _ in range(1000 * n):
        if len(out) == n:
            break
        p = rng.uniform(box[:2], box[2:])
        if not placed or np.min(np.linalg.norm(np.array(placed) - p, axis=1)) >= clearance:
            placed.append(p)
            out.append(p)
    if len(out) < n:
        raise SubmapSlamError(f"cannot place {n} new landmarks {clearance} m from the others in {box}")
    return np.array(out).reshape(-1, 2)
