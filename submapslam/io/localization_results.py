"""Write a :class:`~submapslam.localization.LocalizationResult` to a folder."""

from __future__ import annotations

import csv
import json
from pathlib import Path

from ..localization import LocalizationResult
from .trajectory import Trajectory, write_kitti, write_tum, write_tum_cov


def write_localization(result: LocalizationResult, out_dir: str | Path, extra: dict | None = None) -> dict[str, Path]:
    """Write ``poses_tum.txt`` (one line per scan, the log's timestamps), ``poses_kitti.txt``,
    ``localization.csv`` (timestamp, fitness over all scan points, fitness over the scan points inside
    the mapped area, inlier rmse, lost; one row per scan) and ``summary.json``
    (:meth:`LocalizationResult.summary` plus ``extra``); with covariances also ``poses_cov.txt``
    (:func:`~.trajectory.write_tum_cov`) and ``uncertainty.png`` (σ of each pose against time, lost
    spans shaded); return ``{name: path}``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {name: out / name for name in ("poses_tum.txt", "poses_kitti.txt", "localization.csv", "summary.json")}
    write_tum(paths["poses_tum.txt"], Trajectory(result.timestamps, result.poses))
    write_kitti(paths["poses_kitti.txt"], result.poses)
    with open(paths["localization.csv"], "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["timestamp", "fitness", "fitness_mapped", "rmse", "lost"])
        for t, f, fm, r, lost in zip(result.timestamps, result.fitness, result.fitness_mapped, result.inlier_rmse,
                                     result.lost):
            w.writerow([f"{t:.6f}", f"{f:.4f}", f"{fm:.4f}", f"{r:.4f}", int(lost)])
    if result.covariances is not None:
        from ..evaluation.uncertainty_figures import save_sigma_figure

        paths["poses_cov.txt"], paths["uncertainty.png"] = out / "poses_cov.txt", out / "uncertainty.png"
        write_tum_cov(paths["poses_cov.txt"], Trajectory(result.timestamps, result.poses), result.covariances)
        save_sigma_figure(paths["uncertainty.png"], result.poses[:, :3, 3], result.covariances, result.planar,
                          times=result.timestamps, lost=result.lost)
    paths["summary.json"].write_text(json.dumps({**result.summary(), **(extra or {})}, indent=2) + "\n")
    return paths
