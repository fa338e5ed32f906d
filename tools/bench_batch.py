"""Benchmark of ``submapslam batch``: the same logs on Ray and one after another.

    python tools/bench_batch.py LOG1 LOG2 LOG3 LOG4 --out out/bench_batch [--max-scans N]
    python tools/bench_batch.py LOG1 ... --out out/bench_cluster --address HOST:PORT

Runs ``batch --no-ray`` and ``batch`` (a local Ray instance) as separate processes, wall clock
around each whole command (and the front ends' share, as ``batch`` reports it), and checks that
every log's ``poses_tum.txt`` and the merged one are byte-identical between the two. Prints a
JSON summary. With ``--address`` (a cluster started apart with ``ray start``) it runs the local
Ray instance, then ``batch --address`` with the logs read in place (``--ship-logs never``) and
shipped through the object store (``always``); ratios are against the local instance. The
cluster's own processes are not this process's descendants: their CPU time is not counted.

Also the CPU time (user + system) of each whole process tree: this process is made the
"subreaper" of its descendants (Linux), so Ray's daemons and workers, orphaned when Ray shuts
down, are reaped here and counted too. ``cores_busy`` is CPU time over wall time; with ``C``
cores the Ray run can take no less than its CPU time / C, hence ``ratio_floor`` = Ray's CPU
time / (cores x the sequential wall time): the ratio the run would have with no core ever idle.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PR_SET_CHILD_SUBREAPER = 36


def become_subreaper() -> bool:
    """Orphaned descendants are re-parented to this process (Linux) rather than to init, so they
    stay in its tree and are counted. False where that is not available."""
    try:
        return ctypes.CDLL(None, use_errno=True).prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


class TreeCpu:
    """CPU seconds (user + system) of every process descended from this one, sampled from
    ``/proc`` every ``every_s`` while a command runs: each process's last reading counts (a
    process's last ``every_s`` may be missed)."""

    def __init__(self, every_s: float = 0.2) -> None:
        self.every_s, self.last, self.me = every_s, {}, os.getpid()
        self.tick = os.sysconf("SC_CLK_TCK")

    def sample(self) -> None:
        parent, cpu = {}, {}
        for entry in os.listdir("/proc"):
            if not entry.isdigit():
                continue
            try:
                with open(f"/proc/{entry}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            parent[int(entry)] = int(fields[1])
            cpu[int(entry)] = (int(fields[11]) + int(fields[12])) / self.tick
        for pid in cpu:
            p, hops = parent.get(pid), 0
            while p and p != self.me and hops < 64:
                p, hops = parent.get(p), hops + 1
            if p == self.me:
                self.last[pid] = cpu[pid]

    def run(self, command: list[str], cwd: Path, env: dict) -> tuple[str, float, float]:
        """Run ``command`` while sampling; returns its standard output, its wall time (to its
        end) and its tree's CPU seconds (descendants that outlive it are waited for, up to
        30 s). A failure raises with its standard error."""
        self.last = {}
        with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
            t0 = time.perf_counter()
            proc = subprocess.Popen(command, cwd=cwd, env=env, stdout=out, stderr=err, text=True)
            while True:
                self.sample()
                try:
                    proc.wait(timeout=self.every_s)
                    break
                except subprocess.TimeoutExpired:
                    pass
            wall = time.perf_counter() - t0
            end = time.monotonic() + 30
            while time.monotonic() < end:
                self.sample()
                try:
                    pid, _ = os.waitpid(-1, os.WNOHANG)  # orphans re-parented here
                except ChildProcessError:
                    break
                if pid == 0:
                    time.sleep(self.every_s)
            out.seek(0)
            err.seek(0)
            if proc.returncode:
                raise SystemExit(f"{' '.join(command)} failed:\n{err.read()}")
            return out.read(), wall, sum(self.last.values())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", type=Path, nargs="+")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--max-scans", type=int)
    ap.add_argument("--address", help="a Ray cluster's HOST:PORT: compare batch through it with the local default")
    args = ap.parse_args()
    extra = ["--max-scans", str(args.max_scans)] if args.max_scans else []
    counted = become_subreaper()
    tree = TreeCpu()
    walls, front, cpu = {}, {}, {}
    modes = (("sequential", ["--no-ray"]), ("ray", [])) if args.address is None else (
        ("ray", []), ("cluster", ["--address", args.address, "--ship-logs", "never"]),
        ("cluster_shipped", ["--address", args.address, "--ship-logs", "always"]))
    for mode, flags in modes:
        out = args.out / mode
        shutil.rmtree(out, ignore_errors=True)
        stdout, walls[mode], cpu[mode] = tree.run(
            [sys.executable, "-m", "submapslam", "batch", *map(str, args.logs), "--out", str(out), *flags, *extra],
            cwd=REPO, env={**os.environ, "COLUMNS": "200"})
        print(stdout)
        found = re.search(r"front ends ([0-9.]+) s", stdout)
        front[mode] = float(found.group(1)) if found else None
    if args.address is not None:
        first = args.out / "ray"
        names = sorted(p.name for p in first.iterdir() if (p / "poses_tum.txt").is_file())
        print(json.dumps({"logs": len(args.logs), "address": args.address,
                          **{f"wall_{m}_s": round(walls[m], 1) for m, _ in modes},
                          **{f"front_ends_{m}_s": front[m] for m, _ in modes},
                          "ratio_cluster": round(walls["cluster"] / walls["ray"], 3),
                          "ratio_cluster_shipped": round(walls["cluster_shipped"] / walls["ray"], 3),
                          "identical": {f"{m}/{n}": (args.out / m / n / "poses_tum.txt").read_bytes()
                                        == (first / n / "poses_tum.txt").read_bytes()
                                        for m in ("cluster", "cluster_shipped") for n in names}}, indent=1))
        return
    names = sorted(p.name for p in (args.out / "sequential").iterdir() if (p / "poses_tum.txt").is_file())
    same = {n: (args.out / "ray" / n / "poses_tum.txt").read_bytes()
            == (args.out / "sequential" / n / "poses_tum.txt").read_bytes() for n in names}
    print(json.dumps({"logs": len(args.logs), "wall_sequential_s": round(walls["sequential"], 1),
                      "wall_ray_s": round(walls["ray"], 1), "ratio": round(walls["ray"] / walls["sequential"], 3),
                      "front_ends_sequential_s": front["sequential"], "front_ends_ray_s": front["ray"],
                      "front_end_ratio": round(front["ray"] / front["sequential"], 3)
                      if front["sequential"] and front["ray"] else None,
                      "cpu_sequential_s": round(cpu["sequential"], 1), "cpu_ray_s": round(cpu["ray"], 1),
                      "cores_busy_sequential": round(cpu["sequential"] / walls["sequential"], 2),
                      "cores_busy_ray": round(cpu["ray"] / walls["ray"], 2),
                      "ratio_floor": round(cpu["ray"] / ((os.cpu_count() or 1) * walls["sequential"]), 3)
                      if counted else None,
                      "identical": same}, indent=1))


if __name__ == "__main__":
    main()
