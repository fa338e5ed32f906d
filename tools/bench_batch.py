"""Benchmark of ``submapslam batch``: the same logs on Ray and one after another.

    python tools/bench_batch.py LOG1 LOG2 LOG3 LOG4 --out out/bench_batch [--max-scans N]

Runs ``batch --no-ray`` and ``batch`` (a local Ray instance) as separate processes, wall clock
around each whole command (and the front ends' share, as ``batch`` reports it), and checks that every log's ``poses_tum.txt`` and the merged one are
byte-identical between the two. Prints a JSON summary.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", type=Path, nargs="+")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--max-scans", type=int)
    args = ap.parse_args()
    extra = ["--max-scans", str(args.max_scans)] if args.max_scans else []
    walls, front = {}, {}
    for mode, flags in (("sequential", ["--no-ray"]), ("ray", [])):
        out = args.out / mode
        shutil.rmtree(out, ignore_errors=True)
        t0 = time.perf_counter()
        done = subprocess.run([sys.executable, "-m", "submapslam", "batch", *map(str, args.logs), "--out", str(out),
                               *flags, *extra], check=True, cwd=REPO, capture_output=True, text=True,
                              env={**os.environ, "COLUMNS": "200"})
        walls[mode] = time.perf_counter() - t0
        print(done.stdout)
        found = re.search(r"front ends ([0-9.]+) s", done.stdout)
        front[mode] = float(found.group(1)) if found else None
    names = sorted(p.name for p in (args.out / "sequential").iterdir() if (p / "poses_tum.txt").is_file())
    same = {n: (args.out / "ray" / n / "poses_tum.txt").read_bytes()
            == (args.out / "sequential" / n / "poses_tum.txt").read_bytes() for n in names}
    print(json.dumps({"logs": len(args.logs), "wall_sequential_s": round(walls["sequential"], 1),
                      "wall_ray_s": round(walls["ray"], 1), "ratio": round(walls["ray"] / walls["sequential"], 3),
                      "front_ends_sequential_s": front["sequential"], "front_ends_ray_s": front["ray"],
                      "front_end_ratio": round(front["ray"] / front["sequential"], 3)
                      if front["sequential"] and front["ray"] else None,
                      "identical": same}, indent=1))


if __name__ == "__main__":
    main()
