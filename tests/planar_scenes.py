"""Tiny planar scenes for the 2D registration tests: wall segments and a ray-cast 180-degree scan."""

import numpy as np


def wall_points(segments, pose_xyt, max_range=8.0, beams=361):
    """Ray-cast a 180-degree planar scan of wall ``segments`` from ``pose_xyt``; points in the sensor frame."""
    x, y, th = pose_xyt
    pts = []
    for a in np.linspace(-np.pi / 2, np.pi / 2, beams):
        d = np.array([np.cos(th + a), np.sin(th + a)])
        best = np.inf
        for x0, y0, x1, y1 in segments:
            e = np.array([x1 - x0, y1 - y0])
            M = np.array([d, -e]).T
            if abs(np.linalg.det(M)) < 1e-12:
                continue
            t, u = np.linalg.solve(M, np.array([x0 - x, y0 - y]))
            if t > 0 and 0 <= u <= 1:
                best = min(best, t)
        if best < max_range:
            pts.append([best * np.cos(a), best * np.sin(a)])
    return np.array(pts)
