"""Smooth motion along a world's waypoints (closed loops or open paths), and wheel odometry that drifts."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from submapslam.geometry import se2_array_to_matrices


def _chaikin(points: np.ndarray, iterations: int = 4, closed: bool = True) -> np.ndarray:
    """Corner-cutting smoothing of a polygon ``(W, 2)``; an open one keeps its two end points."""
    p = np.asarray(points, dtype=np.float64)
    for _ in range(iterations):
        q = np.roll(p, -1, axis=0)
        cut = np.stack([0.75 * p + 0.25 * q, 0.25 * p + 0.75 * q], axis=1).reshape(-1, 2)
        p = cut if closed else np.vstack([p[:1], cut[:-2], p[-1:]])
    return p


def _corner_points(w: np.ndarray, radius: float, closed: bool = True) -> np.ndarray:
    """Polygon with extra points ``radius`` before and after every corner (limits rounding)."""
    out = []
    n = len(w)
    for k in range(n):
        cur = w[k]
        if not closed and k in (0, n - 1):
            out.append(cur)
            continue
        prev, nxt = w[k - 1], w[(k + 1) % n]
        a = prev - cur
        b = nxt - cur
        la, lb = np.linalg.norm(a), np.linalg.norm(b)
        if la > 1e-9:
            out.append(cur + a / la * min(radius, la / 2))
        out.append(cur)
        if lb > 1e-9:
            out.append(cur + b / lb * min(radius, lb / 2))
    return np.array(out)


def _sample_curve(curve: np.ndarray, samples: np.ndarray, step: float, period: float | None) -> np.ndarray:
    """Poses ``(N, 3)`` at arc lengths ``samples`` of the polyline ``curve``; heading by a centred
    difference (periodic when ``period`` is the length of a closed curve, clamped at open ends)."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])

    def at(u):
        u = u % period if period is not None else np.clip(u, 0.0, s[-1])
        return np.interp(u, s, curve[:, 0]), np.interp(u, s, curve[:, 1])

    x, y = at(samples)
    (xa, ya), (xb, yb) = at(samples + step), at(samples - step)
    return np.stack([x, y, np.unwrap(np.arctan2(ya - yb, xa - xb))], axis=1)


def loop_path(waypoints: np.ndarray, laps: int, step: float, corner_radius: float = 1.2) -> np.ndarray:
    """Planar poses ``(N, 3)`` ``(x, y, yaw)`` every ``step`` metres along ``laps`` smoothed laps.

    The path starts on the first waypoint edge's midpoint and ends where it started.
    """
    w = np.asarray(waypoints, dtype=np.float64)
    start = 0.5 * (w[0] + w[1])
    w = np.vstack([start, w[1:], w[:1]])
    smooth = _chaikin(_corner_points(w, corner_radius), iterations=3)
    # rotate so the path starts near the start point
    k = int(np.argmin(np.linalg.norm(smooth - start, axis=1)))
    smooth = np.roll(smooth, -k, axis=0)
    closed = np.vstack([smooth, smooth[:1]])
    length = float(np.linalg.norm(np.diff(closed, axis=0), axis=1).sum())
    return _sample_curve(closed, np.arange(0.0, length * laps + 1e-9, step) % length, step, length)


def open_path(waypoints: np.ndarray, step: float, corner_radius: float = 1.2) -> np.ndarray:
    """Planar poses ``(N, 3)`` every ``step`` metres from the first waypoint to the last, corners
    rounded over about ``corner_radius`` metres; driven once (a path that never returns)."""
    w = np.asarray(waypoints, dtype=np.float64)
    smooth = _chaikin(_corner_points(w, corner_radius, closed=False), iterations=3, closed=False)
    length = float(np.linalg.norm(np.diff(smooth, axis=0), axis=1).sum())
    return _sample_curve(smooth, np.arange(0.0, length + 1e-9, step), step, None)


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
