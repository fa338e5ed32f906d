"""Accuracy on synthetic worlds: ATE of wheel odometry, scan-matching odometry and submapslam,
and how many accepted loop closures are false (transform off by more than 1 m from the truth).

Usage: python tools/bench_synthetic.py [--worlds rectangle rooms ...] [--laps 2] [--seed 0]

``--worlds scanners`` runs the 2D worlds with other scanners than the default SICK-like one: a
270 deg / 1081-beam (Hokuyo UTM-like), a 360 deg / 720-beam 12 m (RPLidar-like), a 240 deg /
682-beam 5.6 m (Hokuyo URG-like) and the default with 3 cm range noise.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

VARIANTS = {
    "rectangle": {},
    "rooms": {"size": (36.0, 12.0)},
    "figure8": {},
    "rectangle-sparse": {"world": "rectangle", "feature_density": 0.4, "sensor_options": {"max_range": 8.0}},
    "rectangle-short-range": {"world": "rectangle", "sensor_options": {"beams": 181, "range_noise": 0.03, "max_range": 10.0}},
    "outdoor": {"blocks": (2, 1)},
    # other 2D scanners than the SICK-like 180 deg / 361 beams / 30 m default
    "rooms-270": {"world": "rooms", "sensor_options": {"fov_deg": 270.0, "beams": 1081}},  # Hokuyo UTM-like
    "figure8-360": {"world": "figure8", "sensor_options": {"fov_deg": 360.0, "beams": 720, "max_range": 12.0}},  # RPLidar-like
    "figure8-240": {"world": "figure8", "sensor_options": {"fov_deg": 240.0, "beams": 682, "max_range": 5.6}},  # Hokuyo URG-like
    "figure8-noisy": {"world": "figure8", "sensor_options": {"range_noise": 0.03}},
}
SCANNERS = ["rooms-270", "figure8-360", "figure8-240", "figure8-noisy"]


def write_variant(name: str, out: Path, seed: int, laps: int) -> Path:
    """Generate the world or :data:`VARIANTS` entry ``name`` as a log folder ``out``."""
    from datasets_synth import generate

    opts = dict(VARIANTS.get(name, {}))
    world = opts.pop("world", name)
    return generate(world, out, seed=seed, laps=laps, **opts)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worlds", nargs="+", default=["rectangle", "rooms", "figure8", "rectangle-sparse", "rectangle-short-range"],
                    help=f"worlds or variants ({', '.join(VARIANTS)}); 'scanners' stands for {', '.join(SCANNERS)}")
    ap.add_argument("--laps", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    from submapslam.api import run_log
    from submapslam.evaluation.metrics import ate
    from submapslam.geometry import inverse
    from submapslam.io.trajectory import Trajectory, read_tum

    print("| world | scans | wheel ATE [m] | odometry ATE [m] | submapslam ATE [m] | loops accepted / tested | false closures | run time [s] |")
    print("|---|---|---|---|---|---|---|---|")
    for name in [w for world in args.worlds for w in (SCANNERS if world == "scanners" else [world])]:
        with tempfile.TemporaryDirectory() as tmp:
            log = write_variant(name, Path(tmp) / "log", args.seed, args.laps)
            t0 = time.perf_counter()
            res, _ = run_log(log, None)
            wall = time.perf_counter() - t0
            gt = read_tum(log / "groundtruth_tum.txt")
            wheel = ate(read_tum(log / "odometry_tum.txt"), gt)["rmse"]
        odo = ate(Trajectory(res.timestamps, res.odometry_poses), gt)["rmse"]
        slam = ate(Trajectory(res.timestamps, res.poses), gt)["rmse"]
        anchors = [gt.poses[idx[0]] for idx in res.submap_scan_indices]
        false = sum(1 for lp in res.loops if lp.accepted and
                    np.linalg.norm((inverse(inverse(anchors[lp.i]) @ anchors[lp.j]) @ lp.T_i_j)[:3, 3]) > 1.0)
        print(f"| {name} | {res.n_scans} | {wheel:.3f} | {odo:.3f} | {slam:.3f} | {res.loops_accepted} / {len(res.loops)} "
              f"| {false} | {wall:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
