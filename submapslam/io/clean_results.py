"""Output of ``clean``: the static and the removed points as PLY, and a summary."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import SubmapSlamError
from .ply import write_ply

CLEAN_FILES = ("map_static.ply", "map_dynamic.ply", "summary.json")


def check_clean_folder(out_dir: str | Path) -> Path:
    """The output folder, created; an error when it already holds one of :data:`CLEAN_FILES`."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise SubmapSlamError(f"{out} is a file, not a folder")
    taken = [name for name in CLEAN_FILES if (out / name).exists()]
    if taken:
        raise SubmapSlamError(f"{out} already holds {', '.join(taken)}; not overwriting (choose another --out)")
    out.mkdir(parents=True, exist_ok=True)
    return out


def write_clean_results(out_dir: str | Path, static_points: np.ndarray, dynamic_points: np.ndarray,
                        summary: dict) -> dict[str, Path]:
    """Write ``map_static.ply``, ``map_dynamic.ply`` (float32, world frame) and ``summary.json``."""
    out = Path(out_dir)
    paths = {name: out / name for name in CLEAN_FILES}
    write_ply(paths["map_static.ply"], np.asarray(static_points, dtype=np.float32))
    write_ply(paths["map_dynamic.ply"], np.asarray(dynamic_points, dtype=np.float32))
    paths["summary.json"].write_text(json.dumps(summary, indent=2) + "\n")
    return paths
