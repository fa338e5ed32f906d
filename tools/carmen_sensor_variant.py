"""Rewrite a CARMEN log as another scanner or robot would have recorded it: fewer beams, a shorter
range, noisier ranges, or wheels that measure distance and turn wrongly.

Usage:
    python tools/carmen_sensor_variant.py SRC DST [--every-beam K] [--max-range R] [--range-noise SIGMA]
        [--odometry-scale S] [--odometry-turn-scale K] [--seed N] [--max-lines N]

Every FLASER line of SRC (plain, ``.gz``, ``.bz2`` or ``.xz``) is written to DST (must not exist)
with ``--every-beam K``: every K-th range kept (the beams K times farther apart over the same
180 degrees, where the reader's beam layout for the new count keeps each kept beam's angle;
refused otherwise), or ``--max-range R``: every range beyond R [m] set to R, which a scanner of
that reach reports for a beam that returned nothing (the reader takes the log's most frequent
largest range as its maximum: no returns, free space, no walls), ``--range-noise SIGMA``: Gaussian
noise of SIGMA [m] added to every range that returned (a cheaper scanner; ``--seed``), and
``--odometry-scale S`` / ``--odometry-turn-scale K``: every step of the recorded poses (FLASER's laser
and robot poses, ODOM's pose, each its own chain) re-integrated with its travel times S and its turn
times K (worn wheels, a wheel base calibrated wrong). Timestamps are unchanged, so a run on DST
scores against the corrected log with the original log as the scans' key
(``submapslam eval OUT/poses_tum.txt CORRECTED --raw-log SRC``; BENCHMARKS.md). Other laser
records (ROBOTLASER1, RAWLASER*) are refused: their layouts differ.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from submapslam.geometry import matrix_to_se2, relative, se2_to_matrix  # noqa: E402
from submapslam.io.carmen import RECORD_PRIORITY, beam_angles  # noqa: E402
from submapslam.io.compression import open_text  # noqa: E402


class DistortedChain:
    """Recorded SE(2) poses re-integrated step by step with the travel scaled by ``scale`` and the turn
    by ``turn_scale`` (each step taken in the previous pose's frame); the first pose is kept."""

    def __init__(self, scale: float, turn_scale: float) -> None:
        self.scale, self.turn_scale = scale, turn_scale
        self._last: np.ndarray | None = None  # (4, 4) last recorded pose
        self._out: np.ndarray | None = None  # (4, 4) its distorted pose

    def __call__(self, pose: np.ndarray) -> np.ndarray:
        """The distorted ``(x, y, theta)`` [m, rad] of the next recorded ``pose``."""
        T = se2_to_matrix(*pose)
        if self._last is None:
            out = T
        else:
            dx, dy, turn = matrix_to_se2(relative(self._last, T))  # the step in the last pose's frame
            out = self._out @ se2_to_matrix(self.scale * dx, self.scale * dy, self.turn_scale * turn)
        self._last, self._out = T, out
        return matrix_to_se2(out)


def _pose_tokens(tokens: list[str], chain: DistortedChain | None) -> list[str]:
    """``tokens`` ``x y theta`` rewritten along ``chain`` (unchanged without one)."""
    if chain is None:
        return tokens
    return [f"{v:.6f}" for v in chain(np.array([float(t) for t in tokens]))]


def variant_line(tokens: list[str], every_beam: int | None, max_range: float | None,
                 range_noise: float | None = None, rng: np.random.Generator | None = None,
                 chains: tuple[DistortedChain, DistortedChain] | None = None) -> str:
    """One FLASER line's ``tokens`` as the other scanner (and robot) records it (with its newline);
    ``chains``: the laser pose's and the robot pose's :class:`DistortedChain`."""
    n = int(tokens[1])
    ranges, rest = tokens[2:2 + n], tokens[2 + n:]
    if chains is not None:
        rest = [*_pose_tokens(rest[0:3], chains[0]), *_pose_tokens(rest[3:6], chains[1]), *rest[6:]]
    if range_noise is not None:
        values = np.array([float(r) for r in ranges])
        top = values.max()
        returned = values > 0.0
        if np.count_nonzero(values == top) > 1:
            returned &= values < top  # the scanner's no-return reading (its repeated maximum) stays as it is
        values[returned] = np.maximum(values[returned] + rng.normal(0.0, range_noise, int(returned.sum())), 0.001)
        ranges = [f"{v:.3f}" if ok else r for v, ok, r in zip(values, returned, ranges)]
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
                  max_lines: int | None = None, range_noise: float | None = None, odometry_scale: float = 1.0,
                  odometry_turn_scale: float = 1.0, seed: int = 0) -> int:
    """Write ``dst`` from ``src`` (see the module docstring); return the number of scans written."""
    if every_beam is None and max_range is None and range_noise is None and (odometry_scale, odometry_turn_scale) == (1, 1):
        raise ValueError("nothing to change: give --every-beam, --max-range, --range-noise or an odometry scale")
    if range_noise is not None and range_noise <= 0:
        raise ValueError(f"--range-noise must be positive, not {range_noise}")
    if odometry_scale <= 0 or odometry_turn_scale <= 0:
        raise ValueError(f"odometry scales must be positive, not {odometry_scale} / {odometry_turn_scale}")
    if every_beam is not None and every_beam < 2:
        raise ValueError(f"--every-beam must be at least 2, not {every_beam}")
    if max_range is not None and max_range <= 0:
        raise ValueError(f"--max-range must be positive, not {max_range}")
    if dst.exists():
        raise FileExistsError(f"{dst} exists: not overwritten")
    scans = 0
    rng = np.random.default_rng(seed)
    distort = (odometry_scale, odometry_turn_scale) != (1, 1)
    chains = (DistortedChain(odometry_scale, odometry_turn_scale),
              DistortedChain(odometry_scale, odometry_turn_scale)) if distort else None
    odom_chain = DistortedChain(odometry_scale, odometry_turn_scale) if distort else None
    try:
        with open_text(src) as lines, open(dst, "x") as out:
            for k, line in enumerate(lines):
                if max_lines is not None and k >= max_lines:
                    break
                tokens = line.split()
                record = tokens[0] if tokens else ""
                if record == "FLASER":
                    line = variant_line(tokens, every_beam, max_range, range_noise, rng, chains)
                    scans += 1
                elif record == "ODOM" and odom_chain is not None:
                    line = " ".join(["ODOM", *_pose_tokens(tokens[1:4], odom_chain), *tokens[4:]]) + "\n"
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
    ap.add_argument("--range-noise", type=float, default=None, help="[m] Gaussian noise on every returned range")
    ap.add_argument("--odometry-scale", type=float, default=1.0, help="every recorded step's travel times this")
    ap.add_argument("--odometry-turn-scale", type=float, default=1.0, help="every recorded step's turn times this")
    ap.add_argument("--seed", type=int, default=0, help="seed of --range-noise")
    ap.add_argument("--max-lines", type=int, default=None, help="stop after N lines of SRC")
    args = ap.parse_args(argv)
    try:
        n = write_variant(args.src, args.dst, args.every_beam, args.max_range, args.max_lines, args.range_noise,
                          args.odometry_scale, args.odometry_turn_scale, args.seed)
    except (OSError, ValueError) as exc:
        print(f"carmen_sensor_variant: {exc}", file=sys.stderr)
        return 1
    print(f"{args.dst}: {n} scans")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
