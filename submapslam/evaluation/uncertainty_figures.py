"""The uncertainty a run reports, drawn: per-scan 3σ ellipses on the trajectory and σ along the path.

Input covariances are ``(N, 6, 6)`` as ``poses_cov.txt`` holds them once read
(:func:`submapslam.io.trajectory.read_tum_cov`): GTSAM tangent order ``(rx, ry, rz, x, y, z)``
[rad, m], each in its pose's own frame (right perturbation ``T_true = T Exp(xi)``).
"""

from __future__ import annotations

import numpy as np

from .html_page import png_data_uri
from .run_figures import _ellipses, _plt

#: (label, GTSAM index) of the axes drawn along the path; planar runs draw the first three only
TRANSLATION_AXES = (("x (forward)", 3), ("y (left)", 4), ("z (up)", 5))
ROTATION_AXES = (("yaw", 2), ("roll", 0), ("pitch", 1))


def world_xy_covariances(poses: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """``(N, 2, 2)`` world-frame x-y position covariance of each pose: the pose-frame translation
    block ``C[3:6, 3:6]`` rotated by the pose's rotation ``R`` (``R C R^T``), its top-left 2x2.
    ``poses`` ``(N, 4, 4)`` ``T_world_scan``; ``covariances`` ``(N, 6, 6)`` (GTSAM order)."""
    R = np.asarray(poses, dtype=np.float64)[:, :3, :3]
    C = np.asarray(covariances, dtype=np.float64)[:, 3:6, 3:6]
    return (R @ C @ np.transpose(R, (0, 2, 1)))[:, :2, :2]


def path_distance(positions: np.ndarray) -> np.ndarray:
    """``(N,)`` distance travelled [m] along ``(N, 3)`` positions from the first."""
    steps = np.linalg.norm(np.diff(np.asarray(positions, dtype=np.float64), axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def ellipse_indices(positions: np.ndarray, covariances: np.ndarray, max_count: int = 120) -> np.ndarray:
    """Indices of at most ``max_count`` poses evenly spaced in distance travelled (the first and
    the last included), among those with a finite covariance: which scans get an ellipse."""
    ok = np.flatnonzero(np.isfinite(covariances).all(axis=(1, 2)))
    if len(ok) <= max_count:
        return ok
    d = path_distance(positions)[ok]
    if d[-1] <= 0.0:
        return ok[np.linspace(0, len(ok) - 1, max_count).round().astype(int)]
    wanted = np.linspace(0.0, d[-1], max_count)
    return ok[np.unique(np.clip(np.searchsorted(d, wanted), 0, len(ok) - 1))]


def sigmas(covariances: np.ndarray) -> np.ndarray:
    """``(N, 6)`` standard deviations (GTSAM order) from the diagonals; NaN where not finite."""
    d = np.diagonal(np.asarray(covariances, dtype=np.float64), axis1=1, axis2=2)
    return np.sqrt(np.clip(d, 0.0, None))


def sigma_figure(positions: np.ndarray, covariances: np.ndarray, planar: bool,
                 times: np.ndarray | None = None, lost: np.ndarray | None = None):
    """The matplotlib figure of σ of every pose along the path: translation [m] (x, y; z too in 3D)
    and rotation [deg] (yaw; roll and pitch too in 3D), each about the pose's own axes, against the
    distance travelled along ``positions`` ``(N, 3)`` (or against ``times`` ``(N,)`` [s] from the
    first when given). ``lost`` ``(N,)`` bool shades the spans where the map did not fix the pose
    (localisation)."""
    plt = _plt()
    s = sigmas(covariances)
    if times is not None:
        x, xlabel = np.asarray(times, dtype=np.float64) - times[0], "time since start [s]"
    else:
        x, xlabel = path_distance(positions), "distance travelled along the trajectory [m]"
    trans = TRANSLATION_AXES[:2] if planar else TRANSLATION_AXES
    rot = ROTATION_AXES[:1] if planar else ROTATION_AXES
    fig, axes = plt.subplots(2, 1, figsize=(9, 5.6), sharex=True)
    for ax, group, unit, f in ((axes[0], trans, "[m]", 1.0), (axes[1], rot, "[deg]", np.degrees(1.0))):
        for label, i in group:
            ax.plot(x, s[:, i] * f, lw=0.9, label=f"σ {label}")
        ax.set_ylabel(f"σ {unit}")
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
    if lost is not None and np.any(lost):
        for ax in axes:
            ax.fill_between(x, 0, 1, where=np.asarray(lost, bool), color="#d62020", alpha=0.12,
                            transform=ax.get_xaxis_transform(), label="lost (the map did not fix the pose)")
    for ax in axes:
        ax.legend(fontsize=8, loc="upper left")
    axes[-1].set_xlabel(xlabel)
    return fig


def sigma_along_path_figure(positions: np.ndarray, covariances: np.ndarray, planar: bool,
                            times: np.ndarray | None = None, lost: np.ndarray | None = None,
                            dpi: int = 100) -> str:
    """:func:`sigma_figure` as a PNG data URI."""
    return png_data_uri(sigma_figure(positions, covariances, planar, times, lost), dpi)


def save_sigma_figure(path, positions: np.ndarray, covariances: np.ndarray, planar: bool,
                      times: np.ndarray | None = None, lost: np.ndarray | None = None, dpi: int = 100) -> None:
    """Write :func:`sigma_figure` to the PNG file ``path``."""
    fig = sigma_figure(positions, covariances, planar, times, lost)
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    _plt().close(fig)


def draw_scan_ellipses(ax, poses: np.ndarray, covariances: np.ndarray, n_sigma: float = 3.0,
                       max_count: int = 120) -> int:
    """Draw ``n_sigma`` x-y ellipses (world frame) of at most ``max_count`` scans evenly spaced along
    the path, with their centres, onto ``ax``; return how many were drawn."""
    idx = ellipse_indices(poses[:, :3, 3], covariances, max_count)
    if not len(idx):
        return 0
    xy = poses[idx, :2, 3]
    _ellipses(ax, xy, world_xy_covariances(poses[idx], covariances[idx]), n_sigma,
              edgecolors="#e07000", linewidths=0.9, zorder=6)
    ax.scatter(xy[:, 0], xy[:, 1], color="#e07000", s=5, zorder=7)
    return len(idx)
