"""Write a :class:`~submapslam.result.SlamResult` to a folder in formats other tools read."""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import numpy as np

from ..config import dump_config
from ..geometry import matrix_to_se2
from ..mapping.global_map import MapOutputs
from ..process_stats import combined_peak_mb, peak_memory_mb, peaks_by_process
from ..result import SlamResult
from .g2o import write_g2o
from .pcd import write_pcd
from .ply import write_ply
from .trajectory import Trajectory, write_kitti, write_tum, write_tum_cov


def write_results(result: SlamResult, out_dir: str | Path, maps: MapOutputs,
                  run_started: float | None = None) -> dict[str, Path]:
    """Write every output file of a run and its maps (:func:`~submapslam.mapping.global_map.
    build_map_outputs`); return ``{name: path}``. Nothing is computed here.

    Files: ``poses_tum.txt``, ``poses_kitti.txt``, ``odometry_tum.txt``, ``graph.g2o``,
    ``map.ply``, ``map_dynamic.ply`` (3D runs that split what moved off the map), with
    ``mapping.write_pcd`` the same clouds as ``map.pcd`` / ``map_dynamic.pcd``, ``config.yaml``, ``summary.json``, ``loops.csv``, ``submaps.csv`` (anchor poses,
    marginal standard deviations and the x-y covariance in the anchor frame, for ellipses),
    ``poses_cov.txt`` (every scan's pose and its 6x6 covariance: :func:`~.trajectory.write_tum_cov`), and
    for planar runs ``map.pgm`` + ``map.yaml`` (occupancy grid in the ROS map_server format,
    moving objects cleared; for 3D LiDAR from the obstacle slice of each scan).

    ``run_started``: ``time.perf_counter()`` at the start of the whole run (config, reading, maps
    and writing included); ``summary.json``'s ``wall_time_total_s`` is measured from it. None:
    the engine's time plus the maps' and the writing's.
    """
    t_start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {name: out / name for name in (
        "poses_tum.txt", "poses_kitti.txt", "odometry_tum.txt", "graph.g2o", "map.ply",
        "config.yaml", "summary.json", "loops.csv", "submaps.csv")}
    write_tum(paths["poses_tum.txt"], Trajectory(result.timestamps, result.poses))
    write_kitti(paths["poses_kitti.txt"], result.poses)
    write_tum(paths["odometry_tum.txt"], Trajectory(result.timestamps, result.odometry_poses))
    write_g2o(paths["graph.g2o"], result.submap_poses, result.edges)
    write_ply(paths["map.ply"], maps.points)
    if maps.dynamic_points is not None:
        paths["map_dynamic.ply"] = out / "map_dynamic.ply"
        write_ply(paths["map_dynamic.ply"], maps.dynamic_points)
    if result.config.mapping.write_pcd:
        clouds = {"map.pcd": maps.points, "map_dynamic.pcd": maps.dynamic_points}
        for name, points in clouds.items():
            if points is not None:
                paths[name] = out / name
                write_pcd(paths[name], points)
    paths["config.yaml"].write_text(dump_config(result.config))
    _write_loops(paths["loops.csv"], result)
    _write_submaps(paths["submaps.csv"], result)
    covariances = result.pose_covariances()
    if covariances is not None:
        paths["poses_cov.txt"] = out / "poses_cov.txt"
        write_tum_cov(paths["poses_cov.txt"], Trajectory(result.timestamps, result.poses), covariances)
    if maps.grid is not None:
        from .grid import write_pgm_yaml

        paths["map.pgm"], paths["map.yaml"] = write_pgm_yaml(out / "map", maps.grid, maps.origin, maps.resolution)
    # written last: the run's real wall time and the process's true peak include the maps and the writing
    summary = result.summary()
    writing = time.perf_counter() - t_start
    total = (time.perf_counter() - run_started if run_started is not None
             else result.wall_time_s + maps.seconds + writing)
    summary["wall_time_s"]["map_fusion"] = round(maps.seconds, 3)
    summary["wall_time_s"]["writing"] = round(writing, 3)
    summary["wall_time_total_s"] = round(total, 3)
    summary["scans_per_second"] = round(result.n_scans / max(total, 1e-9), 2)
    summary["cleared_cells"] = maps.cleared_cells
    if maps.dynamic_points is not None:
        summary["map_points"] = len(maps.points)
        summary["map_dynamic_points"] = len(maps.dynamic_points)
        # split off a submap, but another submap keeps that voxel in map.ply: not in map_dynamic.ply
        summary["moved_points_in_map"] = maps.moved_points_in_map
        # taken out of map.ply: as many submaps near it saw it move as kept it (mapping.moved_verdict_range)
        summary["map_left_points"] = maps.left_points
    if maps.vacated_points:
        summary["map_vacated_points"] = maps.vacated_points  # of them, where a later session saw the space empty
    # this process's, the odometry child's when it ran in one, and the map fusion's grid child's when
    # one ran beside this process (mapping.grid_process): process_stats.combined_peak_mb
    peaks = (peak_memory_mb(), result.peak_while_odometry_mb, result.odometry_peak_memory_mb)
    grids = None
    if maps.grid_process is not None:
        grids = (maps.grid_process["main_mb_while_child"], maps.grid_process["peak_mb"])
    summary["peak_memory_mb"] = round(combined_peak_mb(*peaks, grids=grids), 1)
    summary["peak_memory_mb_by_process"] = peaks_by_process(*peaks, grids=grids)
    paths["summary.json"].write_text(json.dumps(summary, indent=2) + "\n")
    return paths


def _write_loops(path: Path, result: SlamResult) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["submap_i", "submap_j", "source", "accepted", "fitness", "overlap", "inlier_rmse", "reason",
                    "final_check_blamed"])
        for lp in result.loops:
            w.writerow([lp.i, lp.j, lp.source, int(lp.accepted), f"{lp.fitness:.4f}", f"{lp.overlap:.4f}",
                        f"{lp.inlier_rmse:.4f}", lp.reason, lp.blamed])


def _write_submaps(path: Path, result: SlamResult) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "first_scan", "last_scan", "x", "y", "z", "yaw",
                    "sigma_x", "sigma_y", "sigma_z", "sigma_roll", "sigma_pitch", "sigma_yaw", "cov_xy"])
        for k, (T, cov, idx) in enumerate(zip(result.submap_poses, result.submap_covariances,
                                               result.submap_scan_indices)):
            sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
            x, y, yaw = matrix_to_se2(T)
            w.writerow([k, idx[0], idx[-1], f"{x:.4f}", f"{y:.4f}", f"{T[2, 3]:.4f}", f"{yaw:.6f}",
                        *(f"{v:.6g}" for v in (sd[3], sd[4], sd[5], sd[0], sd[1], sd[2], cov[3, 4]))])
