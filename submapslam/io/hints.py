"""Manual loop hints: "a human pushes a button at a known landmark".

A hint file has one pair per line, ``a b``: two scan indices (written as integers, ``12 873``)
or two scan timestamps [s] (written with a decimal point, ``1000.5 1088.2``) taken at the same
place. ``#`` starts a comment.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..scan import LoopHint

__all__ = ["LoopHint", "hint_problems", "read_hint_file"]


def read_hint_file(path: str | Path) -> list[LoopHint]:
    """Read a hints file; integers are scan indices, decimals are timestamps."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such hints file")
    pairs = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        body = line.split("#", 1)[0].split()
        if not body:
            continue
        if len(body) != 2:
            raise InputError(path, f"expected two values (scan indices or timestamps), got {len(body)}", lineno)
        try:
            a, b = float(body[0]), float(body[1])
        except ValueError:
            raise InputError(path, f"not a number: {line.strip()[:40]!r}", lineno) from None
        if not (math.isfinite(a) and math.isfinite(b)) or a < 0 or b < 0:
            raise InputError(path, "hint values must be finite and non-negative", lineno)
        integer = [tok.isdigit() for tok in body]
        if integer[0] != integer[1]:
            raise InputError(path, "mixes a scan index with a timestamp (write both as integers or both with a decimal point)", lineno)
        pairs.append(LoopHint(a, b, by_index=integer[0], line=lineno))
    return pairs


def hint_problems(hints: list[LoopHint], timestamps: np.ndarray,
                  submap_scan_indices: list[list[int]] | None = None) -> list[str]:
    """One message per hint the log cannot use; an empty list when every hint is usable.

    Args:
        hints: the hints as read (:func:`read_hint_file`).
        timestamps: ``(N,)`` the scans' timestamps [s], in log order (the run's scans).
        submap_scan_indices: per submap, its scans; a hint whose two scans fall in one submap
            is not a loop (None: not checked).

    Unusable: a scan index beyond the scans read, a timestamp outside the log or far from any
    scan (more than 5 scan intervals, at least 1 s), a scan paired with itself.
    """
    stamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    n = len(stamps)
    interval = float(np.median(np.diff(stamps))) if n > 1 else 0.0
    tolerance = max(5.0 * abs(interval), 1.0)
    submap_of = {}
    for k, scans in enumerate(submap_scan_indices or []):
        submap_of.update({i: k for i in scans})
    problems = []
    for hint in hints:
        where = f"hint{'' if hint.line is None else f' on line {hint.line}'} ({_value(hint.a, hint)} {_value(hint.b, hint)})"
        if hint.a == hint.b:
            problems.append(f"{where}: pairs a scan with itself")
            continue
        scans, why = [], None
        for value in (hint.a, hint.b):
            if hint.by_index:
                if value >= n:
                    why = f"scan {int(value)} is beyond the log's {n} scans (indices 0..{n - 1})"
                    break
                scans.append(int(value))
            else:
                if n == 0:
                    why = "the log has no scans"
                    break
                k = int(np.argmin(np.abs(stamps - value)))
                if abs(stamps[k] - value) > tolerance:
                    outside = value < stamps[0] or value > stamps[-1]
                    why = (f"timestamp {value:.3f} is outside the log ({stamps[0]:.3f}..{stamps[-1]:.3f})" if outside
                           else f"timestamp {value:.3f} is {abs(stamps[k] - value):.1f} s from the nearest scan")
                    break
                scans.append(k)
        if why is None and scans[0] == scans[1]:
            why = f"both timestamps are nearest to scan {scans[0]}: pairs a scan with itself"
        if why is None and scans[0] in submap_of and submap_of[scans[0]] == submap_of.get(scans[1]):
            why = (f"scans {scans[0]} and {scans[1]} are in the same submap ({submap_of[scans[0]]}): "
                   "not a loop; a hint joins scans of different submaps")
        if why is not None:
            problems.append(f"{where}: {why}")
    return problems


def _value(v: float, hint: LoopHint) -> str:
    return str(int(v)) if hint.by_index else f"{v:.3f}"
