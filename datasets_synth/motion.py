"""Smooth closed-loop motion along a world's waypoints, and wheel odometry that drifts."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from submapslam.geometry import se2_array_to_matrices


def _chaikin_closed(points: np.ndarray, iterations: int = 4) -> np.ndarray:
    """Corner-cutting smoothing of a closed polygon ``(W, 2)``."""
    p = np.asarray(points, dtype=np.float64)
    for _ in range(iterations):
        q = np.roll(p, -1, axis=0)
        p = np.stack([0.75 * p + 0.25 * q, 0.25 * p + 0.75 * q], axis=1).reshape(-1, 2)
    return p


def _corner_points(w: np.ndarray, radius: float) -> np.ndarray:
    """Closed polygon with extra points ``radius`` before and after every corner (limits rounding)."""
    out = []
    n = len(w)
    for k in range(n):
        prev, cur, nxt = w[k - 1], w[k], w[(k + 1) % n]
        a = prev - cur
        b = nxt - cur
        la, lb = np.linalg.norm(a), np.linalg.norm(b)
        if la > 1e-9:
            out.append(cur + a / la * min(radius, la / 2))
        out.append(cur)
        if lb > 1e-9:
            out.append(cur + b / lb * min(radius, lb / 2))
    return np.array(out)


def loop_path(waypoints: np.ndarray, laps: int, step: float, corner_radius: float = 1.2) -> np.ndarray:
    """Planar poses ``(N, 3)`` ``(x, y, yaw)`` every ``step`` metres along ``laps`` smoothed laps.

    The path starts on the first waypoint edge's midpoint and ends where it started.
    """
    w = np.asarray(waypoints, dtype=np.float64)
    start = 0.5 * (w[0] + w[1])
    w = np.vstack([start, w[1:], w[:1]])
    smooth = _chaikin_closed(_corner_points(w, corner_radius), iterations=3)
    # rotate so the path starts near the start point
    k = int(np.argmin(np.linalg.norm(smooth - start, axis=1)))
    smooth = np.roll(smooth, -k, axis=0)
    closed = np.vstack([smooth, smooth[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    total = s[-1] * laps
    samples = np.arange(0.0, total + 1e-9, step) % s[-1]
    x = np.interp(samples, s, closed[:, 0])
    y = np.interp(samples, s, closed[:, 1])
    # heading from a centred difference along the (periodic) curve
    ahead = (samples + step) % s[-1]
    behind = (samples - step) % s[-1]
    dx = np.interp(ahead, s, closed[:, 0]) - np.interp(behind, s, closed[:, 0])
    dy = np.interp(ahead, s, closed[:, 1]) - np.interp(behind, s, closed[:, 1])
    return np.stack([x, y, np.unwrap(np.arctan2(dy, dx))], axis=1)


@dataclass
class OdometryNoise:
    """Wheel odometry error model per step of ``d`` metres and ``dtheta`` radians.

    distance scale error ~ N(0, sigma_scale); heading noise ~ N(0, sigma_heading * sqrt(d) +
    sigma_turn * |dtheta|) plus a systematic ``heading_bias`` per metre (a wheel-radius mismatch).
    """

    sigma_scale: float = 0.01
    sigma_heading: float = 0.004
    sigma_turn: float = 0.02
    heading_bias: float = 0.002
    lateral_sigma: float = 0.002

    def scaled(self, factor: float) -> OdometryNoise:
        return OdometryNoise(*(v * factor for v in (self.sigma_scale, self.sigma_heading, self.sigma_turn,
                                                    self.heading_bias, self.lateral_sigma)))


def wheel_odometry(truth_xyt: np.ndarray, noise: OdometryNoise, rng: np.random.Generator) -> np.ndarray:
    """Integrate noisy increments of the true planar path -> ``(N, 4, 4)`` ``T_odom_base``.

    Odometry starts at identity at the first pose.
    """
    truth_xyt = np.asarray(truth_xyt, dtype=np.float64)
    n = len(truth_xyt)
    out = np.zeros((n, 3))
    for k in range(1, n):
        x0, y0, t0 = truth_xyt[k - 1]
        x1, y1, t1 = truth_xyt[k]
        c, s = np.cos(t0), np.sin(t0)
        dx_l = c * (x1 - x0) + s * (y1 - y0)  # increment in the robot frame
        dy_l = -s * (x1 - x0) + c * (y1 - y0)
        dth = t1 - t0
        d = float(np.hypot(dx_l, dy_l))
        dx_l *= 1 + rng.normal(0, noise.sigma_scale)
        dy_l += rng.normal(0, noise.lateral_sigma) * d
        dth += rng.normal(0, noise.sigma_heading * np.sqrt(d) + noise.sigma_turn * abs(dth)) + noise.heading_bias * d
        X, Y, T = out[k - 1]
        out[k] = (X + np.cos(T) * dx_l - np.sin(T) * dy_l, Y + np.sin(T) * dx_l + np.cos(T) * dy_l, T + dth)
    return se2_array_to_matrices(out)
