"""Benchmark of multi-session maps: one log cut into sessions, merged, scored as the whole log.

Cuts a CARMEN log (or a cloud-folder log) at scan indices into separate logs (no odometry link
between the pieces: each starts from its own origin), runs ``submapslam run PIECE1 PIECE2 ...``
and, for comparison, one run over the whole log, and scores both against a reference.

    python tools/bench_fleet.py carmen ../shared/data/carmen/intel.clf.bz2 --cuts 4500 9000 \\
        --reference ../shared/data/carmen/corrected/intel-corrected.log.gz --out out/bench_fleet_intel
    python tools/bench_fleet.py folder out/kitti00 --cuts 600 --overlap 200 --reverse-last \\
        --reference out/kitti00/groundtruth_tum.txt --out out/bench_fleet_kitti
    python tools/bench_fleet.py folder /work/bench_data/kitti00_16 --cuts 2270 --reverse-last \\
        --reference /work/bench_data/kitti00_16/groundtruth_tum.txt --out out/bench_fleet_kitti_city

``--overlap N`` starts each later cloud-folder piece N scans before its cut (that session drives
the stretch again). ``--reverse-last`` plays the last piece backwards (a cloud folder only: its scans renamed in
reverse order, each with its own timestamp), so that session drives the path the other way.
Prints a JSON summary (ATE of the merged map and of the single run, sessions placed, times).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def split_carmen(log: Path, cuts: list[int], out: Path) -> list[Path]:
    """Write the CARMEN ``log`` as ``len(cuts) + 1`` logs cut before the laser scans at ``cuts``
    (0-based FLASER indices); other lines go with the scan that follows them."""
    from submapslam.io.compression import open_text

    out.mkdir(parents=True, exist_ok=True)
    pieces = [out / f"{log.name.split('.')[0]}_part{k + 1}.clf" for k in range(len(cuts) + 1)]
    handles = [open(p, "w") for p in pieces]
    header: list[str] = []
    piece, n_scan = 0, 0
    with open_text(log) as fh:
        for line in fh:
            tag = line.split(" ", 1)[0]
            if tag in ("PARAM", "#"):
                header.append(line)
                for h in handles:
                    h.write(line)
                continue
            if tag == "FLASER":
                while piece < len(cuts) and n_scan >= cuts[piece]:
                    piece += 1
                n_scan += 1
            handles[piece].write(line)
    for h in handles:
        h.close()
    return pieces


def split_folder(log: Path, cuts: list[int], out: Path, reverse_last: bool, overlap: int = 0) -> list[Path]:
    """Cut a cloud-folder log (scans in ``log`` or ``log/scans``, ``times.txt``, ``meta.yaml``)
    into folders of symlinks, each scan with its own timestamp and wheel-odometry row (a piece's
    odometry starts from its own origin: no link between the pieces). With
    ``overlap``, each piece after the first starts that many scans before its cut (the later
    session drives that stretch again)."""
    from submapslam.io.cloud_folder import _find_scans
    from submapslam.io.compression import open_text

    folder, scans = _find_scans(log)
    times = next((p for p in (log / "times.txt", folder / "times.txt") if p.is_file()), None)
    stamps = open_text(times).read().split() if times else [str(k) for k in range(len(scans))]
    odo_path = next((p for p in (log / "odometry_tum.txt", folder / "odometry_tum.txt") if p.is_file()), None)
    odometry = [ln for ln in open_text(odo_path).read().splitlines() if ln.strip() and not ln.startswith("#")] \
        if odo_path else []
    if odometry and len(odometry) != len(scans):
        odometry = []  # not one row per scan: leave the pieces without
    bounds = [0, *cuts, len(scans)]
    pieces = []
    for k in range(len(bounds) - 1):
        d = out / f"{log.name}_part{k + 1}"
        if d.exists():
            shutil.rmtree(d)
        (d / "scans").mkdir(parents=True)
        idx = list(range(max(0, bounds[k] - (overlap if k else 0)), bounds[k + 1]))
        if reverse_last and k == len(bounds) - 2:
            idx = idx[::-1]
        for n, i in enumerate(idx):
            (d / "scans" / f"{n:06d}{scans[i].suffix}").symlink_to(scans[i].resolve())
        # each scan keeps its own timestamp (a reversed piece's run backwards): the merged
        # trajectory is scored against the reference at the right poses
        (d / "times.txt").write_text("\n".join(stamps[i] for i in idx) + "\n")
        if (log / "meta.yaml").is_file():
            shutil.copy(log / "meta.yaml", d / "meta.yaml")
        if odometry:  # each scan keeps its own wheel-odometry pose; a piece starts from its own origin
            (d / "odometry_tum.txt").write_text("\n".join(odometry[i] for i in idx) + "\n")
        pieces.append(d)
    return pieces


def run(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=REPO)
    return time.perf_counter() - t0


def ate(est: Path, ref: Path, raw: Path | None, align: str) -> float:
    from submapslam.api import evaluate_files

    return float(evaluate_files(est, ref, align=align, raw_log=raw)["ate"]["rmse"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("kind", choices=["carmen", "folder"])
    ap.add_argument("log", type=Path)
    ap.add_argument("--cuts", type=int, nargs="+", required=True)
    ap.add_argument("--reference", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--reverse-last", action="store_true")
    ap.add_argument("--overlap", type=int, default=0, help="folder logs: later pieces start this many scans early")
    ap.add_argument("--align", default="se3")
    ap.add_argument("--skip-single", action="store_true", help="reuse OUT/single from an earlier run")
    args = ap.parse_args()
    cli = [sys.executable, "-m", "submapslam"]
    pieces = (split_carmen(args.log, args.cuts, args.out / "pieces") if args.kind == "carmen"
              else split_folder(args.log, args.cuts, args.out / "pieces", args.reverse_last, args.overlap))
    raw = args.log if args.kind == "carmen" else None
    for d in ("merged", *([] if args.skip_single else ["single"])):
        shutil.rmtree(args.out / d, ignore_errors=True)
    t_single = None if args.skip_single else run([*cli, "run", str(args.log), "--out", str(args.out / "single")])
    t_merged = run([*cli, "run", *map(str, pieces), "--out", str(args.out / "merged")])
    sessions = json.loads((args.out / "merged" / "summary.json").read_text())["sessions"]
    ate_single = ate(args.out / "single" / "poses_tum.txt", args.reference, raw, args.align)
    ate_merged = ate(args.out / "merged" / "poses_tum.txt", args.reference, raw, args.align)
    print(json.dumps({"ate_single_m": round(ate_single, 4), "ate_merged_m": round(ate_merged, 4),
                      "ratio": round(ate_merged / ate_single, 3),
                      "sessions": [{k: s[k] for k in ("name", "scans", "placed", "links", "note")} for s in sessions],
                      "wall_single_s": t_single and round(t_single, 1), "wall_merged_s": round(t_merged, 1)},
                     indent=1))


if __name__ == "__main__":
    main()
