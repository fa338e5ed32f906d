"""Occupancy grids as PGM + YAML (the ROS ``map_server`` format) and PNG."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import numpy as np

FREE, UNKNOWN, OCCUPIED = 254, 205, 0


def grid_image(prob: np.ndarray, occupied_thresh: float = 0.65, free_thresh: float = 0.196) -> np.ndarray:
    """Probability grid ``(rows, cols)`` (row 0 = lowest y) -> uint8 image (row 0 = top)."""
    img = np.full(prob.shape, UNKNOWN, dtype=np.uint8)
    img[prob > occupied_thresh] = OCCUPIED
    img[prob < free_thresh] = FREE
    return img[::-1]


class ProbabilityBands(Protocol):
    """A grid too large to hold its probabilities at once (:class:`~submapslam.mapping.tiled_grid.TiledLogOdds`)."""

    shape: tuple[int, int]

    def probability_bands(self) -> Iterator[tuple[int, np.ndarray]]:
        """``(first row, (rows, cols) probabilities)`` bands, highest rows first."""


def write_pgm_yaml(stem: str | Path, prob: np.ndarray | ProbabilityBands, origin_xy: np.ndarray,
                   resolution: float) -> tuple[Path, Path]:
    """Write ``stem.pgm`` (binary P5) and ``stem.yaml``; return both paths. ``prob``: the
    ``(rows, cols)`` probability grid (row 0 = lowest y), or a grid that hands it out in bands of
    rows (written one band at a time: no image of the whole grid in memory)."""
    stem = Path(stem)
    pgm = stem.with_suffix(".pgm")
    with open(pgm, "wb") as fh:
        fh.write(f"P5\n{prob.shape[1]} {prob.shape[0]}\n255\n".encode())
        if isinstance(prob, np.ndarray):
            fh.write(grid_image(prob).tobytes())
        else:
            for _, band in prob.probability_bands():
                fh.write(grid_image(band).tobytes())
    yaml_path = stem.with_suffix(".yaml")
    yaml_path.write_text(
        f"image: {pgm.name}\nresolution: {resolution}\n"
        f"origin: [{origin_xy[0]:.6f}, {origin_xy[1]:.6f}, 0.0]\n"
        "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    return pgm, yaml_path


def read_pgm(path: str | Path) -> np.ndarray:
    """Read a binary P5 PGM written by :func:`write_pgm_yaml` -> uint8 ``(rows, cols)``."""
    from ..errors import InputError

    data = Path(path).read_bytes()
    parts = data.split(maxsplit=4)
    if len(parts) < 5 or parts[0] != b"P5":
        raise InputError(path, "not a binary (P5) PGM file")
    w, h = int(parts[1]), int(parts[2])
    pixels = np.frombuffer(parts[4][: w * h], dtype=np.uint8)
    if pixels.size != w * h:
        raise InputError(path, f"PGM truncated: {pixels.size} of {w * h} pixels")
    return pixels.reshape(h, w)
