"""Cut a CARMEN log: every ``--every``-th laser scan, every other line kept, as a new log file.

Usage:
    python tools/cut_carmen_log.py SRC DST --every K

SRC is a CARMEN log (plain, ``.gz``, ``.bz2`` or ``.xz``); DST (must not exist) gets the same lines with only
every K-th line of each laser record (FLASER, RLASER, ROBOTLASER1/2, RAWLASER1..4: each counted on
its own from its first line): the wheels' ODOM lines and each kept FLASER's own pose stay, so the cut is the same recording at a
K-th of its scan rate, the motion between scans K times larger. Its scans keep their times and
ranges, so ``carmen_reference_trajectory(CORRECTED, DST)`` matches the corrected log to them as to
the original (``tools/bench_real2d.py --every K`` runs the cuts against the corrected logs).
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from submapslam.io.carmen import RECORD_PRIORITY  # noqa: E402  (every laser record the reader knows)
from submapslam.io.compression import open_text  # noqa: E402


def cut(src: Path, dst: Path, every: int) -> tuple[int, int]:
    """Write the cut of ``src`` into ``dst`` (must not exist); return (laser lines kept, laser lines)."""
    if every < 1:
        raise ValueError(f"--every must be at least 1, not {every}")
    if dst.exists():
        raise FileExistsError(f"{dst} exists: not overwritten")
    seen: Counter[str] = Counter()
    kept = 0
    with open_text(src) as lines, open(dst, "x") as out:
        for line in lines:
            record = line.split(" ", 1)[0]
            if record in RECORD_PRIORITY:
                seen[record] += 1
                if (seen[record] - 1) % every:
                    continue
                kept += 1
            out.write(line)
    return kept, sum(seen.values())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", type=Path)
    ap.add_argument("dst", type=Path)
    ap.add_argument("--every", type=int, required=True, help="keep every K-th laser scan")
    args = ap.parse_args(argv)
    try:
        kept, seen = cut(args.src, args.dst, args.every)
    except (OSError, ValueError) as exc:
        print(f"cut_carmen_log: {exc}", file=sys.stderr)
        return 1
    print(f"{args.dst}: {kept} of {seen} laser scans")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
