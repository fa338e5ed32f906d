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


#: the test files that take longest (``make test`` prints the slowest tests), longest first. Under
#: ``pytest -n auto --dist loadfile`` each file goes whole to one worker in collection order; when
#: a long file comes last one core idles while it ends, so these are collected first
LONGEST_FILES = ("test_real2d_logs.py", "test_two_lap_3d.py", "test_city_scale.py", "test_real2d_numeric.py",
                 "test_ray_cluster.py", "test_batch.py", "test_resume.py", "test_real3d_logs.py")


def pytest_collection_modifyitems(config, items) -> None:
    """The :data:`LONGEST_FILES` first (longest first); every other test keeps its place."""
    rank = {name: k for k, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


def load_tool(name: str):
    """The module of the script ``tools/<name>.py`` (the tools are scripts, not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, REPO / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
