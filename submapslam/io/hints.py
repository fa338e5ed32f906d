"""Manual loop hints: "a human pushes a button at a known landmark".

A hint file has one pair per line, ``a b``: two scan indices (written as integers, ``12 873``)
or two scan timestamps [s] (written with a decimal point, ``1000.5 1088.2``) taken at the same
place. ``#`` starts a comment.
"""

from __future__ import annotations

import math
from pathlib import Path

from ..errors import InputError
from ..scan import LoopHint

__all__ = ["LoopHint", "read_hint_file"]


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
        pairs.append(LoopHint(a, b, by_index=integer[0]))
    return pairs
