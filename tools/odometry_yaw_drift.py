"""Where a planar odometry's heading error comes from: its yaw error accumulated scan by scan.

Usage:
    python tools/odometry_yaw_drift.py LOG [LOG ...] [--scans 400] [--at 5 10 20 40 100 200 399]

LOG is a synthetic 2D log folder (``submapslam synth rooms --out LOG``: ``groundtruth_tum.txt``
beside the scans). The odometry runs alone, in this process (no submaps, no loops), at the
config's defaults. Each scan's yaw increment is compared with the truth's. Printed per log: the
summed yaw error [deg] after each ``--at`` scan count, and the sums over the scans where the
truth turns and where it goes straight. Turning is a yaw change above 1e-4 rad between scans.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def yaw_errors(log: Path, scans: int) -> tuple[np.ndarray, np.ndarray]:
    """Per scan after the first: the odometry's yaw increment error [rad] and the truth's increment [rad]."""
    from submapslam.config import PipelineConfig
    from submapslam.geometry import matrix_to_se2
    from submapslam.io.registry import open_log
    from submapslam.io.trajectory import read_tum
    from submapslam.odometry import Odometry

    odometry = Odometry(PipelineConfig().odometry, planar=True)
    yaws = []
    for k, scan in enumerate(open_log(log)):
        if k >= scans:
            break
        pose, _ = odometry.register(scan)
        yaws.append(matrix_to_se2(pose)[2])
    truth = read_tum(log / "groundtruth_tum.txt").poses[:len(yaws)]
    true_yaw = np.arctan2(truth[:, 1, 0], truth[:, 0, 0])
    d_est, d_true = np.diff(np.unwrap(yaws)), np.diff(np.unwrap(true_yaw))
    return d_est - d_true, d_true


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("logs", nargs="+", type=Path)
    ap.add_argument("--scans", type=int, default=400)
    ap.add_argument("--at", type=int, nargs="+", default=[5, 10, 20, 40, 100, 200, 399])
    args = ap.parse_args(argv)
    at = [n for n in args.at if n < args.scans]
    print("| log | " + " | ".join(f"after {n} scans" for n in at) + " | straight | turning |")
    print("|---|" + "---|" * (len(at) + 2))
    for log in args.logs:
        error, turn = yaw_errors(log, args.scans)
        total = np.rad2deg(np.cumsum(error))
        turning = np.abs(turn) > 1e-4
        cells = [f"{total[n - 1]:+.3f}" for n in at if n - 1 < len(total)]
        print(f"| {log.name} | " + " | ".join(cells) +
              f" | {np.rad2deg(error[~turning].sum()):+.3f} ({int((~turning).sum())}) "
              f"| {np.rad2deg(error[turning].sum()):+.3f} ({int(turning.sum())}) |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
