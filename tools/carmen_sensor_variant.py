"""Rewrite a CARMEN log as another scanner would have recorded it: fewer beams or a shorter range.

Usage:
    python tools/carmen_sensor_variant.py SRC DST (--every-beam K | --max-range R) [--max-lines N]

Every FLASER line of SRC (plain, ``.gz``, ``.bz2`` or ``.xz``) is written to DST (must not exist)
with ``--every-beam K``: every K-th range kept (the beams K times farther apart over the same
180 degrees, where the reader's beam layout for the new count keeps each kept beam's angle;
refused otherwise), or ``--max-range R``: every range beyond R [m] set to R, which a scanner of
that reach reports for a beam that returned nothing (the reader takes the log's most frequent
largest range as its maximum: no returns, free space, no walls). Odometry, poses and timestamps
are unchanged, so a run on DST scores against the corrected log with the original log as the
scans' key (``submapslam eval OUT/poses_tum.txt CORRECTED --raw-log SRC``; BENCHMARKS.md). Other
laser records (ROBOTLASER1, RAWLASER*) are refused: their layouts differ.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from submapslam.io.carmen import RECORD_PRIORITY, beam_angles  # noqa: E402
from submapslam.io.compression import open_text  # noqa: E402


def variant_line(tokens: list[str], every_beam: int | None, max_range: float | None) -> str:
    """One FLASER line's ``tokens`` as the other scanner records it (with its newline)."""
    n = int(tokens[1])
    ranges, rest = tokens[2:2 + n], tokens[2 + n:]
    if every_beam is not None:
        kept = ranges[::every_beam]
        if not np.array_equal(beam_angles(len(kept)), beam_angles(n)[::every_beam]):
            raise ValueError(f"{n} beams every {every_beam}: {len(kept)} beams would not keep their angles")
        ranges = kept
    if max_range is not None:
        reach = f"{max_range:g}"
        ranges = [reach if float(r) > max_range else r for r in ranges]
    return " ".join(["FLASER", str(len(ranges)), *ranges, *rest]) + "\n"


def write_variant(src: Path, dst: Path, every_beam: int | None = None, max_range: float | None = None,
                  max_lines: int | None = None) -> int:
    """Write ``dst`` from ``src`` (see the module docstring); return the number of scans written."""
    if (every_beam is None) == (max_range is None):
        raise ValueError("give one of --every-beam and --max-range")
    if every_beam is not None and every_beam < 2:
        raise ValueError(f"--every-beam must be at least 2, not {every_beam}")
    if max_range is not None and max_range <= 0:
        raise ValueError(f"--max-range must be positive, not {max_range}")
    if dst.exists():
        raise FileExistsError(f"{dst} exists: not overwritten")
    scans = 0
    try:
        with open_text(src) as lines, open(dst, "x") as out:
            for k, line in enumerate(lines):
                if max_lines is not None and k >= max_lines:
                    break
                tokens = line.split()
                record = tokens[0] if tokens else ""
                if record == "FLASER":
                    line = variant_line(tokens, every_beam, max_range)
                    scans += 1
                elif record in RECORD_PRIORITY:
                    raise ValueError(f"line {k + 1}: {record} records are not rewritten (FLASER only)")
                out.write(line)
    except ValueError:
        dst.unlink(missing_ok=True)  # the half-written variant this call made is not left behind
        raise
    return scans


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", type=Path)
    ap.add_argument("dst", type=Path)
    ap.add_argument("--every-beam", type=int, default=None, help="keep every K-th beam of each scan")
    ap.add_argument("--max-range", type=float, default=None, help="[m] ranges beyond this become this (no return)")
    ap.add_argument("--max-lines", type=int, default=None, help="stop after N lines of SRC")
    args = ap.parse_args(argv)
    try:
        n = write_variant(args.src, args.dst, args.every_beam, args.max_range, args.max_lines)
    except (OSError, ValueError) as exc:
        print(f"carmen_sensor_variant: {exc}", file=sys.stderr)
        return 1
    print(f"{args.dst}: {n} scans")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
