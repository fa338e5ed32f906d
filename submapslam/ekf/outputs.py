"""Write the stochastic map's results: landmarks.csv, poses_tum.txt, summary.json, the map plot."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from ..geometry import se2_array_to_matrices
from ..io.trajectory import Trajectory, write_tum
from .runner import EkfRun


def write_landmarks_csv(path: Path, landmarks: list[dict]) -> None:
    """``id,x,y,var_xx,var_xy,var_yy,credibility`` per feature."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "x", "y", "var_xx", "var_xy", "var_yy", "credibility"])
        for lm in landmarks:
            w.writerow([lm["id"], *(f"{lm[k]:.6f}" for k in ("x", "y")), *(f"{lm[k]:.6g}" for k in ("var_xx", "var_xy", "var_yy")),
                        f"{lm['credibility']:.4f}"])


def plot_map(path: Path, run: EkfRun, truth_landmarks: dict[int, np.ndarray] | None = None,
             truth_poses: np.ndarray | None = None) -> None:
    """Features with 3-sigma uncertainty ellipses coloured by credibility (seed fig. 5.39)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse

    fig, ax = plt.subplots(figsize=(8, 8))
    if truth_poses is not None:
        ax.plot(truth_poses[:, 0], truth_poses[:, 1], color="0.7", lw=0.8, label="ground truth path")
    ax.plot(run.poses[:, 0], run.poses[:, 1], "b-", lw=0.8, label="EKF path")
    cmap = plt.get_cmap("viridis")
    for lm in run.filter.landmarks():
        C = np.array([[lm["var_xx"], lm["var_xy"]], [lm["var_xy"], lm["var_yy"]]])
        w, V = np.linalg.eigh(C)
        angle = np.degrees(np.arctan2(V[1, 1], V[0, 1]))
        color = cmap(lm["credibility"])
        ax.add_patch(Ellipse((lm["x"], lm["y"]), 6 * np.sqrt(max(w[1], 0)), 6 * np.sqrt(max(w[0], 0)), angle=angle,
                             fill=False, color=color, lw=1.2))
        ax.plot(lm["x"], lm["y"], "+", color=color)
    if truth_landmarks:
        t = np.array(list(truth_landmarks.values()))
        ax.plot(t[:, 0], t[:, 1], "kx", ms=5, label="ground-truth landmarks")
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, 1))
    fig.colorbar(sm, ax=ax, label="credibility c_t", shrink=0.7)
    ax.set_aspect("equal")
    ax.legend(fontsize=8, loc="best")
    ax.set_title("stochastic map: features, 3-sigma ellipses, credibility")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def write_ekf_results(out_dir: Path, run: EkfRun, summary: dict, truth_landmarks=None, truth_poses=None) -> dict[str, Path]:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {k: out / k for k in ("poses_tum.txt", "landmarks.csv", "summary.json", "landmarks.png")}
    write_tum(paths["poses_tum.txt"], Trajectory(run.times, se2_array_to_matrices(run.poses)))
    write_landmarks_csv(paths["landmarks.csv"], run.filter.landmarks())
    paths["summary.json"].write_text(json.dumps(summary, indent=2) + "\n")
    plot_map(paths["landmarks.png"], run, truth_landmarks, truth_poses)
    return paths
