"""Rewrite a CARMEN log's FLASER lines as ROBOTLASER1 or as RAWLASER1 + ODOM lines.

Usage: python tools/carmen_rewrite_records.py SRC DST --record robotlaser1|rawlaser1
                                              [--laser-offset X] [--max-lines N]

No log in ``../shared/data`` holds these records, so the reader of the newer formats is checked
by reading the same real scans written both ways: ``run`` and ``eval`` on the rewritten Intel
log against the same corrected reference (BENCHMARKS.md). ``robotlaser1`` writes each FLASER
scan with its beam layout (start angle, resolution, maximum range 81.9 m), a laser mounted
``--laser-offset`` m ahead of the robot (the ranges are unchanged, so the points move by the
offset) and the FLASER pose as the robot pose; the remission block is empty. ``rawlaser1``
writes the bare reading and an ``ODOM`` line with the FLASER pose at the scan's timestamp; the
log's own ODOM lines are dropped so that the odometry is the FLASER pose. Other lines are kept.
SRC and DST may be plain, ``.gz``, ``.bz2`` or ``.xz``.
"""

from __future__ import annotations

import argparse
import bz2
import gzip
import lzma
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from submapslam.io.carmen import beam_angles  # noqa: E402
from submapslam.io.compression import open_text  # noqa: E402

_WRITERS = {".gz": gzip.open, ".bz2": bz2.open, ".xz": lzma.open}


def rewrite_line(tokens: list[str], record: str, laser_offset: float = 0.0) -> list[str]:
    """The lines (with newlines) that replace one FLASER line's ``tokens``."""
    n = int(tokens[1])
    angles = beam_angles(n)
    ranges = " ".join(tokens[2: 2 + n])
    x, y, theta = (float(v) for v in tokens[2 + n: 5 + n])
    ipc, host, logger = tokens[8 + n], tokens[9 + n], tokens[10 + n]
    head = (f"0 {angles[0]:.9f} {math.pi:.9f} {angles[1] - angles[0]:.12f} 81.9 0.01 0 {n} {ranges} 0")
    if record == "robotlaser1":
        lx, ly = x + laser_offset * math.cos(theta), y + laser_offset * math.sin(theta)
        return [f"ROBOTLASER1 {head} {lx:.6f} {ly:.6f} {theta:.6f} {x:.6f} {y:.6f} {theta:.6f} "
                f"0 0 0 0 0 {ipc} {host} {logger}\n"]
    return [f"ODOM {x:.6f} {y:.6f} {theta:.6f} 0 0 0 {ipc} {host} {logger}\n",
            f"RAWLASER1 {head} {ipc} {host} {logger}\n"]


def rewrite(src: Path, dst: Path, record: str, laser_offset: float = 0.0, max_lines: int | None = None) -> int:
    """Write ``dst`` from ``src``; return the number of scans written."""
    if record not in ("robotlaser1", "rawlaser1"):
        raise ValueError(f"unknown record {record!r}: use robotlaser1 or rawlaser1")
    opener = _WRITERS.get(dst.suffix.lower(), open)
    scans = 0
    with open_text(src) as fi, opener(dst, "wt") as fo:
        for k, line in enumerate(fi):
            if max_lines is not None and k >= max_lines:
                break
            tokens = line.split()
            if tokens[:1] == ["FLASER"]:
                fo.writelines(rewrite_line(tokens, record, laser_offset))
                scans += 1
            elif not (tokens[:1] == ["ODOM"] and record == "rawlaser1"):
                fo.write(line)
    return scans


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("src", type=Path)
    parser.add_argument("dst", type=Path)
    parser.add_argument("--record", choices=["robotlaser1", "rawlaser1"], required=True)
    parser.add_argument("--laser-offset", type=float, default=0.0, help="ROBOTLASER1: laser ahead of the robot [m]")
    parser.add_argument("--max-lines", type=int, default=None, help="Stop after N lines of SRC.")
    args = parser.parse_args(argv)
    n = rewrite(args.src, args.dst, args.record, args.laser_offset, args.max_lines)
    print(f"{n} scans written as {args.record.upper()} to {args.dst}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
