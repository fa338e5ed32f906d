"""Tiny planar scenes for the 2D registration tests: wall segments and a ray-cast 180-degree scan."""

import numpy as np


def wall_ranges(segments, pose_xyt, beams=361, no_return=np.inf):
    """Ranges ``(beams,)`` of a 180-degree planar scan of wall ``segments`` from ``pose_xyt``;
    ``no_return`` where a beam hits no wall."""
    x, y, th = pose_xyt
    out = np.full(beams, float(no_return))
    for k, a in enumerate(np.linspace(-np.pi / 2, np.pi / 2, beams)):
        d = np.array([np.cos(th + a), np.sin(th + a)])
        for x0, y0, x1, y1 in segments:
            e = np.array([x1 - x0, y1 - y0])
            M = np.array([d, -e]).T
            if abs(np.linalg.det(M)) < 1e-12:
                continue
            t, u = np.linalg.solve(M, np.array([x0 - x, y0 - y]))
            if t > 0 and 0 <= u <= 1:
                out[k] = min(out[k], t)
    return out


def wall_points(segments, pose_xyt, max_range=8.0, beams=361):
    """Ray-cast a 180-degree planar scan of wall ``segments`` from ``pose_xyt``; points in the sensor frame."""
    ranges = wall_ranges(segments, pose_xyt, beams)
    angles = np.linspace(-np.pi / 2, np.pi / 2, beams)
    keep = ranges < max_range
    return np.stack([ranges[keep] * np.cos(angles[keep]), ranges[keep] * np.sin(angles[keep])], axis=1)
