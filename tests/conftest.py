"""Shared fixtures: paths to the read-only real data beside the repository."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# pytest-xdist's workers run with COLUMNS=80 in their environment, which rich takes as the width
# of every console; the CLI's output is tested as a script sees it through a pipe, without it
os.environ.pop("COLUMNS", None)
os.environ.pop("LINES", None)

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def shared_data(*parts: str) -> Path:
    """Path under ../shared/data; skip the test with a clear reason when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data not available: {path} (expected ../shared/data beside the repo)")
    return path
