"""A planar run's graph edges against a reference trajectory: are their informations honest?

Usage:
    python tools/edges_vs_reference.py RUN RAW_LOG CORRECTED_LOG [--max-gap 2] [--json FILE]

RUN is a ``submapslam run`` output folder (``graph.g2o``, ``submaps.csv``, ``odometry_tum.txt``)
of the CARMEN log RAW_LOG; CORRECTED_LOG its corrected log (scans matched by identical readings,
:func:`submapslam.io.trajectory.carmen_reference_trajectory`). Each edge ``i -> j`` (odometry
between consecutive anchors, loops otherwise) is compared with the reference's relative pose
between the two anchors' scans: an anchor's reference pose is the nearest corrected pose composed
with the run's own odometry over the few scans between them (at most ``--max-gap``; edges with an
anchor farther from any corrected pose are skipped). The ``(x, y, yaw)`` error is whitened by the
edge's own information: a 3-DOF chi-square, ideal mean 3, median 2.37, 5 % above 7.81. Printed
per kind: count, mean and median chi2, share above 7.81, median error and median sigma. The
corrected logs carry their own errors, so the figures bound the honesty of the edges from above.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CHI2_95_3DOF = 7.81
PLANAR = [3, 4, 2]  # GTSAM order (rx, ry, rz, tx, ty, tz): x, y, yaw


def edge_errors(run: Path, reference, max_gap: int = 2) -> dict[str, list[dict]]:
    """Per edge kind (``odometry``, ``loop``) the edges of ``run/graph.g2o`` near ``reference``
    (a :class:`~submapslam.io.trajectory.Trajectory`): ``i``, ``j``, ``chi2``, ``error_m``,
    ``error_deg``, ``sigma_m``, ``sigma_deg``."""
    from submapslam.evaluation.metrics import associate
    from submapslam.geometry import inverse
    from submapslam.io.g2o import read_g2o_edges
    from submapslam.io.trajectory import read_tum

    odometry = read_tum(run / "odometry_tum.txt")
    scans, rows = associate(odometry, reference, 0.02)
    with open(run / "submaps.csv", newline="") as f:
        first_scan = [int(r["first_scan"]) for r in csv.DictReader(f)]

    def reference_pose(scan: int) -> tuple[np.ndarray, int]:
        k = int(np.argmin(np.abs(scans - scan)))
        near = int(scans[k])
        return reference.poses[rows[k]] @ inverse(odometry.poses[near]) @ odometry.poses[scan], abs(near - scan)

    out: dict[str, list[dict]] = {"odometry": [], "loop": []}
    _, edges = read_g2o_edges(run / "graph.g2o")
    for i, j, T_i_j, info in edges:
        (A, gap_a), (B, gap_b) = reference_pose(first_scan[i]), reference_pose(first_scan[j])
        if max(gap_a, gap_b) > max_gap:
            continue
        E = inverse(inverse(A) @ B) @ T_i_j
        e = np.array([E[0, 3], E[1, 3], np.arctan2(E[1, 0], E[0, 0])])
        info3 = info[np.ix_(PLANAR, PLANAR)]
        sigma = np.sqrt(np.diag(np.linalg.inv(info3)))
        out["odometry" if j == i + 1 else "loop"].append({
            "i": i, "j": j, "chi2": float(e @ info3 @ e), "error_m": float(np.hypot(e[0], e[1])),
            "error_deg": float(np.degrees(abs(e[2]))), "sigma_m": float(sigma[0]),
            "sigma_deg": float(np.degrees(sigma[2]))})
    return out


def summarize(edges: list[dict]) -> dict:
    """Count, mean / median chi2, share above the 95 % bound, median errors and sigmas."""
    if not edges:
        return {"edges": 0}
    chi2 = np.array([e["chi2"] for e in edges])
    med = {k: float(np.median([e[k] for e in edges])) for k in ("error_m", "error_deg", "sigma_m", "sigma_deg")}
    return {"edges": len(edges), "chi2_mean": float(chi2.mean()), "chi2_median": float(np.median(chi2)),
            "share_above_95": float(np.mean(chi2 > CHI2_95_3DOF)), **{f"median_{k}": v for k, v in med.items()}}


def main(argv: list[str] | None = None) -> int:
    from submapslam.io.trajectory import carmen_reference_trajectory

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("raw_log", type=Path)
    ap.add_argument("corrected_log", type=Path)
    ap.add_argument("--max-gap", type=int, default=2, help="scans between an anchor and its corrected pose")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    from submapslam.errors import SubmapSlamError

    try:
        reference = carmen_reference_trajectory(args.corrected_log, args.raw_log)
        figures = {kind: summarize(rows) for kind, rows in edge_errors(args.run, reference, args.max_gap).items()}
    except (OSError, SubmapSlamError, KeyError, ValueError) as exc:  # a missing or foreign file: one line
        print(f"edges_vs_reference: {args.run}: {exc}", file=sys.stderr)
        return 2
    print("| edges | count | mean chi2 | median chi2 | share > 7.81 | median error | median sigma |")
    print("|---|---|---|---|---|---|---|")
    for kind, f in figures.items():
        if f["edges"]:
            print(f"| {kind} | {f['edges']} | {f['chi2_mean']:.2f} | {f['chi2_median']:.2f} | {f['share_above_95']:.2f} "
                  f"| {f['median_error_m']:.3f} m / {f['median_error_deg']:.2f} deg "
                  f"| {f['median_sigma_m']:.3f} m / {f['median_sigma_deg']:.2f} deg |")
    if args.json:
        args.json.write_text(json.dumps(figures, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
