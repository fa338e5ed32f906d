"""One regression bench over every log we have, at defaults, in one table: rerun it whenever the
data path changes.

Usage:
    python tools/bench_regression.py [--data ../shared/data] [--work DIR] [--out DIR] [--json FILE]
        [--only real2d real3d synthetic terrain] [--terrain-scans 600]

Rows, each run in a child process (wall time and its own peak RSS from ``wait4``):

* **real2d**: the CARMEN logs (Intel, FR079, MIT CSAIL), ATE against their corrected logs
  (``bench_real2d.run_child``; its scan-matched relations are left to that tool);
* **real3d**: the real LiDAR sequences in ``DATA/lidar3d`` with ``reference_poses_kitti.txt``
  (the Livox ones), ATE against it (``submapslam run``, then ``bench_terrain.evaluate``);
* **synthetic**: the 2D worlds of ``bench_synthetic`` with the default scanner and the other
  scanners (``bench_synthetic.SCANNERS``), 2 laps, seed 0, written under WORK;
* **terrain**: terrain cities along the KITTI 00, 05 and 08 paths (16 rings, the first
  ``--terrain-scans`` scans; ``bench_terrain.generate`` writes them under WORK once).

Per row: scans, ATE [m], odometry ATE [m] (the same run before loop closure), closures accepted and
false (3D and synthetic, against the truth), wall [s], peak RSS [MiB].
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tools"))
sys.path.insert(0, str(REPO))

GROUPS = ("real2d", "real3d", "synthetic", "terrain")
TERRAIN_PATHS = ("00", "05", "08")


def run_and_evaluate(name: str, kind: str, log: Path, out: Path) -> dict:
    """``submapslam run LOG`` in a child process, then the figures of ``bench_terrain.evaluate``."""
    from bench_city import run_child
    from bench_terrain import evaluate

    cmd = [sys.executable, "-m", "submapslam", "run", str(log), "--out", str(out / name), "--overwrite"]
    usage = run_child(cmd, out / f"{name}.log")
    if usage["exit_code"] != 0:
        return {"name": name, "kind": kind, "error": f"exit code {usage['exit_code']} (see {out / name}.log)"}
    figures = evaluate(log, out / name)
    return {"name": name, "kind": kind, "scans": figures["scans"], "ate_m": figures["ate_m"],
            "odometry_ate_m": figures["odometry_ate_m"], "closures": figures["closures_accepted"],
            "false_closures": figures["false_closures"], "wall_s": usage["wall_s"],
            "peak_rss_mib": usage["peak_rss_kib"] / 1024.0}


def real2d_rows(data: Path, out: Path) -> list[dict]:
    from bench_real2d import LOGS, run_child

    rows = []
    for name in LOGS:
        doc = run_child(name, data / "carmen", out, None)
        rows.append({"name": name, "kind": "real 2D (against the corrected log)", "scans": doc["scans"],
                     "ate_m": doc["ate"], "odometry_ate_m": doc["ate_odometry"], "closures": doc["loops_accepted"],
                     "false_closures": None, "wall_s": doc["wall_s"], "peak_rss_mib": doc["peak_rss_mib"]})
    return rows


def real3d_rows(data: Path, out: Path) -> list[dict]:
    from bench_city import REFERENCE_KITTI

    logs = sorted(p for p in (data / "lidar3d").iterdir() if (p / REFERENCE_KITTI).exists())
    return [run_and_evaluate(log.name, "real 3D (against its reference)", log, out) for log in logs]


def synthetic_rows(work: Path, out: Path) -> list[dict]:
    from bench_synthetic import SCANNERS, write_variant

    rows = []
    for name in ["rectangle", "rooms", "figure8", *SCANNERS]:
        log = work / f"synthetic_{name}"
        if not (log / "meta.yaml").exists():
            write_variant(name, log, seed=0, laps=2)
        rows.append(run_and_evaluate(name, "synthetic 2D", log, out))
    return rows


def terrain_rows(work: Path, out: Path, scans: int) -> list[dict]:
    from bench_terrain import generate

    return [run_and_evaluate(f"terrain {seq}", "synthetic 3D, 16 rings", generate(f"{seq}:16:{scans}", work), out)
            for seq in TERRAIN_PATHS]


def markdown(rows: list[dict]) -> str:
    def f(v, fmt):
        return "—" if v is None else format(v, fmt)

    lines = ["| data | kind | scans | ATE [m] | odometry ATE [m] | closures (false) | wall [s] | peak RSS [MiB] |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['name']} | {r['kind']} | failed: {r['error']} | | | | | |")
            continue
        false = "" if r["false_closures"] is None else f" ({r['false_closures']})"
        lines.append(f"| {r['name']} | {r['kind']} | {r['scans']} | {f(r['ate_m'], '.4f')} | "
                     f"{f(r['odometry_ate_m'], '.4f')} | {r['closures']}{false} | {f(r['wall_s'], '.1f')} | "
                     f"{f(r['peak_rss_mib'], '.0f')} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, default=None, help="where generated worlds are kept between runs "
                    "(default: a temporary folder)")
    ap.add_argument("--out", type=Path, default=None, help="where the runs' output folders go (default: temporary)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--only", nargs="+", choices=GROUPS, default=list(GROUPS))
    ap.add_argument("--terrain-scans", type=int, default=600)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp) / "work"
        out = args.out or Path(tmp) / "out"
        work.mkdir(parents=True, exist_ok=True)
        out.mkdir(parents=True, exist_ok=True)
        rows: list[dict] = []
        for group in args.only:
            if group == "real2d":
                added = real2d_rows(args.data, out)
            elif group == "real3d":
                added = real3d_rows(args.data, out)
            elif group == "synthetic":
                added = synthetic_rows(work, out)
            else:
                added = terrain_rows(work, out, args.terrain_scans)
            print("\n".join(markdown(added).splitlines()[2:]), flush=True)
            rows += added
    table = markdown(rows)
    print(table)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=float) + "\n")
    return 1 if any("error" in r for r in rows) else 0


if __name__ == "__main__":
    raise SystemExit(main())
