"""Terrain along a real path: a smooth ground height field that follows the path's own height.

:class:`PathTerrain` smooths the heights of a driven path ``(N, 3)`` ``(x, y, z)`` along its arc
length, then interpolates them off the path with a narrower Gaussian kernel over the path's
points, so the ground is smooth, equals the smoothed path height on the road (a street passing
near another at a different height keeps its own) and takes the height of the nearest stretch
of road far from it. :func:`terrain_poses` puts a vehicle on that
ground: its position on the surface, its z axis along the ground normal (the road's pitch and
roll), its x axis the heading projected into the ground plane.
"""

from __future__ import annotations

import numpy as np


class PathTerrain:
    """Ground height ``z(x, y)`` [m] from a path's heights.

    Args:
        path_xyz: ``(N, 3)`` world points of the driven path (x, y in the plane, z up) [m].
        sigma: [m] Gaussian smoothing of the heights along the path (grade changes spread over
            about ``2 * sigma``; GPS noise in the heights is smoothed out).
        sigma_across: [m] width of the Gaussian kernel that carries the heights off the path.
        spacing: [m] the path is resampled this finely before interpolating.
        neighbours: path points each query weighs.
    """

    def __init__(self, path_xyz: np.ndarray, sigma: float = 8.0, sigma_across: float = 12.0, spacing: float = 1.0,
                 neighbours: int = 64) -> None:
        from scipy.ndimage import gaussian_filter1d
        from scipy.spatial import cKDTree

        p = np.asarray(path_xyz, dtype=np.float64).reshape(-1, 3)
        seg = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        keep = np.concatenate([[True], seg > 1e-6])
        p, s = p[keep], s[keep]
        if len(p) < 2:
            p = np.vstack([p, p + [1e-3, 0.0, 0.0]])
            s = np.array([0.0, 1e-3])
        grid = np.arange(0.0, s[-1] + 1e-9, spacing)
        self.points = np.stack([np.interp(grid, s, p[:, k]) for k in range(3)], axis=1)
        self.points[:, 2] = gaussian_filter1d(self.points[:, 2], sigma / spacing, mode="nearest")
        self.sigma = float(sigma)
        self.sigma_across = float(sigma_across)
        self.k = int(min(neighbours, len(self.points)))
        self._tree = cKDTree(self.points[:, :2])

    def height(self, xy: np.ndarray, chunk: int = 200_000) -> np.ndarray:
        """Ground height ``(M,)`` [m] at the world points ``(M, 2)``."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        out = np.empty(len(xy))
        for a in range(0, len(xy), chunk):
            d, idx = self._tree.query(xy[a:a + chunk], k=self.k)
            d, idx = d.reshape(len(d), -1), idx.reshape(len(idx), -1)
            # relative to the nearest point: far from the path the weights do not all vanish
            w = np.exp(-(d**2 - d[:, :1] ** 2) / (2 * self.sigma_across**2))
            out[a:a + chunk] = (w * self.points[idx, 2]).sum(axis=1) / w.sum(axis=1)
        return out

    def normal(self, xy: np.ndarray, step: float = 0.5) -> np.ndarray:
        """Unit ground normals ``(M, 3)`` (z > 0) at ``(M, 2)``, from central differences over ``step`` [m]."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        ex, ey = np.array([step, 0.0]), np.array([0.0, step])
        gx = (self.height(xy + ex) - self.height(xy - ex)) / (2 * step)
        gy = (self.height(xy + ey) - self.height(xy - ey)) / (2 * step)
        n = np.stack([-gx, -gy, np.ones_like(gx)], axis=1)
        return n / np.linalg.norm(n, axis=1, keepdims=True)


def terrain_poses(path_xyt: np.ndarray, terrain: PathTerrain, mount_height: float) -> np.ndarray:
    """Vehicle poses ``(N, 4, 4)`` ``T_world_sensor`` on the terrain along the planar path ``(N, 3)``.

    The sensor sits ``mount_height`` [m] above the ground along the ground normal; its z axis is
    the normal (the road's pitch and roll), its x axis the heading ``yaw`` projected into the
    ground plane.
    """
    xyt = np.asarray(path_xyt, dtype=np.float64).reshape(-1, 3)
    z = terrain.height(xyt[:, :2])
    n = terrain.normal(xyt[:, :2])
    f = np.stack([np.cos(xyt[:, 2]), np.sin(xyt[:, 2]), np.zeros(len(xyt))], axis=1)
    x = f - (f * n).sum(axis=1, keepdims=True) * n
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(n, x)
    T = np.tile(np.eye(4), (len(xyt), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = x, y, n
    T[:, :3, 3] = np.column_stack([xyt[:, :2], z]) + mount_height * n
    return T


def lift_odometry(odom_planar: np.ndarray, truth_planar: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """3D odometry ``(N, 4, 4)``: each true 3D step ``truth`` ``(N, 4, 4)`` with the planar
    odometry's error of that step (``odom_planar`` against ``truth_planar``, both ``(N, 4, 4)``
    with z = 0) applied in the vehicle frame. Starts at identity."""
    from submapslam.geometry import inverse

    out = np.tile(np.eye(4), (len(truth), 1, 1))
    for k in range(1, len(truth)):
        err = inverse(inverse(truth_planar[k - 1]) @ truth_planar[k]) @ (inverse(odom_planar[k - 1]) @ odom_planar[k])
        out[k] = out[k - 1] @ inverse(truth[k - 1]) @ truth[k] @ err
    return out


def keyframe_schedule(n: int, rate_hz: float, rng: np.random.Generator, *, step: tuple[int, int] = (2, 6),
                      stop_probability: float = 0.02, stop_s: tuple[float, float] = (6.0, 13.0),
                      still_scans: tuple[int, int] = (1, 4)) -> tuple[np.ndarray, np.ndarray]:
    """Irregular keyframes of a drive of ``n`` poses recorded at ``rate_hz``.

    Returns ``(index (K,), time (K,) [s from the start])``: which pose each keyframe shows and
    when. Keyframes skip ``step`` poses (drawn in [lo, hi), 0.2-0.5 s at 10 Hz); after a keyframe,
    with ``stop_probability`` the vehicle stands still: a few keyframes (``still_scans``) of the
    same pose, the last after a gap of ``stop_s`` seconds. Time is the drive's own time plus the
    stops. The last pose is always a keyframe.
    """
    index: list[int] = [0]
    times: list[float] = [0.0]
    shift = 0.0
    k = 0
    while True:
        if rng.random() < stop_probability:
            extra = int(rng.integers(still_scans[0], still_scans[1] + 1))
            wait = float(rng.uniform(*stop_s))
            for m in range(1, extra + 1):
                index.append(k)
                times.append(k / rate_hz + shift + wait * m / extra)
            shift += wait
        k += int(rng.integers(step[0], step[1]))
        if k >= n - 1:
            break
        index.append(k)
        times.append(k / rate_hz + shift)
    if index[-1] != n - 1:
        index.append(n - 1)
        times.append((n - 1) / rate_hz + shift)
    return np.asarray(index, dtype=np.int64), np.asarray(times, dtype=np.float64)
