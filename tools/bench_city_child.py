"""One peer of ``tools/bench_city.py`` in its own process: KISS-ICP or KISS-SLAM on a log.

Usage (started by bench_city.py, which times the process and reads its peak RSS with wait4):
    python tools/bench_city_child.py kiss-icp|kiss-slam LOG OUT [--max-scans N]

The scans are read with ``submapslam.io.registry.open_log`` -- the same reader, the same points
(in the robot's base frame, ``T_base_sensor`` of meta.yaml applied) that ``submapslam run``
gets. Each peer runs with its default configuration except ``deskew: false`` (the synthetic
scans are taken from one pose, there is no motion within a sweep); KISS-ICP's default max range
is 100 m, KISS-SLAM's too. Wheel odometry is not given to the peers (they do not read it).

OUT receives ``poses_tum.txt`` (one line per scan, the log's timestamps), ``odometry_tum.txt``
(KISS-SLAM: its KISS-ICP odometry before loop closure; KISS-ICP: the same as poses_tum.txt)
and ``result.json`` (scans, closures, the configuration used, a digest of every point read,
RSS samples for memory growth). This script may run under another interpreter (a separate venv
for KISS-SLAM), so it imports nothing from tools/ and only the light reader part of submapslam.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

_PAGE_MIB = os.sysconf("SC_PAGE_SIZE") / 2**20


def current_rss_mib() -> float:
    """Resident set of this process now [MiB] (``/proc/self/statm``)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * _PAGE_MIB
    except OSError:  # pragma: no cover - not Linux
        return float("nan")


class Recorder:
    """Poses, odometry, a digest of the input points and RSS samples, per scan."""

    def __init__(self, n_expected: int | None) -> None:
        self.stamps: list[float] = []
        self.poses: list[np.ndarray] = []
        self.odometry: list[np.ndarray] = []
        self.digest = hashlib.blake2b(digest_size=16)
        self.n_points = 0
        self.every = max(1, (n_expected or 1000) // 200)
        self.rss: list[tuple[int, float]] = []

    def scan(self, scan) -> np.ndarray:
        pts = np.ascontiguousarray(scan.points, dtype=np.float64)
        self.digest.update(pts.tobytes())
        self.n_points += len(pts)
        self.stamps.append(float(scan.timestamp))
        return pts

    def after(self, index: int) -> None:
        if index % self.every == 0:
            self.rss.append((index, round(current_rss_mib(), 1)))


def _scans(log: Path, max_scans: int | None):
    from submapslam.io.registry import open_log

    reader = open_log(log)
    try:
        n = len(reader)  # type: ignore[arg-type]
    except TypeError:
        n = None
    if max_scans is not None:
        n = min(n, max_scans) if n is not None else max_scans

    def gen():
        for k, scan in enumerate(reader):
            if max_scans is not None and k >= max_scans:
                return
            yield scan

    return gen(), n


def _times(scan) -> np.ndarray:
    t = scan.point_times
    return np.zeros(len(scan.points)) if t is None else np.asarray(t, dtype=np.float64)


def run_kiss_icp(log: Path, max_scans: int | None) -> tuple[Recorder, dict]:
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    config = load_config(None)  # defaults: max_range 100 m, voxel = max_range / 100 = 1 m
    config.data.deskew = False
    odom = KissICP(config)
    scans, n = _scans(log, max_scans)
    rec = Recorder(n)
    for k, scan in enumerate(scans):
        pts = rec.scan(scan)
        odom.register_frame(pts, _times(scan))
        rec.poses.append(odom.last_pose.copy())
        rec.after(k)
    rec.odometry = rec.poses
    import kiss_icp

    info = {"version": getattr(kiss_icp, "__version__", "?"), "config": config.model_dump(),
            "closures": None, "submaps": None, "loop_edges": None}
    return rec, info


def run_kiss_slam(log: Path, max_scans: int | None) -> tuple[Recorder, dict]:
    from submapslam._deps import open3d

    open3d()  # preloads libusb where the system lacks it, before kiss_slam imports open3d
    from kiss_slam.config import load_config
    from kiss_slam.slam import KissSLAM

    config = load_config(None)
    config.odometry.preprocessing.deskew = False
    slam = KissSLAM(config)
    closures: list[tuple[int, int, list]] = []
    compute = slam.closer.compute

    def recording_compute(query_id, points, graph):
        # pose_constraint maps the reference local map into the query's frame: T_query_ref
        good, ref_id, q_id, T = compute(query_id, points, graph)
        if good:
            closures.append((int(q_id), int(ref_id), np.asarray(T).tolist()))
        return good, ref_id, q_id, T

    slam.closer.compute = recording_compute
    node_first = {0: 0}
    T_odom_node = np.eye(4)
    scans, n = _scans(log, max_scans)
    rec = Recorder(n)
    k = -1
    for k, scan in enumerate(scans):
        pts = rec.scan(scan)
        node = slam.local_map_graph.last_local_map
        slam.process_scan(pts, _times(scan))
        if slam.local_map_graph.last_id != node.id:
            # a new local map starts at this scan; its keypose is this scan's pose
            T_odom_node = T_odom_node @ node.local_trajectory[-1]
            node_first[int(slam.local_map_graph.last_id)] = k
        rec.odometry.append(T_odom_node @ slam.odometry.last_pose)
        rec.after(k)
    # what KISS-SLAM's own SlamPipeline does at the end of the sequence
    slam.generate_new_node()
    slam.local_map_graph.erase_last_local_map()
    poses, _ = slam.fine_grained_optimization()
    rec.poses = [np.asarray(p) for p in poses]
    ids = sorted(node_first)
    ids = [i for i in ids if i in slam.local_map_graph.graph]
    submaps = [{"id": i, "first_scan": node_first[i],
                "last_scan": node_first[ids[m + 1]] if m + 1 < len(ids) else k}
               for m, i in enumerate(ids)]
    import kiss_slam

    version = getattr(kiss_slam, "__version__", None)
    if version is None:
        from importlib.metadata import version as _v

        version = _v("kiss-slam")
    info = {"version": version, "config": config.model_dump(), "closures": len(slam.closures),
            "submaps": submaps, "loop_edges": [{"i": i, "j": j, "T_i_j": T} for i, j, T in closures]}
    return rec, info


def _write_tum(path: Path, stamps: list[float], poses: list[np.ndarray]) -> None:
    from submapslam.io.trajectory import Trajectory, write_tum

    write_tum(path, Trajectory(np.asarray(stamps), np.asarray(poses)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("tool", choices=["kiss-icp", "kiss-slam"])
    ap.add_argument("log", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--max-scans", type=int)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    runner = run_kiss_icp if args.tool == "kiss-icp" else run_kiss_slam
    rec, info = runner(args.log, args.max_scans)
    seconds = time.perf_counter() - t0
    if len(rec.poses) != len(rec.stamps):
        raise SystemExit(f"{args.tool}: {len(rec.poses)} poses for {len(rec.stamps)} scans")
    _write_tum(args.out / "poses_tum.txt", rec.stamps, rec.poses)
    _write_tum(args.out / "odometry_tum.txt", rec.stamps, rec.odometry)
    result = {"tool": args.tool, "scans": len(rec.stamps), "points": rec.n_points,
              "points_digest": rec.digest.hexdigest(), "seconds_in_process": round(seconds, 3),
              "rss_samples": rec.rss, "python": sys.executable,
              "numpy": np.__version__, **info}
    (args.out / "result.json").write_text(json.dumps(result, indent=1, default=str) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
