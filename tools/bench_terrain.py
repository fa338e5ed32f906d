"""Terrain cities along real KITTI paths: accuracy, closures and the static map, one run per log.

Usage:
    python tools/bench_terrain.py LOG... [--out DIR] [--config FILE] [--max-scans N] [--json FILE]
        [--markdown FILE]
    python tools/bench_terrain.py --generate 00:16 05:16:1800 08:64:1800 09:livox 06:livox:s5 --data-root /work/bench_data

LOG is a synthetic cloud-folder log (``submapslam synth kitti --terrain``). ``--generate
SEQ:RINGS[:SCANS][:sSEED]`` uses DATA_ROOT/terSEQ_RINGS[_SCANS][_sSEED] and writes it first (``synth
kitti --path kitti_gt/SEQ.txt.xz --rings RINGS --terrain [--max-scans SCANS] [--seed SEED]``) when the
folder is missing; RINGS ``livox`` writes the Livox-like pattern with irregular keyframes (``--sensor
livox --keyframes``), RINGS ending in ``kf`` (``16kf``) that many rings at irregular keyframes
(``--rings 16 --keyframes``).

Each log runs as ``submapslam run LOG --out OUT/NAME`` in a child process. Per log: ATE RMSE
after SE(3) alignment [m] and as % of the 3D ground-truth path, odometry ATE, closures accepted
(loops.csv) and false (graph.g2o against the ground truth, ``bench_city.false_closures``),
closures dropped by the final check and rejected by GNC, and of those dropped how many join
anchors the ground truth puts within twice the submap extent (a closure there may well be
right; loops.csv keeps no relative pose, so this is an upper bound on true closures dropped),
what the final check blamed instead (summary.json ``final_check``), whether the ground priors
stayed (summary.json ``ground_priors``: the run's level test), the share of the map's
points in ``map_dynamic.ply`` (nothing moves in these worlds: every such point is a loss), and
the wall time of the child.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tools"))
sys.path.insert(0, str(REPO))

from bench_city import (  # noqa: E402
    ate_rmse,
    false_closures,
    ground_truth_per_scan,
    loop_edges_g2o,
    path_length_m,
    read_submaps_csv,
    submap_extent_m,
)

KITTI_GT = REPO.parent / "shared" / "data" / "trajectories" / "kitti_gt"


def generate(spec: str, root: Path) -> Path:
    """The log of ``SEQ:RINGS[:SCANS][:sSEED]`` under ``root``, written first when missing."""
    parts = spec.split(":")
    seed = parts.pop()[1:] if len(parts) > 2 and parts[-1].startswith("s") else None
    if len(parts) not in (2, 3) or (seed is not None and not seed.isdigit()):
        raise SystemExit(f"--generate {spec!r}: use SEQ:RINGS[:SCANS][:sSEED]")
    seq, rings = parts[0], parts[1]
    name = f"ter{seq}_{rings}" + (f"_{parts[2]}" if len(parts) == 3 else "") + (f"_s{seed}" if seed else "")
    out = root / name
    if not (out / "meta.yaml").exists():
        if rings == "livox":
            sensor = ["--sensor", "livox", "--keyframes"]
        elif rings.endswith("kf"):
            sensor = ["--rings", rings[:-2], "--keyframes"]
        else:
            sensor = ["--rings", rings]
        cmd = [sys.executable, "-m", "submapslam", "synth", "kitti", "--path", str(KITTI_GT / f"{seq}.txt.xz"),
               *sensor, "--terrain", "--out", str(out), "--overwrite"]
        if len(parts) == 3:
            cmd += ["--max-scans", parts[2]]
        if seed:
            cmd += ["--seed", seed]
        proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
        if proc.returncode != 0:
            why = (proc.stderr.strip() or proc.stdout.strip()).splitlines()[-1:] or ["no message"]
            raise SystemExit(f"--generate {spec!r}: synth failed: {why[0]}")
    return out


def evaluate(log: Path, out: Path) -> dict:
    """Figures of one finished run ``out`` of ``log`` (see the module docstring)."""
    summary = json.loads((out / "summary.json").read_text())
    n = summary.get("scans")
    gt, gt_scan = ground_truth_per_scan(log, n)
    # a synthetic log's ground truth is time-stamped: the run's poses are matched to it by time (a
    # log cut with scans left out is not its first scans); a real log's reference is one pose a scan
    synthetic = (log / "groundtruth_tum.txt").exists()
    gt_used = gt if synthetic or len(gt_scan) >= len(gt) else type(gt)(gt.timestamps[: len(gt_scan)], gt_scan)
    ate = ate_rmse(out / "poses_tum.txt", gt_used)
    length = path_length_m(gt_scan)
    submaps = read_submaps_csv(out / "submaps.csv")
    edges = loop_edges_g2o(out / "graph.g2o")
    fc = false_closures(edges, submaps, gt_scan)
    extent = submap_extent_m(submaps, gt_scan) or 20.0
    with open(out / "loops.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    accepted = [r for r in rows if r["accepted"] == "1"]
    dropped = [r for r in rows if r["reason"].startswith("dropped by the final check")]
    gnc = [r for r in rows if r["reason"].startswith("rejected by the optimiser")]

    def near(r: dict) -> bool:
        i, j = int(r["submap_i"]), int(r["submap_j"])
        if i not in submaps or j not in submaps:
            return False
        a, b = gt_scan[submaps[i][0], :3, 3], gt_scan[submaps[j][0], :3, 3]
        return bool(np.linalg.norm(a - b) <= 2 * extent)

    points, moved = summary.get("map_points"), summary.get("map_dynamic_points")
    return {
        "scans": n, "path_m": round(length, 1), "ate_m": round(ate, 4),
        "ate_pct_of_path": round(100.0 * ate / max(length, 1e-9), 4),
        "odometry_ate_m": round(ate_rmse(out / "odometry_tum.txt", gt_used), 4),
        "closures_accepted": len(accepted), "closures_in_graph": len(edges), "false_closures": fc["false"],
        "dropped_final_check": len(dropped), "rejected_gnc": len(gnc),
        "dropped_near_in_truth": sum(near(r) for r in dropped + gnc),
        "gave_way": (summary.get("final_check") or {}).get("gave_way", []),
        "ground_priors": _ground_priors(summary.get("ground_priors") or {}),
        "map_points": points, "map_dynamic_points": moved,
        "map_dynamic_pct": (round(100.0 * moved / max(points + moved, 1), 3)
                            if points is not None and moved is not None else None),
        "relief_m": _relief(log),
    }


def _relief(log: Path) -> float | None:
    import yaml

    meta = yaml.safe_load((log / "meta.yaml").read_text()) if (log / "meta.yaml").exists() else {}
    return (meta.get("terrain") or {}).get("relief_m")


def _ground_priors(test: dict) -> str:
    """summary.json's ``ground_priors`` in a few words: level or not (the ratio), kept or not."""
    if not test:
        return "-"
    ratio = test.get("level_ratio")
    level = "level" if test.get("level") else ("not level" if test.get("level") is False else "untested")
    return f"{level} ({ratio}), " + ("kept" if test.get("kept") else "dropped")


def markdown(rows: list[dict]) -> str:
    head = ("| log | scans | path [m] | relief [m] | ATE [m] | ATE % of path | odometry ATE [m] | closures accepted "
            "(false) | dropped by the final check / GNC (near in truth) | gave way | ground priors | map_dynamic % "
            "| wall [s] |")
    lines = [head, "|" + "---|" * 13]
    for r in rows:
        gave = "; ".join(f"{g['constraint']} {g['i']}-{g['j']}" for g in r["gave_way"]) or "-"
        lines.append(f"| {r['log']} | {r['scans']} | {r['path_m']:.0f} | {r['relief_m']} | {r['ate_m']:.3f} | "
                     f"{r['ate_pct_of_path']:.4f} | {r['odometry_ate_m']:.3f} | {r['closures_accepted']} "
                     f"({r['false_closures']}) | {r['dropped_final_check']} / {r['rejected_gnc']} "
                     f"({r['dropped_near_in_truth']}) | {gave} | {r['ground_priors']} | {r['map_dynamic_pct']} | "
                     f"{r['wall_s']:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="*", type=Path)
    ap.add_argument("--generate", nargs="*", default=[], help="SEQ:RINGS[:SCANS] terrain logs to use (written first)")
    ap.add_argument("--data-root", type=Path, default=Path("/work/bench_data"))
    ap.add_argument("--out", type=Path, default=Path("out/bench_terrain"))
    ap.add_argument("--config", type=Path)
    ap.add_argument("--max-scans", type=int)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--markdown", type=Path)
    args = ap.parse_args(argv)
    logs = list(args.logs) + [generate(s, args.data_root) for s in args.generate]
    if not logs:
        ap.error("give LOG folders or --generate")
    rows = []
    for log in logs:
        out = args.out / log.name
        cmd = [sys.executable, "-m", "submapslam", "run", str(log), "--out", str(out), "--overwrite"]
        if args.config:
            cmd += ["--config", str(args.config)]
        if args.max_scans:
            cmd += ["--max-scans", str(args.max_scans)]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            print(f"{log}: run failed: {proc.stderr.strip().splitlines()[-1:] or proc.stdout[-200:]}", file=sys.stderr)
            continue
        row = {"log": log.name, **evaluate(log, out), "wall_s": round(wall, 1), "command": " ".join(cmd)}
        rows.append(row)
        print(markdown([row]).splitlines()[-1], flush=True)
    text = markdown(rows)
    print(text)
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0 if rows else 1


if __name__ == "__main__":
    raise SystemExit(main())
