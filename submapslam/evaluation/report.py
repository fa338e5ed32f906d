"""Comparison reports: several trajectories against one reference, as a table and plots.

The only module (with the EKF plot) that imports matplotlib, lazily and with the Agg backend.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import SubmapSlamError
from ..trajectory import Trajectory
from .metrics import Alignment, AlignMode, associate, ate, kitti_segment_error, rpe
from .metrics import align as align_fn


@dataclass
class ComparisonResult:
    """Figures per estimate name and the files written."""

    rows: dict[str, dict]
    markdown: str
    files: dict[str, Path]


def compare_trajectories(reference: Trajectory, estimates: dict[str, Trajectory], out_dir: str | Path,
                         align: AlignMode = Alignment.SE3, reference_name: str = "reference") -> ComparisonResult:
    """Write ``report.md``, ``report.json``, ``trajectories.png``, ``ate.png`` and ``report.html``
    (one self-contained page: sortable table, every estimate side by side and overlaid) into ``out_dir``.

    ``align`` is an :class:`~submapslam.evaluation.metrics.Alignment` (or its string), checked
    before anything is computed or written.
    """
    align = Alignment(align)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows: dict[str, dict] = {}
    aligned: dict[str, np.ndarray] = {}
    errors: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, est in estimates.items():
        a = ate(est, reference, align=align)
        p = rpe(est, reference)
        try:
            seg = kitti_segment_error(est, reference)
        except SubmapSlamError:  # no segment fits (the association already succeeded in ate): empty column
            seg = {"trans_percent": float("nan"), "rot_deg_per_m": float("nan")}
        rows[name] = {"ate_rmse": a["rmse"], "ate_mean": a["mean"], "ate_max": a["max"], "rpe_trans_rmse": p["rmse"],
                      "rpe_rot_rmse_deg": p["rotation_rmse"], "segment_trans_percent": seg["trans_percent"],
                      "segment_rot_deg_per_m": seg["rot_deg_per_m"], "poses": a["n"]}
        i_e, i_r = associate(est, reference)
        T, s = align_fn(est.subset(i_e), reference.subset(i_r), align)
        P = s * est.positions @ T[:3, :3].T + T[:3, 3]
        aligned[name] = P
        errors[name] = (reference.timestamps[i_r] - reference.timestamps[0], a["errors"])
    header = "| trajectory | ATE RMSE [m] | ATE mean [m] | ATE max [m] | RPE [m/frame] | RPE [deg/frame] | segment [%] | segment [deg/m] | poses |"
    lines = [header, "|" + "---|" * 9]
    for name, r in rows.items():
        lines.append(f"| {name} | {r['ate_rmse']:.3f} | {r['ate_mean']:.3f} | {r['ate_max']:.3f} | {r['rpe_trans_rmse']:.4f} | "
                     f"{r['rpe_rot_rmse_deg']:.3f} | {r['segment_trans_percent']:.2f} | {r['segment_rot_deg_per_m']:.4f} | {r['poses']} |")
    markdown = "\n".join(lines)
    files = {"report.md": out / "report.md", "report.json": out / "report.json",
             "trajectories.png": out / "trajectories.png", "ate.png": out / "ate.png"}
    files["report.md"].write_text(f"# Trajectory comparison (alignment {align})\n\n{markdown}\n")
    files["report.json"].write_text(json.dumps(rows, indent=2) + "\n")
    fig, ax = plt.subplots(figsize=(8, 8))
    ax.plot(reference.positions[:, 0], reference.positions[:, 1], "k-", lw=1.2, label="reference")
    for name, P in aligned.items():
        ax.plot(P[:, 0], P[:, 1], lw=0.8, label=f"{name} (ATE {rows[name]['ate_rmse']:.3f} m)")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="best", fontsize=8)
    fig.savefig(files["trajectories.png"], dpi=120, bbox_inches="tight")
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(9, 4))
    for name, (t, e) in errors.items():
        ax.plot(t, e, lw=0.8, label=name)
    ax.set_xlabel("time since start [s]")
    ax.set_ylabel("position error [m]")
    ax.legend(fontsize=8)
    fig.savefig(files["ate.png"], dpi=120, bbox_inches="tight")
    plt.close(fig)
    from .html_report import build_comparison_report

    files["report.html"] = out / "report.html"
    files["report.html"].write_text(build_comparison_report(reference, estimates, rows, align, reference_name),
                                     encoding="utf-8")
    return ComparisonResult(rows, markdown, files)
