"""Benchmark localization in a fixed map: scans/s and ATE.

Usage:
    python tools/bench_localization.py synthetic [--world rectangle] [--out DIR]
    python tools/bench_localization.py carmen LOG REF [--map-scans N] [--out DIR] [--map-run DIR] [--max-scans N]

``synthetic``: a map from one run of the world (``submapslam run``, two laps), then a
*different* run in the same world (other speed, twice the odometry noise, so other scan places
and other noise) localised in it; errors against the generator's ground truth expressed in the
map frame (the mapping run's first ground-truth pose), without any alignment.

``carmen``: a map from the first N scans of a real CARMEN log (``submapslam run --max-scans N``),
then the remaining scans localised in it starting from a global search (no initial pose); ATE
against the corrected reference REF (one SE(3) alignment for the whole localised part, as
``submapslam eval --raw-log`` does). Prints one markdown table row per measure. For iterating:
``--map-run DIR`` reuses the map of an earlier run (e.g. ``OUT/map_run``) instead of building it,
``--max-scans N`` localises only the first N scans after the map's.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _rows_table(title: str, rows: list[tuple[str, object]]) -> str:
    return "\n".join([f"| {title} | value |", "|---|---|", *(f"| {k} | {v} |" for k, v in rows)])


def synthetic(world: str, out: Path) -> list[tuple[str, object]]:
    from datasets_synth import generate
    from submapslam.api import run_log
    from submapslam.io.registry import open_log
    from submapslam.io.trajectory import read_tum
    from submapslam.localization import localize_log

    planar = world != "outdoor"
    map_log = generate(world, out / "map_log", seed=0, laps=2)
    t0 = time.perf_counter()
    slam, _ = run_log(map_log, out / "map_run", overwrite=True)
    t_map = time.perf_counter() - t0
    loc_log = generate(world, out / "loc_log", seed=0, laps=1, speed=0.8 if planar else 6.5, odometry_noise=2.0)
    gt_map, gt = read_tum(map_log / "groundtruth_tum.txt"), read_tum(loc_log / "groundtruth_tum.txt")
    T_map_gt = np.linalg.inv(gt_map.poses[0])
    slam_err = np.linalg.norm(slam.poses[:, :3, 3] - (T_map_gt @ gt_map.poses)[:, :3, 3], axis=1)
    rows: list[tuple[str, object]] = [("map run: scans, wall time [s]", f"{slam.n_scans}, {t_map:.1f}"),
                                      ("map run: position RMSE vs ground truth [m]", f"{np.sqrt(np.mean(slam_err**2)):.3f}")]
    for label, init in (("initial pose given", T_map_gt @ gt.poses[0]), ("global initialisation", None)):
        res = localize_log(open_log(loc_log), out / "map_run", initial_pose=init)
        err = np.linalg.norm(res.poses[:, :3, 3] - (T_map_gt @ gt.poses[: res.n_scans])[:, :3, 3], axis=1)
        tracked = ~res.lost
        s = res.summary()
        rows += [(f"{label}: scans, lost, scans/s", f"{s['scans']}, {s['lost_scans']}, {s['scans_per_s']}"),
                 (f"{label}: position RMSE / max, tracked scans [m]",
                  f"{np.sqrt(np.mean(err[tracked] ** 2)):.3f} / {err[tracked].max():.3f}"),
                 (f"{label}: position RMSE, all scans [m]", f"{np.sqrt(np.mean(err**2)):.3f}")]
    return rows


def carmen(log: Path, ref_path: Path, map_scans: int, out: Path, map_run: Path | None = None,
           max_scans: int | None = None) -> list[tuple[str, object]]:
    from submapslam.api import run_log
    from submapslam.evaluation.metrics import ate
    from submapslam.io.registry import open_log
    from submapslam.io.trajectory import Trajectory, carmen_reference_trajectory, read_tum
    from submapslam.localization import localize_log

    ref = carmen_reference_trajectory(ref_path, log)
    if map_run is None:
        map_run = out / "map_run"
        t0 = time.perf_counter()
        slam, _ = run_log(log, map_run, max_scans=map_scans, overwrite=True)
        t_map = f"{time.perf_counter() - t0:.1f}"
        slam_traj = Trajectory(slam.timestamps, slam.poses)
    else:
        t_map, slam_traj = "(reused)", read_tum(map_run / "poses_tum.txt")
    slam_ate = ate(slam_traj, ref)
    res = localize_log(open_log(log), map_run, start=map_scans, max_scans=max_scans)
    s = res.summary()
    (out / "localization_summary.json").write_text(json.dumps(s, indent=2) + "\n")
    est = Trajectory(res.timestamps, res.poses)
    a_all = ate(est, ref)
    tracked = Trajectory(res.timestamps[~res.lost], res.poses[~res.lost])
    a_trk = ate(tracked, ref)
    spans = res.lost_spans()
    longest = max((b - a + 1 for a, b in spans), default=0)
    return [("map: first N scans (submapslam run --max-scans N)", map_scans),
            ("map run: wall time [s], ATE RMSE [m]", f"{t_map}, {slam_ate['rmse']:.3f}"),
            ("localised scans (the rest of the log)", s["scans"]),
            ("initialised at scan (global search)", s["initialised_at_scan"]),
            ("lost scans / spans (longest) / relocalisations",
             f"{s['lost_scans']} / {len(spans)} ({longest}) / {s['relocalisations']}"),
            ("global searches", s["global_searches"]),
            ("wall time [s], scans/s", f"{s['wall_time_s']:.1f}, {s['scans_per_s']}"),
            ("  of which tracking / global search [s]", f"{s['time_s']['tracking']:.1f} / {s['time_s']['global_search']:.1f}"),
            (f"ATE RMSE / max, all scans [m] ({a_all['n']} poses)", f"{a_all['rmse']:.3f} / {a_all['max']:.3f}"),
            (f"ATE RMSE, tracked scans [m] ({a_trk['n']} poses)", f"{a_trk['rmse']:.3f}"),
            ("mean fitness: all scan points / mapped area", f"{s['mean_fitness']:.3f} / {s['mean_fitness_mapped']:.3f}")]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="mode", required=True)
    a = sub.add_parser("synthetic")
    a.add_argument("--world", default="rectangle")
    a.add_argument("--out", type=Path)
    b = sub.add_parser("carmen")
    b.add_argument("log", type=Path)
    b.add_argument("reference", type=Path, help="corrected CARMEN log of the same run")
    b.add_argument("--map-scans", type=int, help="scans in the map (default: half the log)")
    b.add_argument("--out", type=Path)
    b.add_argument("--map-run", type=Path, help="reuse this map folder (an earlier OUT/map_run) instead of building it")
    b.add_argument("--max-scans", type=int, help="localise only this many scans after the map's")
    args = ap.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_loc_"))
    out.mkdir(parents=True, exist_ok=True)
    if args.mode == "synthetic":
        rows = synthetic(args.world, out)
        title = f"synthetic {args.world}"
    else:
        from submapslam.io.registry import open_log

        n = args.map_scans or sum(1 for _ in open_log(args.log)) // 2
        rows = carmen(args.log, args.reference, n, out, args.map_run, args.max_scans)
        title = args.log.name
    print(_rows_table(title, rows))
    (out / "bench.json").write_text(json.dumps(dict(rows), indent=2, default=str) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
