"""Dynamic-point removal side by side: ``submapslam clean``, DUFOMap and no removal, same scans and poses.

Usage:
    python tools/bench_dynamic.py LOG [--poses TRAJ] [--out DIR] [--methods clean,dufomap,none]
                                  [--dufomap "0.1,0.2,2;0.2,0.2,1"]

LOG is a labelled log folder (``scans/`` + ``labels/NNNNNN.label``, e.g. ``submapslam synth kitti
--movers 80``); TRAJ one pose per scan that the methods use (default: the log's ground truth),
e.g. ``run``'s own ``poses_tum.txt``: it is moved into the ground truth's frame by its first pose
(``T_gt[0] @ inv(T_traj[0])``, no other alignment), and the maps are always scored against the
log's ground truth, so drift costs static accuracy as it would in a real map. Every method runs in its
own child process, so its wall time (around the whole run: reading the scans, the removal and
writing the map) and peak memory (``ru_maxrss`` of that process) are its own. Each map is then
scored with ``submapslam eval-map``'s DynamicMap scores (0.1 m voxels, 0.15 m radius). Prints a
markdown table; ``--out`` keeps the maps and ``results.json``.

DUFOMap (``pip install dufomap``, Duberg et al., RA-L 2024) is run as its authors' Python
binding: every scan integrated from the sensor pose, one propagation pass, then every scan's
points segmented; its static points are voxel-downsampled at 0.1 m for the map. Settings are
``resolution, d_s, d_p``; the published KITTI setting is 0.1, 0.2, 2.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _poses_in_truth_frame(log: Path, poses: Path | None) -> np.ndarray:
    """The poses the methods use ``(S, 4, 4)``, in the frame of the log's ground truth."""
    from submapslam.io.labels import count_scans, scan_poses

    n = count_scans(log)
    truth = scan_poses(log, None, n)
    if poses is None:
        return truth
    est = scan_poses(log, poses, n)
    return truth[0] @ np.linalg.inv(est[0]) @ est


def _scans_and_poses(log: Path, poses: Path | None):
    from submapslam.io.registry import open_log

    reader = open_log(log)
    T = _poses_in_truth_frame(log, poses)
    T_bs = getattr(reader, "T_base_sensor", None)
    return reader, T, np.eye(4) if T_bs is None else T_bs


def _downsample(points: np.ndarray, voxel: float = 0.1) -> np.ndarray:
    from submapslam.mapping.dynamic_removal import VoxelAccumulator

    acc = VoxelAccumulator(voxel)
    acc.add(points, 0)
    return acc.result()[1]


def child(method: str, log: Path, poses: Path | None, out: Path, setting: str) -> dict:
    """Run one method; write ``out/map.ply``; return wall time and peak memory."""
    from submapslam.io.ply import write_ply

    t0 = time.perf_counter()
    if method == "clean":
        from submapslam.api import clean_log
        from submapslam.io.trajectory import Trajectory, read_tum, write_tum

        traj = log / "groundtruth_tum.txt"
        if poses is not None:
            traj = out / "poses_in_truth_frame_tum.txt"
            write_tum(traj, Trajectory(read_tum(log / "groundtruth_tum.txt").timestamps, _poses_in_truth_frame(log, poses)))
        s = clean_log(log, traj, out / "clean")
        (out / "map.ply").symlink_to(out / "clean" / "map_static.ply")
        extra = {"points_removed": s["points_removed"]}
    else:
        reader, T, T_bs = _scans_and_poses(log, poses)
        static: list[np.ndarray] = []
        extra = {}
        if method == "none":
            from submapslam.mapping.dynamic_removal import VoxelAccumulator

            acc = VoxelAccumulator(0.1)
            for k, scan in enumerate(reader):
                acc.add(scan.points @ T[k][:3, :3].T + T[k][:3, 3], k)
            static.append(acc.result()[1])
        elif method == "dufomap":
            from dufomap import dufomap

            res, d_s, d_p = setting.split(",")
            dm = dufomap(float(res), float(d_s), int(d_p), num_threads=1)
            scans = []
            for k, scan in enumerate(reader):
                T_ws = T[k] @ T_bs
                p_sensor = (scan.points - T_bs[:3, 3]) @ T_bs[:3, :3]
                dm.run(p_sensor, T_ws, cloud_transform=True)
                scans.append(p_sensor.astype(np.float32))
            dm.oncePropagateCluster(if_propagate=True, if_cluster=False)
            removed = 0
            for k, p_sensor in enumerate(scans):
                T_ws = T[k] @ T_bs
                world = p_sensor @ T_ws[:3, :3].T + T_ws[:3, 3]
                dyn = dm.segment(world, T_ws, cloud_transform=False).astype(bool)
                removed += int(dyn.sum())
                static.append(world[~dyn])
            static = [_downsample(np.vstack(static))]
            extra = {"points_removed": removed}
        else:
            raise SystemExit(f"unknown method {method}")
        write_ply(out / "map.ply", np.vstack(static).astype(np.float32))
    return {"seconds": round(time.perf_counter() - t0, 2),
            "peak_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1), **extra}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("log", type=Path)
    ap.add_argument("--poses", type=Path)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--methods", default="clean,dufomap,none")
    ap.add_argument("--dufomap", default="0.1,0.2,2;0.2,0.2,1", help="resolution,d_s,d_p settings, ';'-separated")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--setting", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.log, args.poses, args.out, args.setting)))
        return
    from submapslam.api import evaluate_map_file

    tmp = None
    if args.out is None:
        tmp = tempfile.TemporaryDirectory()
        args.out = Path(tmp.name)
    runs = []
    for method in args.methods.split(","):
        for setting in (args.dufomap.split(";") if method == "dufomap" else [""]):
            name = method + (f" ({setting})" if setting else "")
            folder = args.out / (method + ("_" + setting.replace(",", "_") if setting else ""))
            folder.mkdir(parents=True, exist_ok=True)
            cmd = [sys.executable, __file__, str(args.log), "--child", method, "--setting", setting, "--out", str(folder)]
            if args.poses:
                cmd += ["--poses", str(args.poses)]
            proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
            if proc.returncode:
                raise SystemExit(f"{name} failed:\n{proc.stderr[-2000:]}")
            stats = json.loads(proc.stdout.strip().splitlines()[-1])
            scores = evaluate_map_file(folder / "map.ply", args.log)  # always against the ground truth
            runs.append({"method": name, **stats, **{k: scores[k] for k in ("SA", "DA", "AA", "static_voxels",
                                                                            "dynamic_voxels", "map_points")}})
            print(f"done: {name}", file=sys.stderr)
    n_scans = len(list((args.log / "scans").glob("*")))
    print(f"| method ({n_scans} scans) | SA | DA | AA | wall time [s] | peak memory [MiB] |")
    print("|---|---|---|---|---|---|")
    for r in runs:
        print(f"| {r['method']} | {r['SA']:.4f} | {r['DA']:.4f} | {r['AA']:.4f} | {r['seconds']:.1f} | {r['peak_mb']:.0f} |")
    (args.out / "results.json").write_text(json.dumps(runs, indent=2) + "\n")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
