"""Planar speed and memory: ``submapslam run`` against KISS-ICP on the same 2D scans (issue 26).

Usage:
    python tools/bench_speed2d.py [LOG] [--out DIR] [--repeat N] [--tools submapslam kiss-icp]
                                  [--json FILE] [--max-scans N]

LOG defaults to ../shared/data/carmen/intel.clf.bz2. Each tool runs in its own child process,
one after the other (``--repeat`` times, alternating, so both see the same machine load):

* submapslam: ``python -m submapslam run LOG --out DIR/submapslam --overwrite`` (everything the
  CLI does: imports, reading, odometry, loops, scan refinement, every output file written);
* KISS-ICP: this script with ``--kiss-icp-child``: ``KissICP`` 1.3 (max_range 40 m, voxel
  0.1 m, no deskew, no wheel odometry) on the scans submapslam's own CARMEN reader yields.

Wall time is measured around the child process, peak memory is its own ``ru_maxrss`` from
``os.wait4`` (for submapslam the larger of its main and odometry processes), and, for submapslam,
its ``summary.json`` ``peak_memory_mb`` as well (both processes counted). Printed per run: wall,
user+sys CPU, peak RSS, and submapslam's ratios to KISS-ICP from the same round; plus a digest of
submapslam's ``poses_tum.txt`` (equal digests = bit-identical trajectories).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_LOG = REPO.parent / "shared" / "data" / "carmen" / "intel.clf.bz2"
KISS_MAX_RANGE_M = 40.0
KISS_VOXEL_M = 0.1


def run_child(cmd: list[str], log_file: Path) -> dict:
    """Run ``cmd``; its wall time [s], CPU time [s] and peak RSS [MiB] (its own, from ``wait4``)."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    with open(log_file, "wb") as fh:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"bench_speed2d: {cmd} failed ({proc.returncode}), see {log_file}")
    return {"wall_s": round(wall, 2), "cpu_s": round(usage.ru_utime + usage.ru_stime, 2),
            "peak_rss_mib": round(usage.ru_maxrss / 1024.0, 1)}


def kiss_icp_child(log: Path, max_scans: int | None, poses: Path | None = None) -> None:
    """KISS-ICP on ``log``'s scans as submapslam's reader yields them; prints the scan count and,
    with ``poses``, writes its trajectory there (TUM, stamped with the scans' timestamps)."""
    import numpy as np
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    from submapslam.io.registry import open_log
    from submapslam.io.trajectory import write_tum
    from submapslam.trajectory import Trajectory

    config = load_config(None)
    config.data.deskew = False
    config.data.max_range = KISS_MAX_RANGE_M
    config.mapping.voxel_size = KISS_VOXEL_M
    odom = KissICP(config)
    n = 0
    stamps, trajectory = [], []
    for scan in open_log(log):
        if max_scans is not None and n >= max_scans:
            break
        pts = np.ascontiguousarray(scan.points, dtype=np.float64)
        odom.register_frame(pts, np.zeros(len(pts)))
        if poses is not None:
            stamps.append(scan.timestamp)
            trajectory.append(np.array(odom.last_pose, dtype=np.float64))
        n += 1
    if poses is not None:
        write_tum(poses, Trajectory(np.array(stamps), np.array(trajectory).reshape(-1, 4, 4)))
    print(f"kiss-icp: {n} scans, last pose {odom.last_pose[:2, 3].round(3).tolist()}")


def _digest(path: Path) -> str:
    return hashlib.blake2b(path.read_bytes(), digest_size=8).hexdigest() if path.exists() else "-"


def _peak_both(summary: Path) -> float | str:
    """``summary.json``'s ``peak_memory_mb``: the run's peak with its odometry process counted
    (``wait4``'s ``ru_maxrss`` is the larger of the two processes, not their sum)."""
    try:
        return round(float(json.loads(summary.read_text())["peak_memory_mb"]), 1)
    except (OSError, ValueError, KeyError):
        return "-"


def bench(log: Path, out: Path, tools: list[str], repeat: int, max_scans: int | None) -> list[dict]:
    """``repeat`` rounds of every tool in ``tools``; one dict per round."""
    out.mkdir(parents=True, exist_ok=True)
    limit = [] if max_scans is None else ["--max-scans", str(max_scans)]
    rounds = []
    for r in range(repeat):
        row: dict = {"round": r}
        for tool in tools:
            if tool == "submapslam":
                cmd = [sys.executable, "-m", "submapslam", "run", str(log), "--out", str(out / "submapslam"),
                       "--overwrite", *limit]
            else:
                cmd = [sys.executable, __file__, "--kiss-icp-child", str(log), *limit]
            row[tool] = run_child(cmd, out / f"{tool}.log")
            print(f"bench_speed2d: round {r} {tool}: {row[tool]}", file=sys.stderr, flush=True)
        if "submapslam" in row:
            row["submapslam"]["poses_digest"] = _digest(out / "submapslam" / "poses_tum.txt")
            row["submapslam"]["peak_both_mib"] = _peak_both(out / "submapslam" / "summary.json")
        if "submapslam" in row and "kiss-icp" in row:
            s, k = row["submapslam"], row["kiss-icp"]
            row["ratio_wall"] = round(s["wall_s"] / k["wall_s"], 3)
            row["ratio_cpu"] = round(s["cpu_s"] / k["cpu_s"], 3)
            row["ratio_rss"] = round(s["peak_rss_mib"] / k["peak_rss_mib"], 3)
            if isinstance(s["peak_both_mib"], float):
                row["ratio_rss_both"] = round(s["peak_both_mib"] / k["peak_rss_mib"], 3)
        rounds.append(row)
    return rounds


def markdown(rounds: list[dict]) -> str:
    lines = ["| round | submapslam wall [s] | CPU [s] | peak RSS [MiB] | both processes [MiB] | KISS-ICP wall [s] | "
             "CPU [s] | peak RSS [MiB] | wall ratio | CPU ratio | poses digest |", "|---" * 11 + "|"]
    for row in rounds:
        s, k = row.get("submapslam", {}), row.get("kiss-icp", {})
        lines.append(f"| {row['round']} | {s.get('wall_s', '-')} | {s.get('cpu_s', '-')} | {s.get('peak_rss_mib', '-')} "
                     f"| {s.get('peak_both_mib', '-')} "
                     f"| {k.get('wall_s', '-')} | {k.get('cpu_s', '-')} | {k.get('peak_rss_mib', '-')} "
                     f"| {row.get('ratio_wall', '-')} | {row.get('ratio_cpu', '-')} | {s.get('poses_digest', '-')} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("log", nargs="?", type=Path, default=DEFAULT_LOG)
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_speed2d"))
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--tools", nargs="+", choices=["submapslam", "kiss-icp"], default=["submapslam", "kiss-icp"])
    ap.add_argument("--max-scans", type=int)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--kiss-icp-child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--poses", type=Path, help=argparse.SUPPRESS)  # the child: where to write its TUM poses
    args = ap.parse_args(argv)
    if args.kiss_icp_child:
        sys.path.insert(0, str(REPO))
        kiss_icp_child(args.log, args.max_scans, args.poses)
        return 0
    rounds = bench(args.log, args.out, args.tools, args.repeat, args.max_scans)
    print(markdown(rounds))
    if args.json:
        args.json.write_text(json.dumps({"log": str(args.log), "rounds": rounds}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
