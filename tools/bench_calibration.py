"""Are the covariances we output honest? Monte Carlo calibration of anchor (and scan) covariances.

Usage:
    python tools/bench_calibration.py [--world2d rectangle] [--seeds2d 0:20] [--laps 2]
        [--path3d 05] [--seeds3d 0:20] [--scans3d 200] [--ekf-runs 20] [--config FILE]
        [--only 2d 3d ekf] [--json FILE] [--workdir DIR]

For every noise seed (the seed also draws the world's layout): write the synthetic log
(``datasets_synth``: a 2D world, or a KITTI-path city with ``--terrain`` cut after ``--scans3d``
scans), run the pipeline, and compare every anchor with the ground truth. Both trajectories are
aligned by the first anchor (the graph holds it fixed): the error of anchor k is
``xi = Log((G_0^-1 G_k)^-1 (A_0^-1 A_k))`` in anchor k's own frame (right perturbation, GTSAM
order ``(rx, ry, rz, tx, ty, tz)``, translation taken as is), compared with the anchor's marginal
covariance (``SlamResult.submap_covariances``, same order and frame). Scans likewise against
their covariances (:func:`submapslam.uncertainty.scan_covariances`) when that module exists.

Reported, pooled over the seeds (anchor 0 left out, it is the reference):
- per axis the mean of ``(e/sigma)^2`` (ideal 1) and the share of ``(e/sigma)^2 <= 3.84`` (the
  95 % chi-square(1) bound; ideal 0.95);
- NEES of x-y (2 DOF) and of the full pose (3 DOF planar: x, y, yaw; 6 DOF in 3D) with the
  two-sided 95 % band of its mean over all samples (samples within one run are correlated, so
  the band is optimistic), and the share of samples inside the 95 % chi-square bound.
- the landmark world's EKF (``nees_study``, ``--ekf-runs`` runs): mean robot-pose NEES (3 DOF),
  share of steps whose Monte Carlo average lies in the 95 % band, first step out of it; and the
  landmarks' EKF covariances against the graph's marginals (symmetric KL, ellipse areas), both
  estimators' joint landmark NEES and last-pose NEES against their 95 % bands.

``--json`` keeps every sample (errors and covariances) for fitting a calibration.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

KITTI_GT = REPO.parent / "shared" / "data" / "trajectories" / "kitti_gt"
AXES = ("rx", "ry", "rz", "tx", "ty", "tz")  # GTSAM order
LABEL = {"rx": "roll", "ry": "pitch", "rz": "yaw", "tx": "x", "ty": "y", "tz": "z"}


def seed_range(text: str) -> list[int]:
    """``"0:20"`` -> 0..19; ``"3"`` -> [3]; ``"1,4,7"`` -> [1, 4, 7]."""
    if ":" in text:
        a, b = text.split(":")
        return list(range(int(a), int(b)))
    return [int(x) for x in text.split(",")]


def pose_error(T_gt: np.ndarray, T_est: np.ndarray) -> np.ndarray:
    """``(6,)`` error of ``T_est`` against ``T_gt`` (both ``(4, 4)``, relative to the reference):
    ``Log(T_gt^-1 T_est)`` in the pose's own frame, GTSAM order, translation as is."""
    from submapslam.geometry import inverse, so3_log

    E = inverse(T_gt) @ T_est
    return np.concatenate([so3_log(E[:3, :3]), E[:3, 3]])


def run_samples(log: Path, config: str | None) -> dict:
    """Run the pipeline on ``log`` and return ``{"anchors": (errors (K, 6), covs (K, 6, 6)), "scans": ...,
    "seconds": s, "planar": bool}`` against ``log/groundtruth_tum.txt``."""
    from submapslam.api import run_log
    from submapslam.geometry import inverse
    from submapslam.io.trajectory import read_tum

    t0 = time.perf_counter()
    res, _ = run_log(log, None, config=config)
    seconds = time.perf_counter() - t0
    gt = read_tum(log / "groundtruth_tum.txt").poses
    if len(gt) != res.n_scans:
        raise SystemExit(f"{log}: {len(gt)} ground-truth poses for {res.n_scans} scans")
    first = [idx[0] for idx in res.submap_scan_indices]
    G0, A0 = gt[first[0]], res.submap_poses[0]
    errs = np.array([pose_error(inverse(G0) @ gt[s], inverse(A0) @ res.submap_poses[k])
                     for k, s in enumerate(first)])[1:]
    out = {"anchors": (errs, np.asarray(res.submap_covariances)[1:]), "seconds": seconds, "planar": res.planar,
           "loops": int(res.loops_accepted), "n_anchors": len(first)}
    try:
        from submapslam.uncertainty import scan_covariances
    except ImportError:
        return out
    covs = scan_covariances(res)
    if covs is not None:
        serr = np.array([pose_error(inverse(G0) @ gt[s], inverse(A0) @ res.poses[s]) for s in range(res.n_scans)])
        out["scans"] = (serr[1:], covs[1:])
    return out


def summarise(errs: np.ndarray, covs: np.ndarray, planar: bool) -> dict:
    """Per-axis mean ``(e/sigma)^2`` and share within 3.84; x-y and full NEES with band and share."""
    from scipy.stats import chi2

    axes = [2, 3, 4] if planar else list(range(6))
    var = np.einsum("kii->ki", covs)
    z2 = errs**2 / np.maximum(var, 1e-300)
    out: dict = {"n": len(errs), "axes": {}}
    for a in axes:
        out["axes"][LABEL[AXES[a]]] = {"mean_z2": float(z2[:, a].mean()), "in95": float((z2[:, a] <= 3.841).mean())}
    for name, idx in (("xy", [3, 4]), ("full", axes)):
        d = len(idx)
        nees = np.array([e[idx] @ np.linalg.solve(c[np.ix_(idx, idx)], e[idx]) for e, c in zip(errs, covs)])
        n = len(nees)
        out[f"nees_{name}"] = {"dof": d, "mean": float(nees.mean()),
                               "band": [float(chi2.ppf(0.025, n * d) / n), float(chi2.ppf(0.975, n * d) / n)],
                               "in95": float((nees <= chi2.ppf(0.95, d)).mean())}
    return out


def table(title: str, s: dict) -> str:
    """One markdown row per sample kind."""
    axes = ", ".join(f"{k} {v['mean_z2']:.2f} ({v['in95']:.2f})" for k, v in s["axes"].items())
    xy, full = s["nees_xy"], s["nees_full"]
    return (f"| {title} | {s['n']} | {axes} | {xy['mean']:.2f} [{xy['band'][0]:.2f}, {xy['band'][1]:.2f}] ({xy['in95']:.2f}) "
            f"| {full['mean']:.2f} ({full['dof']} DOF) [{full['band'][0]:.2f}, {full['band'][1]:.2f}] ({full['in95']:.2f}) |")


def monte_carlo(kind: str, seeds: list[int], make_log, config: str | None, keep: dict) -> list[str]:
    """Run every seed, print a progress line each, return the markdown rows (anchors, scans)."""
    pooled: dict[str, list] = {}
    planar = True
    for seed in seeds:
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory(dir=keep.get("workdir")) as tmp:
            log = make_log(seed, Path(tmp) / "log")
            r = run_samples(log, config)
        planar = r["planar"]
        for what in ("anchors", "scans"):
            if what in r:
                pooled.setdefault(what, []).append(r[what])
        e, c = r["anchors"]
        z2 = (e**2 / np.einsum("kii->ki", c)).mean(axis=0)
        print(f"  {kind} seed {seed}: {r['n_anchors']} anchors, {r['loops']} loops, mean (e/sigma)^2 "
              + " ".join(f"{LABEL[AXES[a]]} {z2[a]:.2f}" for a in ([2, 3, 4] if planar else range(6)))
              + f", {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    rows = []
    for what, parts in pooled.items():
        errs = np.concatenate([p[0] for p in parts])
        covs = np.concatenate([p[1] for p in parts])
        keep.setdefault("samples", {})[f"{kind} {what}"] = {"errors": errs.tolist(), "covariances": covs.tolist()}
        s = summarise(errs, covs, planar)
        keep.setdefault("summary", {})[f"{kind} {what}"] = s
        rows.append(table(f"{kind}, {what} ({len(parts)} seeds)", s))
    return rows


def ekf_rows(runs: int, workdir: str | None) -> list[str]:
    """The landmark world's EKF, FEJ-EKF and smoother NEES over ``runs`` Monte Carlo runs."""
    from submapslam.cli.ekf import synthetic_nees_trials
    from submapslam.evaluation.landmark_compare import nees_study

    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        study = nees_study(synthetic_nees_trials(Path(tmp), runs=runs))
    lo, hi = study["band"]
    rows = [f"landmark world, {runs} runs, 2 laps: 95 % band of the {runs}-run average NEES (3 DOF) [{lo:.2f}, {hi:.2f}]",
            "", "| filter | mean NEES | share of steps in band | first step out (10-step mean) |", "|---|---|---|---|"]
    for name, key in (("EKF", "ekf"), ("FEJ-EKF", "ekf_fej"), ("graph (smoother)", "graph")):
        x = study[key]
        rows.append(f"| {name} | {x.mean():.2f} | {((x >= lo) & (x <= hi)).mean():.2f} | {study[key + '_left_band_at']} |")
    return rows + [""] + landmark_rows(runs, workdir)


def landmark_rows(runs: int, workdir: str | None) -> list[str]:
    """The same worlds' landmarks and last pose: the EKF against the graph's marginals, and both
    against the truth (:func:`~submapslam.evaluation.landmark_compare.landmark_consistency_study`)."""
    from submapslam.cli.ekf import synthetic_nees_trials
    from submapslam.evaluation.landmark_compare import landmark_consistency_study

    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        st = landmark_consistency_study(synthetic_nees_trials(Path(tmp), runs=runs))
    (la, lb), (fa, fb) = st["landmark_nees_per_dof_band_95"], st["final_nees_band_95"]
    ra, rb = st["landmark_area_ratio_range"]
    return [f"EKF vs graph marginals over {runs} runs: landmark symmetric KL max {st['landmark_sym_kl_max']:.4f}, "
            f"ellipse area ratio (EKF / graph) {ra:.3f}-{rb:.3f}; last pose symmetric KL max "
            f"{st['final_pose_sym_kl_max']:.4f}", "",
            f"| estimator | joint landmark NEES per DOF ({st['landmark_dof']} DOF) [95 % band] | last pose NEES "
            "mean (3 DOF) [95 % band] |", "|---|---|---|",
            *(f"| {name} | {st[key + '_landmark_nees_per_dof']:.3f} [{la:.3f}, {lb:.3f}] | "
              f"{st[key + '_final_nees_mean']:.2f} [{fa:.2f}, {fb:.2f}] |" for name, key in (("EKF", "ekf"),
                                                                                             ("graph", "graph")))]


def rescore(files: list[str], scale: list[float] | None) -> int:
    """Print the table of the samples in ``files`` (``--json`` output), their covariances scaled by
    ``scale`` (6 variance factors, GTSAM order; None: as run), and the per-axis scale that would make
    each run's mean (e/sigma)^2 one (the fit: mean (e/sigma)^2 per axis of the unscaled samples)."""
    from submapslam.uncertainty import calibrate

    rows = []
    for f in files:
        data = json.loads(Path(f).read_text())
        for name, smp in data["samples"].items():
            errs, covs = np.array(smp["errors"]), np.array(smp["covariances"])
            planar = bool(np.all(np.einsum("kii->ki", covs)[:, [0, 1, 5]] < 1e-4))  # pinned (sigma 1e-4 per edge)
            fit = (errs**2 / np.einsum("kii->ki", covs)).mean(axis=0)
            print(f"{f}: {name}: fitted variance scale (GTSAM order) " + " ".join(f"{x:.4g}" for x in fit))
            if scale is not None:
                covs = calibrate(covs, np.array(scale))
            rows.append(table(name + ("" if scale is None else " (rescaled)"), summarise(errs, covs, planar)))
    print()
    print("\n".join(["| run | samples | per axis mean (e/sigma)^2 (share <= 3.84) | x-y NEES [95 % band] (share in "
                     "95 % bound) | full NEES [95 % band] (share in bound) |", "|---|---|---|---|---|"] + rows))
    return 0


def _anchor_rows(submaps_csv: Path, scans: list[int]) -> list[int]:
    """Rows of ``scans`` (scan indices) that are a submap's first scan (``submaps.csv``'s
    ``first_scan``: the anchor's own pose); none without the file."""
    if not submaps_csv.exists():
        return []
    import csv

    with open(submaps_csv, newline="") as f:
        first = {int(row["first_scan"]) for row in csv.DictReader(f)}
    return [n for n, k in enumerate(scans) if k in first]


def real_run(out: Path, log: Path, corrected: Path | None, scale: list[float] | None) -> int:
    """A finished run's ``poses_cov.txt`` (in ``out``) against the log's reference: a CARMEN log's
    corrected log (``corrected``; itself a few cm off, not ground truth) or a cloud folder's
    ground truth / reference poses (``tools/bench_city.ground_truth_per_scan``). Errors of the
    scans with a reference, relative to the first of them, in each scan's frame, against the
    file's covariances (relative to scan 0, which the graph holds fixed; the first referenced scan
    is at or near it). Every scan is a sample (neighbours are strongly correlated); a second row
    scores the anchors alone (each submap's first scan, ``submaps.csv``). ``scale``: the
    variance scale the run used, to show the raw marginals' figures beside the written ones."""
    from submapslam.geometry import inverse
    from submapslam.io.trajectory import carmen_reference_trajectory, read_tum_cov

    traj, covs = read_tum_cov(out / "poses_cov.txt")
    if corrected is not None:
        ref = carmen_reference_trajectory(corrected, log)
        index = {round(float(t), 6): k for k, t in enumerate(traj.timestamps)}
        pairs = [(index[round(float(t), 6)], P) for t, P in zip(ref.timestamps, ref.poses)
                 if round(float(t), 6) in index]
    else:
        sys.path.insert(0, str(REPO / "tools"))
        from bench_city import ground_truth_per_scan

        _, gt = ground_truth_per_scan(log, len(traj.poses))
        pairs = list(enumerate(gt))
    if len(pairs) < 3:
        raise SystemExit(f"only {len(pairs)} scans of {out} have a reference pose")
    planar = bool(np.all(covs[:, 5, 5] < 1e-4))  # z pinned (sigma 1e-4 m per edge)
    (f, R_f), rest = pairs[0], pairs[1:]
    errs = np.array([pose_error(inverse(R_f) @ R, inverse(traj.poses[f]) @ traj.poses[k]) for k, R in rest])
    c = covs[[k for k, _ in rest]]
    print(f"{out}: {len(rest)} scans with a reference (the first at scan {f})\n")
    print("| covariances | samples | per axis mean (e/sigma)^2 (share <= 3.84) | x-y NEES [95 % band] (share in "
          "95 % bound) | full NEES [95 % band] (share in bound) |\n|---|---|---|---|---|")
    print(table("as written", summarise(errs, c, planar)))
    anchors = _anchor_rows(out / "submaps.csv", [k for k, _ in rest])
    if len(anchors) >= 3:
        print(table("as written, anchors (each submap's first scan)", summarise(errs[anchors], c[anchors], planar)))
    if scale is not None:
        from submapslam.uncertainty import calibrate

        print(table("raw marginals (the scale undone)", summarise(errs, calibrate(c, 1.0 / np.array(scale)), planar)))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--world2d", default="rectangle", help="rectangle, rooms, figure8 ...")
    ap.add_argument("--seeds2d", default="0:20")
    ap.add_argument("--laps", type=int, default=2)
    ap.add_argument("--path3d", default="05", help="KITTI sequence whose path the terrain city follows")
    ap.add_argument("--seeds3d", default="0:20")
    ap.add_argument("--scans3d", type=int, default=200)
    ap.add_argument("--rings", type=int, default=16)
    ap.add_argument("--kitti-gt", type=Path, default=KITTI_GT, help="folder of KITTI ground-truth NN.txt(.xz)")
    ap.add_argument("--ekf-runs", type=int, default=20)
    ap.add_argument("--config", default=None, help="pipeline config YAML (default: the defaults)")
    ap.add_argument("--only", nargs="+", default=["2d", "3d", "ekf"], choices=["2d", "3d", "ekf"])
    ap.add_argument("--json", default=None, help="write summaries and every sample here")
    ap.add_argument("--workdir", default=None, help="where the temporary logs go (default: the system's)")
    ap.add_argument("--rescore", nargs="+", metavar="JSON", help="no runs: score the samples of these --json files "
                    "again, their covariances scaled per axis by --scale (a calibration applied after the fact)")
    ap.add_argument("--scale", nargs=6, type=float, metavar=("RX", "RY", "RZ", "X", "Y", "Z"),
                    help="with --rescore: variance scale per axis, GTSAM order")
    ap.add_argument("--run", nargs=2, type=Path, metavar=("OUT", "LOG"),
                    help="no runs: a finished run's OUT/poses_cov.txt against LOG's reference (a cloud folder's "
                    "ground truth, or with --corrected a CARMEN log's corrected log); --scale: the scale the run "
                    "used, to show the raw marginals too")
    ap.add_argument("--corrected", type=Path, help="with --run: the CARMEN corrected log")
    args = ap.parse_args(argv)
    if args.run:
        return real_run(*args.run, args.corrected, args.scale)
    if args.rescore:
        return rescore(args.rescore, args.scale)

    from datasets_synth import generate
    from datasets_synth.city import generate_kitti_drive

    if args.workdir:
        Path(args.workdir).mkdir(parents=True, exist_ok=True)  # a new folder is fine: only temporary logs go there
    keep: dict = {"workdir": args.workdir, "args": {k: str(v) for k, v in vars(args).items()}}
    header = ["| run | samples | per axis mean (e/sigma)^2 (share <= 3.84) | x-y NEES [95 % band] (share in 95 % bound) "
              "| full NEES [95 % band] (share in bound) |", "|---|---|---|---|---|"]
    rows: list[str] = []
    if "2d" in args.only:
        rows += monte_carlo(f"{args.world2d} {args.laps} laps", seed_range(args.seeds2d),
                            lambda s, out: generate(args.world2d, out, seed=s, laps=args.laps), args.config, keep)
    if "3d" in args.only:
        path = args.kitti_gt / f"{args.path3d}.txt.xz"
        rows += monte_carlo(f"terrain city {args.path3d}, {args.scans3d} scans", seed_range(args.seeds3d),
                            lambda s, out: generate_kitti_drive(path, out, rings=args.rings, seed=s, terrain=True,
                                                                max_scans=args.scans3d),
                            args.config, keep)
    if rows:
        print("\n".join(header + rows) + "\n")
    if "ekf" in args.only:
        print("\n".join(ekf_rows(args.ekf_runs, args.workdir)))
    if args.json:
        keep.pop("workdir")
        Path(args.json).write_text(json.dumps(keep))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
