"""Benchmark the HTML report against the run it reports on: size, time, memory.

Usage:
    python tools/bench_report.py LOG --out DIR [--reference REF] [--raw RAW] [--repeat N]

Runs ``submapslam run LOG --out DIR/run`` once, then ``submapslam report`` on that folder N
times with ``--ref`` (when given) and N times without, each a fresh process timed by wall clock
from start to exit (Python start-up and imports included), peak memory from the child's
``ru_maxrss``. Prints a markdown table: the run and the report, and the report's time as a
share of the run's (the issue's target: <= 10 %), the report's size (target: <= 10 MB).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def timed(cmd: list[str]) -> tuple[float, float, float]:
    """Run ``cmd`` in a child process; return (wall seconds, CPU seconds user + system, its peak
    resident MiB)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)  # the child's own rusage, not all children's
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{proc.stderr.read().decode()[-2000:]}")
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024.0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("log", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--reference", type=Path)
    ap.add_argument("--raw", type=Path, help="raw CARMEN log when REF is a corrected CARMEN log")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--max-scans", type=int)
    args = ap.parse_args(argv)
    cli = [sys.executable, "-m", "submapslam"]
    run_dir = args.out / "run"
    args.out.mkdir(parents=True, exist_ok=True)
    run_cmd = [*cli, "run", str(args.log), "--out", str(run_dir), "--overwrite"]  # the bench's own folder
    if args.max_scans:
        run_cmd += ["--max-scans", str(args.max_scans)]
    run_wall, run_cpu, run_mem = timed(run_cmd)
    rows = [("run", run_wall, run_cpu, run_mem, None)]
    variants = [("report", [])]
    if args.reference:
        ref = ["--ref", str(args.reference)] + (["--raw-log", str(args.raw)] if args.raw else [])
        variants.insert(0, ("report --ref", ref))
    for name, extra in variants:
        page = args.out / f"{name.replace(' ', '').replace('--', '_')}.html"
        if page.exists():
            page.unlink()
        times, cpus, mems = [], [], []
        for _ in range(max(1, args.repeat)):
            wall, cpu, mem = timed([*cli, "report", str(run_dir), "--out", str(page), *extra])
            times.append(wall)
            cpus.append(cpu)
            mems.append(mem)
        rows.append((name, statistics.median(times), statistics.median(cpus), max(mems), page.stat().st_size))
    summary = json.loads((run_dir / "summary.json").read_text())
    print(f"{summary['scans']} scans, {summary['submaps']} submaps, {summary['loop_candidates_tested']} hypotheses; "
          f"report times: median of {args.repeat}; this process's children peak {resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024:.0f} MiB")
    print("| step | wall time [s] | share of the run's wall time | CPU time [s] | share of the run's CPU time "
          "| peak memory [MiB] | file size [MB] |")
    print("|---|---|---|---|---|---|---|")
    for name, wall, cpu, mem, size in rows:
        share = "–" if name == "run" else f"{100 * wall / run_wall:.1f} %"
        cpu_share = "–" if name == "run" else f"{100 * cpu / run_cpu:.1f} %"
        print(f"| {name} | {wall:.2f} | {share} | {cpu:.2f} | {cpu_share} | {mem:.0f} | "
              f"{'–' if size is None else f'{size / 1e6:.2f}'} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
