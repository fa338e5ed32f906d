"""Benchmark the whole pipeline on a log: wall time per stage, peak memory, and ATE.

Usage:
    python tools/bench_pipeline.py LOG [--reference REF] [--raw RAW] [--config FILE] [--out DIR]

REF is a TUM/KITTI trajectory, or a corrected CARMEN log (then RAW, the raw CARMEN log, maps
its timestamps to the raw log's ipc_timestamps). Prints one markdown table row per measure.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("log", type=Path)
    ap.add_argument("--reference", type=Path)
    ap.add_argument("--raw", type=Path, help="raw CARMEN log when REF is a corrected CARMEN log")
    ap.add_argument("--config", type=Path)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--max-scans", type=int)
    args = ap.parse_args(argv)

    from submapslam.api import run_log
    from submapslam.evaluation.metrics import ate
    from submapslam.io.trajectory import Trajectory, carmen_reference_trajectory, read_trajectory

    out = args.out or Path(tempfile.mkdtemp(prefix="bench_"))
    t0 = time.perf_counter()
    result, _ = run_log(args.log, out, config=args.config, max_scans=args.max_scans, overwrite=True)
    wall = time.perf_counter() - t0
    s = result.summary()
    rows = [("scans", s["scans"]), ("submaps", s["submaps"]),
            ("loop candidates tested", s["loop_candidates_tested"]),
            ("loop closures accepted", s["loop_closures_accepted"]),
            ("wall time end to end incl. writing [s]", f"{wall:.1f}"),
            ("peak memory [MiB]", f"{s['peak_memory_mb']:.0f}")]
    rows += [(f"  stage {k} [s]", f"{v:.2f}") for k, v in s["wall_time_s"].items()]
    if args.reference:
        if args.raw:
            ref = carmen_reference_trajectory(args.reference, args.raw)
        else:
            ref = read_trajectory(args.reference)
        for name, poses in (("odometry", result.odometry_poses), ("submapslam", result.poses)):
            stats = ate(Trajectory(result.timestamps, poses), ref, align="se3")
            rows.append((f"ATE RMSE {name} [m] ({stats['n']} poses)", f"{stats['rmse']:.3f}"))
    print(f"| {args.log.name} | value |\n|---|---|")
    for k, v in rows:
        print(f"| {k} | {v} |")
    (out / "bench.json").write_text(json.dumps(dict(rows), indent=2, default=str) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
