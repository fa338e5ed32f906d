"""Cut a cloud-folder log: every ``--step``-th scan from scan ``--start`` on, without the scans of
each ``--drop A:B`` (scans A to B-1 of SRC: frames lost), as a new log folder.

Usage:
    python tools/cut_cloud_log.py SRC DST [--start N] [--step K] [--drop A:B ...]

SRC is a cloud-folder log with its reference: a real one (``scans/*.pcd|ply|bin`` with
``scans/times.txt`` and ``reference_poses_kitti.txt``, line k for scan k: the Livox sequences of
``../shared/data/lidar3d``) or a synthetic one (``scans/`` with ``times.txt``,
``groundtruth_tum.txt`` and ``meta.yaml``). DST gets symbolic links to the kept scans, renumbered
from 0, their times, and the reference cut the same way (a synthetic log's time-stamped ground
truth and ``meta.yaml`` are linked whole). ``tools/bench_city.py DST`` then runs it against that
reference. A cut is the same recording with twice or three times the motion between scans, a
start facing other walls, or seconds of scans lost: how the odometry copes off the data it was
tuned on (BENCHMARKS.md, "Narrow-field odometry off its tuning", stop 69). A cut carries no wheel
odometry (``odometry_tum.txt`` is not linked): the scans alone, as the real sequences.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from submapslam.io.cloud_folder import SCAN_SUFFIXES


def cut(src: Path, dst: Path, start: int, step: int, drops: tuple[range, ...] = ()) -> int:
    """Write the cut of ``src`` into ``dst`` (must not exist); return the number of scans kept.
    ``drops``: ranges of ``src``'s scan indices left out."""
    folder = src / "scans"
    scans = sorted(p for p in folder.iterdir() if p.suffix.lower() in SCAN_SUFFIXES and p.is_file()) \
        if folder.is_dir() else []
    times_file = next((p for p in (folder / "times.txt", src / "times.txt") if p.exists()), None)
    if not scans or times_file is None:
        raise SystemExit(f"cut_cloud_log: {src}: no scans/ folder of {'/'.join(SCAN_SUFFIXES)} scans with a times.txt")
    keep = [k for k in range(start, len(scans), step) if not any(k in lost for lost in drops)]
    if not keep:
        raise SystemExit(f"cut_cloud_log: {src} has {len(scans)} scans: none from scan {start} on")
    reference = src / "reference_poses_kitti.txt"
    lines = reference.read_text().splitlines() if reference.exists() else None
    if lines is not None and len(lines) < len(scans):
        raise SystemExit(f"cut_cloud_log: {reference}: {len(lines)} poses for {len(scans)} scans")
    dst.mkdir(parents=True)
    (dst / "scans").mkdir()
    for n, k in enumerate(keep):
        (dst / "scans" / f"{n:06d}{scans[k].suffix}").symlink_to(scans[k].resolve())
    times = np.loadtxt(times_file, ndmin=1, usecols=0)
    np.savetxt(dst / times_file.relative_to(src), times[keep], fmt="%.9f")
    if lines is not None:
        (dst / reference.name).write_text("\n".join(lines[k] for k in keep) + "\n")
    for name in ("groundtruth_tum.txt", "meta.yaml"):  # time-stamped: the cut's times pick from it
        if (src / name).exists():
            os.symlink((src / name).resolve(), dst / name)
    return len(keep)


def parse_drop(text: str) -> range:
    """``"A:B"`` -> ``range(A, B)`` (0 <= A < B), or one line naming the problem."""
    a, sep, b = text.partition(":")
    if not sep or not a.isdigit() or not b.isdigit() or int(a) >= int(b):
        raise SystemExit(f"cut_cloud_log: --drop {text!r}: give A:B with 0 <= A < B (scans A to B-1 left out)")
    return range(int(a), int(b))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("src", type=Path)
    ap.add_argument("dst", type=Path)
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--step", type=int, default=1)
    ap.add_argument("--drop", action="append", default=[], metavar="A:B",
                    help="leave out scans A to B-1 of SRC (repeatable)")
    args = ap.parse_args(argv)
    if args.start < 0 or args.step < 1:
        raise SystemExit("cut_cloud_log: --start must be >= 0 and --step >= 1")
    drops = tuple(parse_drop(text) for text in args.drop)
    if args.dst.exists():
        raise SystemExit(f"cut_cloud_log: {args.dst} exists: give a new folder")
    print(f"{args.dst}: {cut(args.src, args.dst, args.start, args.step, drops)} scans")
    return 0


if __name__ == "__main__":
    sys.exit(main())
