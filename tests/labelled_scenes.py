"""A tiny labelled 3D log shared by the mover-map tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from datasets_synth.writer import write_labels, write_ply_xyzt
from submapslam.geometry import se2_array_to_matrices
from submapslam.io.trajectory import Trajectory, write_tum


def write_wall_and_person_log(log: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Write to ``log`` two 3D scans 1 m apart along x (PLY, SemanticKITTI labels, TUM ground
    truth): a static wall seen twice (label 50), a person seen in the first only (254). Returns
    ``(T (2, 4, 4) world poses, wall (50, 3), person (10, 3))`` in metres, world frame."""
    (log / "labels").mkdir(parents=True)
    (log / "scans").mkdir()
    wall = np.column_stack([np.full(50, 5.0), np.linspace(-2.45, 2.45, 50), np.full(50, 0.5)])
    person = np.column_stack([np.full(10, 2.0), np.full(10, 0.05), np.linspace(0.05, 0.95, 10)])
    T = se2_array_to_matrices(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    for k, pts in enumerate([np.vstack([wall, person]), wall]):
        local = pts - T[k][:3, 3]
        write_ply_xyzt(log / "scans" / f"{k:06d}.ply", local, np.zeros(len(local)))
        write_labels(log / "labels" / f"{k:06d}.label", np.r_[np.full(50, 50), np.full(len(pts) - 50, 254)])
    write_tum(log / "groundtruth_tum.txt", Trajectory(np.array([0.0, 0.1]), T))
    return T, wall, person
