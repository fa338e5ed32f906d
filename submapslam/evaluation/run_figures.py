"""The figures of a run report (matplotlib, Agg), each returned as an inline PNG ``data:`` URI.

Frames: everything is drawn top-down in the run's world frame (x right, y up, metres); the
trajectory error figures in the reference's frame after aligning the estimate to it.
"""

from __future__ import annotations

import numpy as np

from ..trajectory import Trajectory
from .html_page import png_data_uri
from .metrics import AlignMode, associate
from .metrics import align as align_fn
from .run_record import GridImage, RunRecord

_ACCEPTED, _REJECTED = "#1a9a1a", "#d62020"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def anchor_covariances_xy(submaps: dict[str, np.ndarray]) -> np.ndarray:
    """``(S, 2, 2)`` world-frame x-y covariance of each anchor from ``submaps.csv``'s anchor-frame
    standard deviations (and ``cov_xy`` when written), rotated by the anchor's yaw."""
    sx, sy, yaw = submaps["sigma_x"], submaps["sigma_y"], submaps["yaw"]
    cxy = np.nan_to_num(submaps.get("cov_xy", np.zeros_like(sx)))
    C = np.zeros((len(sx), 2, 2))
    C[:, 0, 0], C[:, 1, 1], C[:, 0, 1], C[:, 1, 0] = sx**2, sy**2, cxy, cxy
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    return R @ C @ np.transpose(R, (0, 2, 1))


def _ellipses(ax, centers: np.ndarray, covs: np.ndarray, n_sigma: float, **kw) -> None:
    """All ``n_sigma`` ellipses of ``(K, 2, 2)`` covariances at ``(K, 2)`` centres as one collection
    (one artist: a hundred patches cost a second to draw)."""
    from matplotlib.collections import EllipseCollection

    w, V = np.linalg.eigh(covs)
    w = np.clip(w, 0.0, None)
    angles = np.degrees(np.arctan2(V[:, 1, 1], V[:, 0, 1]))
    ax.add_collection(EllipseCollection(2 * n_sigma * np.sqrt(w[:, 1]), 2 * n_sigma * np.sqrt(w[:, 0]), angles,
                                        units="xy", offsets=centers, offset_transform=ax.transData,
                                        facecolors="none", **kw))


def top_down_image(points: np.ndarray, max_pixels: int = 1400, min_cell: float = 0.1,
                   bounds: tuple[float, float, float, float] | None = None
                   ) -> tuple[np.ndarray, tuple[float, float, float, float], float]:
    """Top-down render of a ``(M, 3)`` cloud: the highest point's z per cell (NaN where empty),
    row 0 = top.

    ``bounds`` ``(x0, x1, y0, y1)`` [m] crops the cloud first. Returns ``(image (rows, cols),
    extent (x0, x1, y0, y1) [m], cell [m])``; the cell is chosen so the longer side has at most
    ``max_pixels`` cells.
    """
    P = np.asarray(points, dtype=np.float64)
    if bounds is not None:
        x0, x1, y0, y1 = bounds
        P = P[(P[:, 0] >= x0) & (P[:, 0] <= x1) & (P[:, 1] >= y0) & (P[:, 1] <= y1)]
    if len(P) == 0:
        return np.full((1, 1), np.nan), (0.0, 1.0, 0.0, 1.0), 1.0
    lo, hi = P[:, :2].min(axis=0), P[:, :2].max(axis=0)
    cell = max(min_cell, float((hi - lo).max()) / max_pixels)
    ij = np.floor((P[:, :2] - lo) / cell).astype(np.int64)
    cols, rows = int(ij[:, 0].max()) + 1, int(ij[:, 1].max()) + 1
    flat = ij[:, 1] * cols + ij[:, 0]
    order = np.argsort(flat, kind="stable")
    flat, z = flat[order], P[order, 2]
    starts = np.flatnonzero(np.r_[True, np.diff(flat) != 0])
    height = np.full(rows * cols, np.nan)
    height[flat[starts]] = np.maximum.reduceat(z, starts)
    return height.reshape(rows, cols)[::-1], (lo[0], lo[0] + cols * cell, lo[1], lo[1] + rows * cell), cell


def _draw_cloud(fig, ax, cloud: np.ndarray, path_xy: np.ndarray | None, cax=None) -> None:
    """The 3D map from above: cells whose highest point stands < 0.3 m over the ground in grey,
    the rest coloured by that height; cropped to 20 m around the path when it is known."""
    bounds = None
    if path_xy is not None and len(path_xy):
        (x0, y0), (x1, y1) = path_xy.min(axis=0) - 20.0, path_xy.max(axis=0) + 20.0
        bounds = (x0, x1, y0, y1)
    img, extent, _ = top_down_image(cloud, max_pixels=700, min_cell=0.2, bounds=bounds)
    finite = img[np.isfinite(img)]
    if not finite.size:
        return
    ground = float(np.percentile(finite, 10))
    rel = img - ground
    ax.imshow(np.where(rel < 0.3, 0.8, np.nan), extent=extent, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
    top = max(float(np.percentile(rel[np.isfinite(rel)], 99)), 1.0)
    im = ax.imshow(np.where(rel >= 0.3, rel, np.nan), extent=extent, cmap="viridis", vmin=0.3, vmax=top,
                   interpolation="nearest")
    if cax is not None:
        fig.colorbar(im, cax=cax, label="height over the ground of the highest map point [m]")
    else:
        fig.colorbar(im, ax=ax, shrink=0.6, label="height over the ground of the highest map point [m]")


_MAP_RECT = (0.08, 0.06, 0.80, 0.90)  # the map axes' place in every layer (same pixels in each)


def map_layers(rec: RunRecord, dpi: int = 100, size: float = 12.0) -> list[tuple[str, str, str, bool]]:
    """The map view as stacked layers of the same size and axes: the map with the trajectory and
    the odometry (the base), then transparent overlays of the accepted loops, the rejected
    hypotheses and the submap anchors with their 3σ ellipses, for the page to toggle. Returns
    ``[(key, label, data URI, shown at first)]``, the base first."""
    plt = _plt()

    height = size

    def canvas(transparent: bool):
        fig = plt.figure(figsize=(size, height))
        ax = fig.add_axes(_MAP_RECT)
        if transparent:
            fig.patch.set_alpha(0.0)
            ax.patch.set_alpha(0.0)
            ax.set_axis_off()
        return fig, ax

    fig, ax = canvas(False)
    if rec.grid is not None and (rec.cloud is None or len(rec.cloud) == 0):
        _draw_grid(ax, rec.grid)
    elif rec.cloud is not None and len(rec.cloud):
        _draw_cloud(fig, ax, rec.cloud, rec.poses.positions[:, :2] if rec.poses is not None else None,
                    cax=fig.add_axes((0.90, 0.25, 0.02, 0.5)))
    if rec.odometry is not None:
        ax.plot(rec.odometry.positions[:, 0], rec.odometry.positions[:, 1], color="0.55", lw=0.7, ls="--",
                label="odometry (before loop closure)")
    if rec.poses is not None:
        ax.plot(rec.poses.positions[:, 0], rec.poses.positions[:, 1], color="#1f5fd0", lw=1.0, label="trajectory")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper right", fontsize=8, framealpha=0.85)
    limits = ax.get_xlim(), ax.get_ylim()
    # the figure takes the map's shape (no empty bands above and below a wide map)
    (x0, x1), (y0, y1) = limits
    w_in, h_in = _MAP_RECT[2] * size, _MAP_RECT[3] * size
    height = size * float(np.clip((y1 - y0) / max(x1 - x0, 1e-9) * w_in / h_in, 0.35, 1.0))
    fig.set_size_inches(size, height)
    layers = [("map", "map and trajectory", _png_exact(fig, dpi), True)]

    def overlay(key: str, label: str, draw, shown: bool) -> None:
        fig, ax = canvas(True)
        draw(ax)
        ax.set_xlim(*limits[0])
        ax.set_ylim(*limits[1])
        ax.set_aspect("equal")
        layers.append((key, label, _png_exact(fig, dpi), shown))

    if rec.poses is not None and rec.pose_covariances is not None:
        from .uncertainty_figures import draw_scan_ellipses, ellipse_indices

        n = len(ellipse_indices(rec.poses.positions, rec.pose_covariances))
        overlay("uncertainty", f"scan poses with 3σ ellipses ({n} along the path, from poses_cov.txt)",
                lambda ax: draw_scan_ellipses(ax, rec.poses.poses, rec.pose_covariances), True)
    if rec.submaps is None or not len(rec.submaps.get("x", [])):
        return layers
    xy = np.stack([rec.submaps["x"], rec.submaps["y"]], axis=1)

    n_ok = sum(r.get("accepted") == "1" for r in rec.loops)
    overlay("accepted", f"accepted loops ({n_ok})",
            lambda ax: _draw_loops(ax, [r for r in rec.loops if r.get("accepted") == "1"], xy), True)
    overlay("rejected", f"rejected hypotheses ({len(rec.loops) - n_ok})",
            lambda ax: _draw_loops(ax, [r for r in rec.loops if r.get("accepted") != "1"], xy), False)

    def anchors(ax) -> None:
        covs = anchor_covariances_xy(rec.submaps)
        ax.scatter(xy[:, 0], xy[:, 1], color="#7a1fa0", s=12, zorder=5)
        _ellipses(ax, xy, covs, 3.0, edgecolors="#7a1fa0", linewidths=0.8, zorder=4)

    overlay("submaps", f"submap anchors and 3σ ellipses ({len(xy)})", anchors, False)
    return layers


def _png_exact(fig, dpi: int) -> str:
    """A figure as a PNG data URI at its exact size (no tight bounding box: layers stay aligned)."""
    import base64
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, transparent=fig.patch.get_alpha() not in (None, 1.0))
    _plt().close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def save_map_picture(rec: RunRecord, path, dpi: int = 110) -> None:
    """Write a PNG of the map (grid, or the 3D cloud from above) with the optimised trajectory
    (and the odometry before loop closure, dashed) to ``path``: the run at a glance, without the
    report's anchors, ellipses and hypotheses."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 9))
    if rec.grid is not None and (rec.cloud is None or len(rec.cloud) == 0):
        _draw_grid(ax, rec.grid)
    elif rec.cloud is not None and len(rec.cloud):
        _draw_cloud(fig, ax, rec.cloud, rec.poses.positions[:, :2] if rec.poses is not None else None)
    if rec.odometry is not None:
        ax.plot(rec.odometry.positions[:, 0], rec.odometry.positions[:, 1], color="0.55", lw=0.7, ls="--",
                label="odometry (before loop closure)")
    if rec.poses is not None:
        ax.plot(rec.poses.positions[:, 0], rec.poses.positions[:, 1], color="#1f5fd0", lw=1.0, label="trajectory")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="upper right", fontsize=8, framealpha=0.85)
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    plt.close(fig)


def _draw_grid(ax, grid: GridImage) -> None:
    img = grid.image
    known = np.argwhere(img != 205)
    ax.imshow(img, cmap="gray", vmin=0, vmax=255, extent=grid.extent, interpolation="nearest")
    if len(known):  # zoom to the mapped cells
        (r0, c0), (r1, c1) = known.min(axis=0), known.max(axis=0)
        x0, _, _, y1 = grid.extent
        pad = 2.0
        ax.set_xlim(x0 + c0 * grid.resolution - pad, x0 + (c1 + 1) * grid.resolution + pad)
        ax.set_ylim(y1 - (r1 + 1) * grid.resolution - pad, y1 - r0 * grid.resolution + pad)


def _draw_loops(ax, loops: list[dict[str, str]], xy: np.ndarray) -> None:
    from matplotlib.collections import LineCollection

    for accepted, color, lw, alpha, label in ((False, _REJECTED, 0.6, 0.45, "rejected hypotheses"),
                                              (True, _ACCEPTED, 1.1, 0.9, "accepted loops")):
        segs = [(xy[int(r["submap_i"])], xy[int(r["submap_j"])]) for r in loops
                if (r.get("accepted") == "1") == accepted and max(int(r["submap_i"]), int(r["submap_j"])) < len(xy)]
        if segs:
            ax.add_collection(LineCollection(segs, colors=color, linewidths=lw, alpha=alpha, zorder=3,
                                             label=f"{label} ({len(segs)})"))


def aligned_positions(est: Trajectory, ref: Trajectory, mode: AlignMode) -> tuple[np.ndarray, np.ndarray]:
    """``(est positions aligned to ref (N, 3), indices into ref (K,) of the matched poses)``."""
    i_e, i_r = associate(est, ref)
    T, s = align_fn(est.subset(i_e), ref.subset(i_r), mode)
    return s * est.positions @ T[:3, :3].T + T[:3, 3], i_r


def error_figures(reference: Trajectory, series: dict[str, tuple[Trajectory, dict]], segments: dict[str, dict],
                  mode: AlignMode, dpi: int = 100) -> list[tuple[str, str]]:
    """Figures of the error against ``reference``: along the path (``series``: name ->
    (trajectory, ate(...) figures)), the path coloured by the first series' error, and the KITTI
    segment errors per length (``segments``: name -> {length: (trans %, deg/m)}).
    Returns ``[(data URI, caption)]``."""
    plt = _plt()
    out = []
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(reference.positions, axis=0), axis=1))])
    fig, ax = plt.subplots(figsize=(9, 3.8))
    for name, (traj, a) in series.items():
        _, i_r = associate(traj, reference)
        ax.plot(dist[i_r], a["errors"], lw=0.8, label=f"{name} (ATE RMSE {a['rmse']:.3f} m)")
    ax.set_xlabel("distance along the reference path [m]")
    ax.set_ylabel("position error [m]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    out.append((png_data_uri(fig, dpi), f"Position error along the path after {mode} alignment"))
    first = next(iter(series))
    traj, a = series[first]
    P, i_r = aligned_positions(traj, reference, mode)
    i_e, _ = associate(traj, reference)
    fig, ax = plt.subplots(figsize=(7, 7))
    ax.plot(reference.positions[:, 0], reference.positions[:, 1], color="0.6", lw=0.8, label="reference")
    sc = ax.scatter(P[i_e, 0], P[i_e, 1], c=a["errors"], s=3, cmap="inferno_r", label=first)
    fig.colorbar(sc, ax=ax, shrink=0.7, label="position error [m]")
    ax.set_aspect("equal")
    ax.legend(fontsize=8)
    out.append((png_data_uri(fig, dpi), f"{first}: where along the path the error is"))
    if any(segments.values()):
        fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
        width = 0.8 / max(1, len(segments))
        for k, (name, per_len) in enumerate(segments.items()):
            lengths = sorted(per_len)
            x = np.arange(len(lengths)) + k * width
            axes[0].bar(x, [per_len[L][0] for L in lengths], width, label=name)
            axes[1].bar(x, [per_len[L][1] for L in lengths], width, label=name)
            for axx in axes:
                axx.set_xticks(np.arange(len(lengths)) + width * (len(segments) - 1) / 2,
                               [f"{L:.0f}" for L in lengths])
        axes[0].set_ylabel("translation error [%]")
        axes[1].set_ylabel("rotation error [deg/m]")
        for axx in axes:
            axx.set_xlabel("segment length [m]")
            axx.grid(alpha=0.3, axis="y")
        axes[0].legend(fontsize=8)
        out.append((png_data_uri(fig, dpi), "KITTI segment errors per segment length"))
    return out


def degenerate_alignment(reference: Trajectory, mode: AlignMode) -> str | None:
    """A warning when the alignment's rotation is not determined by the reference path: a path
    (nearly) along a straight line leaves the rotation about it free, so the aligned estimate's
    rotation error means nothing. None when the path spans a plane or more (or no alignment)."""
    if str(mode) == "none" or len(reference.positions) < 3:
        return None
    P = reference.positions - reference.positions.mean(axis=0)
    sv = np.linalg.svd(P, compute_uv=False)
    if sv[0] <= 0 or sv[1] / sv[0] >= 0.02:
        return None
    return (f"the reference path is nearly a straight line (its second extent is {sv[1] / sv[0]:.1%} of the first): "
            f"the {mode} alignment cannot fix the rotation about it, so the ATE rotation figures are not "
            "meaningful (the position errors are)")


def evo_figures(reference: Trajectory, traj: Trajectory, name: str, mode: AlignMode,
                dpi: int = 100) -> list[tuple[str, str, str]]:
    """evo's standard plots of ``traj`` against ``reference`` after ``mode`` alignment, against
    time from the reference's first pose: x, y, z and yaw of both; the position error (APE) with
    its mean, median and ±1 std band; the relative error between consecutive poses (RPE); and
    histograms of both. Returns ``[(data URI, caption, element id)]``."""
    from ..geometry import inverse, rotation_angle
    from .metrics import associate as assoc

    plt = _plt()
    i_e, i_r = assoc(traj, reference)
    if len(i_e) < 2:
        return []
    e, r = traj.subset(i_e), reference.subset(i_r)
    T, s = align_fn(e, r, mode)
    A = np.array([T @ p for p in e.poses])
    A[:, :3, 3] = s * e.poses[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
    t = r.timestamps - r.timestamps[0]
    out = []
    fig, axes = plt.subplots(4, 1, figsize=(9, 8), sharex=True)
    yaw = lambda P: np.degrees(np.unwrap(np.arctan2(P[:, 1, 0], P[:, 0, 0])))  # noqa: E731
    for ax, label, a, b in ((axes[0], "x [m]", A[:, 0, 3], r.poses[:, 0, 3]),
                            (axes[1], "y [m]", A[:, 1, 3], r.poses[:, 1, 3]),
                            (axes[2], "z [m]", A[:, 2, 3], r.poses[:, 2, 3]),
                            (axes[3], "yaw [deg]", yaw(A), yaw(r.poses))):
        ax.plot(t, b, color="0.5", lw=1.0, ls="--", label="reference")
        ax.plot(t, a, color="#1f5fd0", lw=0.9, label=name)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="upper right")
    axes[-1].set_xlabel("time [s]")
    out.append((png_data_uri(fig, dpi), f"{name}: x, y, z and yaw against time ({mode} aligned)", "evo-xyz"))
    ape = np.linalg.norm(A[:, :3, 3] - r.positions, axis=1)
    rel = [inverse(r.poses[k]) @ r.poses[k + 1] for k in range(len(r.poses) - 1)]
    rel_e = [inverse(A[k]) @ A[k + 1] for k in range(len(A) - 1)]
    rpe = np.array([np.linalg.norm((inverse(a) @ b)[:3, 3]) for a, b in zip(rel, rel_e)])
    rpe_rot = np.degrees([rotation_angle(inverse(a) @ b) for a, b in zip(rel, rel_e)])
    fig, axes = plt.subplots(2, 1, figsize=(9, 5.6), sharex=True)
    mean, med, std = float(ape.mean()), float(np.median(ape)), float(ape.std())
    axes[0].plot(t, ape, color="#c0392b", lw=0.8, label="APE")
    axes[0].axhline(mean, color="k", lw=0.9, label=f"mean {mean:.3f} m")
    axes[0].axhline(med, color="#1a9a1a", lw=0.9, ls="--", label=f"median {med:.3f} m")
    axes[0].axhspan(mean - std, mean + std, color="0.6", alpha=0.25, label=f"±1 std {std:.3f} m")
    axes[0].set_ylabel("APE [m]")
    axes[0].legend(fontsize=8, loc="upper left")
    axes[1].plot(t[1:], rpe, color="#7a1fa0", lw=0.8, label="RPE trans (consecutive poses)")
    axes[1].set_ylabel("RPE [m/frame]")
    axes[1].set_xlabel("time [s]")
    axes[1].legend(fontsize=8, loc="upper left")
    for ax in axes:
        ax.grid(alpha=0.3)
    out.append((png_data_uri(fig, dpi), f"{name}: absolute position error (APE) and relative error (RPE) "
                "against time", "evo-ape"))
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.2))
    for ax, values, label in ((axes[0], ape, "APE [m]"), (axes[1], rpe, "RPE [m/frame]"),
                              (axes[2], rpe_rot, "RPE [deg/frame]")):
        ax.hist(values, bins=40, color="#1f5fd0", alpha=0.8)
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("poses")
    out.append((png_data_uri(fig, dpi), f"{name}: histograms of the errors", "evo-hist"))
    return out


def landmarks_figure(rec: RunRecord, dpi: int = 100) -> str:
    """EKF runs: the robot path and every feature with its 3σ ellipse, coloured by credibility;
    the true landmarks as black crosses when the log knows them."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 9))
    if rec.poses is not None:
        ax.plot(rec.poses.positions[:, 0], rec.poses.positions[:, 1], color="#1f5fd0", lw=0.8, label="EKF path")
    cmap = plt.get_cmap("RdYlGn")
    lms = rec.landmarks or []
    if lms:
        xy = np.array([[lm["x"], lm["y"]] for lm in lms])
        C = np.array([[[lm["var_xx"], lm["var_xy"]], [lm["var_xy"], lm["var_yy"]]] for lm in lms])
        colors = cmap(np.clip([lm["credibility"] for lm in lms], 0, 1))
        _ellipses(ax, xy, C, 3.0, edgecolors=colors, linewidths=1.1)
        ax.scatter(xy[:, 0], xy[:, 1], marker="+", c=colors, s=30, label="features")
    if rec.truth_landmarks is not None and len(rec.truth_landmarks):
        ax.scatter(rec.truth_landmarks[:, 0], rec.truth_landmarks[:, 1], marker="x", color="k", s=22, lw=0.9,
                   label=f"true landmarks ({len(rec.truth_landmarks)})")
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, 1))
    fig.colorbar(sm, ax=ax, shrink=0.7, label="credibility c_t")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(fontsize=8)
    return png_data_uri(fig, dpi)


def nees_figure(nees: dict, dpi: int = 100) -> str:
    """Mean NEES per step of the estimators in ``nees.json`` with the 95 % band."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 3.8))
    for key, label in (("ekf_mean_nees", "EKF"), ("ekf_fej_mean_nees", "FEJ-EKF"), ("graph_mean_nees", "smoother")):
        if nees.get(key):
            ax.plot(nees[key], lw=0.9, label=label)
    lo, hi = nees.get("band_95", [None, None])
    if lo is not None:
        ax.axhspan(lo, hi, color="0.85", label="95 % band")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("mean NEES")
    ax.legend(fontsize=8)
    return png_data_uri(fig, dpi)


def pose_nees_figure(times: np.ndarray, nees: np.ndarray, dpi: int = 100) -> str:
    """NEES per step of one run (log scale) with the single-step 95 % chi-square band (3 DOF)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 3.6))
    t = np.asarray(times) - times[0]
    ax.axhspan(0.2158, 9.348, color="0.88", label="95 % band (χ², 3 DOF)")
    ax.plot(t, np.clip(nees, 1e-3, None), lw=0.7, color="#1f5fd0", label="NEES")
    ax.axhline(3.0, color="k", lw=0.6, ls="--")
    ax.set_yscale("log")
    ax.set_xlabel("time since start [s]")
    ax.set_ylabel("NEES")
    ax.legend(fontsize=8)
    return png_data_uri(fig, dpi)
