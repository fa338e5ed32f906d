"""Write the stochastic map's results: landmarks.csv, poses_tum.txt, summary.json.

The map plot (``landmarks.png``) is drawn by
:func:`submapslam.evaluation.landmark_compare.plot_stochastic_map`.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

from ..ekf.runner import EkfRun
from ..geometry import se2_array_to_matrices
from ..trajectory import Trajectory
from .trajectory import write_tum


def write_landmarks_csv(path: Path, landmarks: list[dict]) -> None:
    """``id,x,y,var_xx,var_xy,var_yy,credibility`` per feature."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "x", "y", "var_xx", "var_xy", "var_yy", "credibility"])
        for lm in landmarks:
            w.writerow([lm["id"], *(f"{lm[k]:.6f}" for k in ("x", "y")), *(f"{lm[k]:.6g}" for k in ("var_xx", "var_xy", "var_yy")),
                        f"{lm['credibility']:.4f}"])


def write_ekf_results(out_dir: str | Path, run: EkfRun, summary: dict) -> dict[str, Path]:
    """``poses_tum.txt`` (the filter's robot poses), ``landmarks.csv`` and ``summary.json`` in
    ``out_dir`` (created); returns their paths by file name."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {k: out / k for k in ("poses_tum.txt", "landmarks.csv", "summary.json")}
    write_tum(paths["poses_tum.txt"], Trajectory(run.times, se2_array_to_matrices(run.poses)))
    write_landmarks_csv(paths["landmarks.csv"], run.filter.landmarks())
    paths["summary.json"].write_text(json.dumps(summary, indent=2) + "\n")
    return paths
