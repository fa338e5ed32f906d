"""Output of ``clean``: the static and the removed points as PLY, and a summary."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .ply import write_ply

CLEAN_FILES = ("map_static.ply", "map_dynamic.ply", "summary.json")


def write_clean_results(out_dir: str | Path, static_points: np.ndarray, dynamic_points: np.ndarray,
                        summary: dict) -> dict[str, Path]:
    """Write ``map_static.ply``, ``map_dynamic.ply`` (float32, world frame) and ``summary.json``."""
    out = Path(out_dir)
    paths = {name: out / name for name in CLEAN_FILES}
    write_ply(paths["map_static.ply"], np.asarray(static_points, dtype=np.float32))
    write_ply(paths["map_dynamic.ply"], np.asarray(dynamic_points, dtype=np.float32))
    paths["summary.json"].write_text(json.dumps(summary, indent=2) + "\n")
    return paths
