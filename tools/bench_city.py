"""Long 3D drives: submapslam side by side with KISS-ICP and KISS-SLAM, in one bench run.

Usage:
    python tools/bench_city.py LOG... [--tools submapslam kiss-icp kiss-slam] [--max-scans N]
        [--out DIR] [--json FILE] [--markdown FILE] [--config FILE]
    python tools/bench_city.py --generate 00 02 05 08 --rings 16 --data-root /work/bench_data

LOG is a synthetic cloud-folder log (scans/NNNNNN.ply, times.txt, odometry_tum.txt,
groundtruth_tum.txt, meta.yaml), or a real log folder with ``reference_poses_kitti.txt`` (one pose a
scan file) and ``scans/times.txt``: ``python tools/bench_city.py ../shared/data/lidar3d/livox_hku_loop
../shared/data/lidar3d/livox_hku_main_building``. ``--generate NN`` uses DATA_ROOT/kittiNN_RR and writes it
first with ``datasets_synth.generate_kitti_drive`` along the KITTI ground-truth path NN when the
folder is missing.

Every tool runs in its own child process, one after the other: ``submapslam run LOG --out OUT``
(all its output files written), and tools/bench_city_child.py for KISS-ICP (``KissICP``) and
KISS-SLAM (``KissSLAM``), which read the very same scans with submapslam's reader and run with
their default configuration except ``deskew: false``. Wall time is measured around the whole
child process (interpreter start-up, imports, reading, writing), peak memory is the child's own
``ru_maxrss`` from ``os.wait4`` (not the cumulative RUSAGE_CHILDREN); for submapslam, whose 3D
odometry runs in a child process of its own that ends before the maps are fused, at least the
main process's peak when that child ended plus the child's own (both from ``summary.json``):
wait4 reports only the larger of the two processes. The peers get no wheel
odometry: on the toy ``outdoor`` world, whose corners turn 90 deg within 2-3 scans (up to 47 deg
between scans), KISS-ICP's constant-velocity prediction loses the heading at every corner; the
KITTI paths turn at real vehicle rates.

KISS-SLAM 0.0.2 needs map_closures 2.2.0, which pins numpy<2.3, pydantic<2.14 and typer<0.26:
installing it here would downgrade submapslam's environment. Unless the main venv already has
it, it is installed on first use into a separate venv (``--peer-venv``, default
../bench_venv next to the repository: ``python -m venv`` + ``pip install kiss-slam==0.0.2
libusb-package``), whose interpreter runs its child with the repository on PYTHONPATH for the
reader. ``--no-peer-install`` reports it as skipped instead.

Per log and tool: ATE RMSE after SE(3) alignment [m] and as % of the ground-truth path length,
odometry ATE (submapslam: before loop closure; KISS-ICP: its poses; KISS-SLAM: its KISS-ICP
odometry before closures), closures accepted, false closures (:func:`false_closures`), wall
time, scans/s, peak RSS, memory growth per km (least-squares slope over the second half of the
drive: submapslam's ``summary.json`` ``memory_mb_by_km`` when it has it; the peers' RSS sampled
in the child), and submapslam's time/memory/ATE ratio to each peer.
"""

from __future__ import annotations

import argparse
import csv
import datetime as _dt
import importlib.util
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

TOOLS = ("submapslam", "kiss-icp", "kiss-slam")
TOOL_LABEL = {"submapslam": "submapslam", "kiss-icp": "KISS-ICP", "kiss-slam": "KISS-SLAM"}
KISS_SLAM_REQUIREMENTS = ("kiss-slam==0.0.2", "libusb-package>=1.0.26")
DEFAULT_PEER_VENV = REPO.parent / "bench_venv"
DEFAULT_KITTI_GT = REPO.parent / "shared" / "data" / "trajectories" / "kitti_gt"
CHILD = Path(__file__).resolve().parent / "bench_city_child.py"
DEFAULT_SUBMAP_EXTENT_M = 12.0
MAX_TRANS_ERR_M = 1.0
MAX_ROT_ERR_DEG = 2.0


def _say(msg: str) -> None:
    print(f"bench_city: {msg}", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- child processes

def run_child(cmd: list[str], log_file: Path, env: dict | None = None) -> dict:
    """Run ``cmd`` as a child process; wall time around it and its own rusage from ``wait4``.

    Returns ``wall_s``, ``peak_rss_kib`` (the child's ``ru_maxrss``, KiB on Linux), ``user_s``,
    ``sys_s``, ``exit_code`` and ``pid``. stdout and stderr go to ``log_file``.
    """
    log_file.parent.mkdir(parents=True, exist_ok=True)
    with open(log_file, "wb") as fh:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
    code = os.waitstatus_to_exitcode(status)
    proc.returncode = code  # reaped here; keeps Popen from waiting on it again
    return {"wall_s": wall, "peak_rss_kib": int(usage.ru_maxrss), "user_s": usage.ru_utime,
            "sys_s": usage.ru_stime, "exit_code": code, "pid": proc.pid}


def _tail(path: Path, n: int = 3) -> str:
    try:
        lines = [x for x in path.read_text(errors="replace").splitlines() if x.strip()]
    except OSError:
        return ""
    return " | ".join(lines[-n:])[-400:]


def _can_import(python: str, module: str, env: dict | None = None) -> bool:
    try:
        r = subprocess.run([python, "-c", f"import {module}"], capture_output=True, env=env, timeout=300)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return r.returncode == 0


def _has_module(name: str) -> bool:
    """Whether ``name`` is importable in this (the main) venv."""
    return importlib.util.find_spec(name) is not None


def _peer_env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    return env


def ensure_peer_venv(venv: Path, install: bool) -> tuple[str | None, str]:
    """Interpreter of the separate venv that has kiss-slam, creating it on first use.

    Returns ``(python, note)``; ``python`` is None when kiss-slam is not available (``note``
    says why).
    """
    python = venv / "bin" / "python"
    env = _peer_env()
    if python.exists() and _can_import(str(python), "kiss_slam", env):
        return str(python), f"separate venv {venv}"
    if not install:
        return None, (f"kiss-slam is not installed (not in this venv, not in {venv}); "
                      "run without --no-peer-install to create that venv")
    _say(f"installing {' '.join(KISS_SLAM_REQUIREMENTS)} into {venv} (first use; kiss-slam's "
         "map_closures pins numpy<2.3, so it does not go into the main venv)")
    try:
        if not python.exists():
            subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, capture_output=True)
        r = subprocess.run([str(python), "-m", "pip", "install", "--quiet", *KISS_SLAM_REQUIREMENTS],
                           capture_output=True, text=True)
    except (OSError, subprocess.CalledProcessError) as exc:
        return None, f"could not create the venv {venv}: {exc}"
    if r.returncode != 0:
        last = (r.stderr.strip().splitlines() or ["?"])[-1]
        return None, f"pip install {' '.join(KISS_SLAM_REQUIREMENTS)} into {venv} failed: {last}"
    if not _can_import(str(python), "kiss_slam", env):
        return None, f"kiss_slam does not import in {venv} after installing it"
    return str(python), f"separate venv {venv} (created now)"


def tool_command(tool: str, log: Path, out: Path, args) -> tuple[list[str] | None, dict | None, str]:
    """``(cmd, env, note)`` to run ``tool`` on ``log``; ``cmd`` None means skipped (note: why)."""
    if tool == "submapslam":
        exe = Path(sys.executable).parent / "submapslam"
        if not exe.exists():
            return None, None, f"no submapslam command next to {sys.executable} (run make install)"
        cmd = [str(exe), "run", str(log), "--out", str(out), "--overwrite"]
        if args.config:
            cmd += ["--config", str(args.config)]
        if args.max_scans:
            cmd += ["--max-scans", str(args.max_scans)]
        return cmd, None, "submapslam run, default config" if not args.config else f"submapslam run --config {args.config}"
    tail = [str(CHILD), tool, str(log), str(out)] + (["--max-scans", str(args.max_scans)] if args.max_scans else [])
    if tool == "kiss-icp":
        if not _has_module("kiss_icp"):
            return None, None, "kiss-icp is not installed in this venv"
        return [sys.executable, *tail], None, "KissICP, default config, deskew false"
    if tool == "kiss-slam":
        if _has_module("kiss_slam"):
            return [sys.executable, *tail], None, "KissSLAM, default config, deskew false (main venv)"
        if args._peer_python is None:
            args._peer_python, args._peer_note = ensure_peer_venv(args.peer_venv, not args.no_peer_install)
        if args._peer_python is None:
            return None, None, args._peer_note
        return [args._peer_python, *tail], _peer_env(), f"KissSLAM, default config, deskew false ({args._peer_note})"
    return None, None, f"unknown tool {tool!r}; known: {', '.join(TOOLS)}"


# --------------------------------------------------------------------------- ground truth, metrics

def read_log_meta(log: Path) -> dict:
    import yaml

    path = log / "meta.yaml"
    return (yaml.safe_load(path.read_text()) or {}) if path.exists() else {}


REFERENCE_KITTI = "reference_poses_kitti.txt"  # real logs (../shared/data/lidar3d/livox_*): pose k <-> scan k
#: the reference poses of real logs, one KITTI line per scan file (line k: scan k): the Livox
#: sequences' and SC-A-LOAM's pose-graph output beside its MulRan keyframes (mulran_kaist03, whose
#: file covers the whole drive; its first scans are in the folder)
REFERENCE_FILES = (REFERENCE_KITTI, "optimized_poses.txt.xz")


def reference_file(log: Path) -> Path | None:
    """The real log's reference pose file (:data:`REFERENCE_FILES`), None when it has none."""
    return next((log / name for name in REFERENCE_FILES if (log / name).exists()), None)


def _times_file(log: Path) -> Path:
    candidates = [log / "times.txt", log / "scans" / "times.txt", log / "times.txt.xz"]
    return next((p for p in candidates if p.exists()), candidates[0])


def ground_truth_per_scan(log: Path, n: int | None = None):
    """``(gt, poses)``: the ground-truth Trajectory, and ``(n, 4, 4)`` ground-truth poses of the
    log's first ``n`` scans (matched to times.txt by timestamp within 20 ms). A real log without
    ``groundtruth_tum.txt`` uses its reference pose file (:func:`reference_file`; line k: scan k)."""
    from submapslam.io.trajectory import read_kitti, read_tum

    times_path = _times_file(log)
    reference = reference_file(log)
    if not (log / "groundtruth_tum.txt").exists() and reference is not None:
        # a real log: the reference poses, one KITTI line per scan file, stamped with times.txt
        gt = read_kitti(reference, timestamps=np.loadtxt(times_path, ndmin=1, usecols=0))
        return gt, gt.poses[:n]
    gt = read_tum(log / "groundtruth_tum.txt")
    times = np.loadtxt(times_path, ndmin=1, usecols=0) if times_path.exists() else gt.timestamps
    times = times if n is None else times[:n]
    order = np.argsort(gt.timestamps)
    ts = gt.timestamps[order]
    k = np.clip(np.searchsorted(ts, times), 1, max(len(ts) - 1, 1))
    best = np.where(np.abs(ts[k - 1] - times) <= np.abs(ts[np.minimum(k, len(ts) - 1)] - times), k - 1, k)
    best = np.minimum(best, len(ts) - 1)
    if np.any(np.abs(ts[best] - times) > 0.02):
        raise ValueError(f"{log}: some scans have no ground-truth pose within 20 ms")
    return gt, gt.poses[order[best]]


def path_length_m(poses: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum()) if len(poses) > 1 else 0.0


def ate_rmse(poses_file: Path, gt) -> float:
    """ATE RMSE [m] after SE(3) alignment of a TUM file against the ground truth."""
    from submapslam.evaluation.metrics import ate
    from submapslam.io.trajectory import read_tum

    return float(ate(read_tum(poses_file), gt, align="se3")["rmse"])


def submap_extent_m(submaps: dict[int, tuple[int, int]], gt_scan_poses: np.ndarray) -> float | None:
    """Largest distance of a submap's own scans (ground truth) from its anchor, over all submaps."""
    best = None
    n = len(gt_scan_poses)
    for first, last in submaps.values():
        if not 0 <= first < n:
            continue
        pos = gt_scan_poses[first: min(last, n - 1) + 1, :3, 3]
        d = float(np.linalg.norm(pos - gt_scan_poses[first, :3, 3], axis=1).max())
        best = d if best is None else max(best, d)
    return best


def false_closures(edges, submaps: dict[int, tuple[int, int]], gt_scan_poses: np.ndarray, *,
                   max_trans_m: float = MAX_TRANS_ERR_M, max_rot_deg: float = MAX_ROT_ERR_DEG,
                   default_extent_m: float = DEFAULT_SUBMAP_EXTENT_M) -> dict:
    """Count loop closures that ground truth says are wrong.

    ``edges``: ``(i, j, T_i_j)`` with ``T_i_j = T_world_anchor_i^-1 T_world_anchor_j`` (None when
    only the pair is known); ``submaps``: ``{id: (first_scan, last_scan)}``, the anchor of a
    submap being the pose of its first scan; ``gt_scan_poses``: ``(N, 4, 4)`` ground truth per scan.
    A closure is false when the two submaps' ground-truth paths (their scans' positions) never
    come within twice the submap extent of each other (the extent: :func:`submap_extent_m`, else
    ``default_extent_m``) or when its relative pose differs from the ground truth by more than
    ``max_trans_m`` or ``max_rot_deg``. (The paths, not the anchors: a 2D laser's submaps are
    proposed where their paths pass near each other, and two submaps whose anchors are far apart
    may share most of what they see.)
    Returns ``{"closures", "false", "extent_m", "max_anchor_distance_m", "details"}``.
    """
    from submapslam.geometry import inverse, rotation_angle

    extent = submap_extent_m(submaps, gt_scan_poses)
    extent_known = extent is not None and extent > 0
    extent = extent if extent_known else default_extent_m
    details = []
    for i, j, T_i_j in edges:
        if i not in submaps or j not in submaps:
            details.append({"i": i, "j": j, "false": None, "reason": "submap not in submaps list"})
            continue
        A_i, A_j = gt_scan_poses[submaps[i][0]], gt_scan_poses[submaps[j][0]]
        T_gt = inverse(A_i) @ A_j
        dist = float(np.linalg.norm(T_gt[:3, 3]))
        apart = _path_distance_m(submaps[i], submaps[j], gt_scan_poses)
        d = {"i": int(i), "j": int(j), "anchor_distance_m": round(dist, 3), "path_distance_m": round(apart, 3)}
        reasons = []
        if apart > 2 * extent:
            reasons.append(f"paths {apart:.1f} m apart at their nearest > 2 x extent {extent:.1f} m")
        if T_i_j is not None:
            E = inverse(T_gt) @ np.asarray(T_i_j, dtype=float)
            dt, dr = float(np.linalg.norm(E[:3, 3])), float(np.rad2deg(rotation_angle(E)))
            d.update(trans_err_m=round(dt, 3), rot_err_deg=round(dr, 3))
            if dt > max_trans_m:
                reasons.append(f"translation off by {dt:.2f} m")
            if dr > max_rot_deg:
                reasons.append(f"rotation off by {dr:.2f} deg")
        d["false"] = bool(reasons)
        d["reason"] = "; ".join(reasons)
        details.append(d)
    judged = [d for d in details if d["false"] is not None]
    return {"closures": len(judged), "false": sum(d["false"] for d in judged),
            "extent_m": round(extent, 3), "extent_from_ground_truth": extent_known,
            "max_anchor_distance_m": max((d["anchor_distance_m"] for d in judged), default=None),
            "details": details}


def _path_distance_m(a: tuple[int, int], b: tuple[int, int], gt_scan_poses: np.ndarray) -> float:
    """Nearest distance [m] between the ground-truth positions of two submaps' scans
    ``(first, last)`` (at most 200 of each, evenly spaced)."""
    n = len(gt_scan_poses)

    def positions(first: int, last: int) -> np.ndarray:
        idx = np.arange(max(first, 0), min(last, n - 1) + 1)
        return gt_scan_poses[idx[np.linspace(0, len(idx) - 1, min(len(idx), 200)).astype(int)], :3, 3]

    pa, pb = positions(*a), positions(*b)
    return float(np.linalg.norm(pa[:, None] - pb[None], axis=2).min())


def read_submaps_csv(path: Path) -> dict[int, tuple[int, int]]:
    with open(path, newline="") as fh:
        return {int(r["id"]): (int(r["first_scan"]), int(r["last_scan"])) for r in csv.DictReader(fh)}


def read_accepted_loops_csv(path: Path) -> list[tuple[int, int]]:
    with open(path, newline="") as fh:
        return [(int(r["submap_i"]), int(r["submap_j"])) for r in csv.DictReader(fh)
                if str(r.get("accepted", "0")).strip() in ("1", "True", "true")]


def loop_edges_g2o(path: Path) -> list[tuple[int, int, np.ndarray]]:
    """Loop edges of a graph.g2o: edges between non-consecutive submaps (``|j - i| >= 2``)."""
    from submapslam.io.g2o import read_g2o_edges

    _, edges = read_g2o_edges(path)
    return [(i, j, T) for i, j, T, _info in edges if abs(j - i) >= 2]


def false_closures_from_files(g2o: Path, submaps_csv: Path, gt_scan_poses: np.ndarray, **kw) -> dict:
    """:func:`false_closures` of the loop edges of a submapslam ``graph.g2o``."""
    return false_closures(loop_edges_g2o(g2o), read_submaps_csv(submaps_csv), gt_scan_poses, **kw)


def memory_growth_per_km(pairs) -> float | None:
    """Least-squares slope [MiB/km] of ``[(km, rss_mib), ...]`` over the second half of the drive."""
    from submapslam.process_stats import memory_growth_mb_per_km

    if not pairs:
        return None
    km = np.asarray(pairs, dtype=float).reshape(-1, 2)[:, 0]
    return memory_growth_mb_per_km(pairs, from_km=float(np.nanmax(km)) / 2, min_span_km=0.0)


# --------------------------------------------------------------------------- per tool results

def evaluate_submapslam(out: Path, gt, gt_scan_poses: np.ndarray) -> dict:
    summary = json.loads((out / "summary.json").read_text())
    peaks = summary.get("peak_memory_mb_by_process") or {}
    res: dict = {"scans": summary.get("scans"), "submaps": summary.get("submaps"),
                 "pipeline_peak_memory_mb": summary.get("peak_memory_mb"),
                 # the odometry's child process: wait4 sees only the larger of the two processes;
                 # both together held at most the main process's peak when the child ended plus the
                 # child's own (summary.json), and the main process alone after that
                 "odometry_process_peak_kib": round(1024 * peaks.get("odometry", 0.0)),
                 "main_peak_when_odometry_ended_kib": round(1024 * peaks.get("main_when_odometry_ended", 0.0)),
                 "pipeline_wall_time_s": summary.get("wall_time_total_s"),
                 "loop_candidates_tested": summary.get("loop_candidates_tested")}
    res["ate_m"] = ate_rmse(out / "poses_tum.txt", gt)
    res["odometry_ate_m"] = ate_rmse(out / "odometry_tum.txt", gt)
    submaps = read_submaps_csv(out / "submaps.csv")
    g2o_edges = loop_edges_g2o(out / "graph.g2o")
    fc = false_closures(g2o_edges, submaps, gt_scan_poses)
    by_pair = {(i, j): T for i, j, T in g2o_edges} | {(j, i): np.linalg.inv(T) for i, j, T in g2o_edges}
    accepted = read_accepted_loops_csv(out / "loops.csv")
    fc_csv = false_closures([(i, j, by_pair.get((i, j))) for i, j in accepted], submaps, gt_scan_poses)
    res.update(closures_g2o=len(g2o_edges), closures_loops_csv=len(accepted),
               false_closures_g2o=fc["false"], false_closures_loops_csv=fc_csv["false"],
               loops_csv_accepted_not_in_graph=sum((i, j) not in by_pair for i, j in accepted),
               false_closure_check=fc, false_closure_check_loops_csv=fc_csv)
    mem = summary.get("memory_mb_by_km")
    res["memory_mb_by_km"] = mem
    res["memory_growth_mib_per_km"] = memory_growth_per_km(mem) if mem else None
    res["memory_growth_source"] = "summary.json memory_mb_by_km" if mem else "n/a (no memory_mb_by_km in summary.json)"
    return res


def evaluate_peer(out: Path, gt, gt_scan_poses: np.ndarray) -> dict:
    info = json.loads((out / "result.json").read_text())
    res: dict = {k: info.get(k) for k in ("scans", "version", "points", "points_digest", "python", "numpy",
                                          "seconds_in_process", "config")}
    res["ate_m"] = ate_rmse(out / "poses_tum.txt", gt)
    res["odometry_ate_m"] = ate_rmse(out / "odometry_tum.txt", gt)
    if info.get("loop_edges") is not None:
        submaps = {int(s["id"]): (int(s["first_scan"]), int(s["last_scan"])) for s in info["submaps"]}
        edges = [(int(e["i"]), int(e["j"]), np.asarray(e["T_i_j"])) for e in info["loop_edges"]]
        fc = false_closures(edges, submaps, gt_scan_poses)
        res.update(submaps=len(submaps), closures=info.get("closures"), false_closures=fc["false"],
                   false_closure_check=fc)
    else:
        res.update(closures=None, false_closures=None)
    km = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(gt_scan_poses[:, :3, 3], axis=0), axis=1))]) / 1000
    pairs = [(float(km[min(int(k), len(km) - 1)]), mib) for k, mib in info.get("rss_samples") or []]
    res["memory_mb_by_km"] = pairs
    res["memory_growth_mib_per_km"] = memory_growth_per_km(pairs)
    res["memory_growth_source"] = "RSS sampled in the child"
    return res


def bench_log(log: Path, args) -> dict:
    meta = read_log_meta(log)
    n_meta = meta.get("n_scans")
    n_files = (sum(p.suffix in (".ply", ".pcd", ".bin") for p in (log / "scans").iterdir())
               if (log / "scans").is_dir() else None)
    n = n_files if n_files is not None else n_meta
    if args.max_scans:
        n = min(n, args.max_scans) if n else args.max_scans
    gt, gt_scan_poses = ground_truth_per_scan(log, n)
    entry = {"log": str(log), "name": log.name, "scans": len(gt_scan_poses),
             "path_length_m": path_length_m(gt_scan_poses),
             "meta_path_length_m": meta.get("path_length_m", meta.get("loop_length_m")),
             "meta_n_scans": n_meta, "tools": {}}
    for tool in args.tools:
        out = args.out / log.name / tool
        cmd, env, note = tool_command(tool, log, out, args)
        if cmd is None:
            _say(f"{log.name}: {tool} skipped: {note}")
            entry["tools"][tool] = {"status": "skipped", "reason": note}
            continue
        _say(f"{log.name}: {tool} running ... ({shlex.join(cmd)})")
        child_log = out.with_name(f"{tool}.log")  # beside the tool's folder: `run` writes only into its own
        run = run_child(cmd, child_log, env)
        rec: dict = {"status": "ok", "note": note, "command": shlex.join(cmd), "out": str(out), **run,
                     "peak_rss_mib": run["peak_rss_kib"] / 1024.0, "child_log": str(child_log)}
        if run["exit_code"] != 0:
            rec.update(status="failed", reason=f"exit code {run['exit_code']}: {_tail(child_log)}")
        else:
            try:
                res = (evaluate_submapslam if tool == "submapslam" else evaluate_peer)(out, gt, gt_scan_poses)
            except Exception as exc:  # an unreadable output is a failed run, not a crash of the bench
                res = {}
                rec.update(status="failed", reason=f"evaluating its output: {type(exc).__name__}: {exc}")
            rec.update(res)
            if res.get("odometry_process_peak_kib"):
                rec["peak_rss_kib"] = max(rec["peak_rss_kib"], res["main_peak_when_odometry_ended_kib"]
                                          + res["odometry_process_peak_kib"])
                rec["peak_rss_mib"] = rec["peak_rss_kib"] / 1024.0
            if res:
                rec["ate_percent"] = 100.0 * res["ate_m"] / entry["path_length_m"] if entry["path_length_m"] > 0 else None
                rec["scans_per_s"] = (res.get("scans") or entry["scans"]) / run["wall_s"]
        entry["tools"][tool] = rec
        _say(f"{log.name}: {tool} {rec['status']}: {run['wall_s']:.1f} s, peak {rec['peak_rss_mib']:.0f} MiB"
             + (f", ATE {rec['ate_m']:.3f} m" if rec.get("ate_m") is not None else "")
             + (f" ({rec['reason']})" if rec["status"] != "ok" else ""))
    sub = entry["tools"].get("submapslam")
    for peer in ("kiss-icp", "kiss-slam"):
        p = entry["tools"].get(peer)
        if sub and p and sub["status"] == p["status"] == "ok":
            p["submapslam_ratio"] = {"time": sub["wall_s"] / p["wall_s"],
                                     "memory": sub["peak_rss_kib"] / p["peak_rss_kib"],
                                     "ate": sub["ate_m"] / p["ate_m"] if p["ate_m"] > 0 else None}
    digests = {t: r.get("points_digest") for t, r in entry["tools"].items() if r.get("points_digest")}
    entry["peers_read_identical_points"] = len(set(digests.values())) == 1 if len(digests) > 1 else None
    return entry


# --------------------------------------------------------------------------- report

def _f(v, fmt: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return format(v, fmt)


COLUMNS = ["tool", "ATE [m]", "ATE [%]", "odometry ATE [m]", "closures accepted", "false closures",
           "wall [s]", "scans/s", "peak RSS [MiB]", "memory growth [MiB/km]",
           "time ratio (submapslam / row)", "memory ratio (submapslam / row)", "ATE ratio (submapslam / row)"]


def table_rows(entry: dict) -> list[list[str]]:
    rows = []
    for tool, r in entry["tools"].items():
        label = TOOL_LABEL.get(tool, tool)
        if r["status"] != "ok":
            rows.append([label, f"{r['status']}: {r.get('reason', '')}".replace("|", "/")] + ["–"] * (len(COLUMNS) - 2))
            continue
        if tool == "submapslam":
            closures = f"{r['closures_g2o']} (loops.csv {r['closures_loops_csv']})"
            false = f"{r['false_closures_g2o']} (loops.csv {r['false_closures_loops_csv']})"
            ratio = ["1", "1", "1"]
        else:
            closures = _f(r.get("closures"), "d")
            false = _f(r.get("false_closures"), "d")
            q = r.get("submapslam_ratio") or {}
            ratio = [_f(q.get("time"), ".2f"), _f(q.get("memory"), ".2f"), _f(q.get("ate"), ".2f")]
        mem = _f(r.get("memory_growth_mib_per_km"), ".1f") if r.get("memory_growth_mib_per_km") is not None else "n/a"
        rows.append([label, _f(r["ate_m"], ".3f"), _f(r.get("ate_percent"), ".3f"), _f(r["odometry_ate_m"], ".3f"),
                     closures, false, _f(r["wall_s"], ".1f"), _f(r.get("scans_per_s"), ".1f"),
                     _f(r["peak_rss_mib"], ".0f"), mem, *ratio])
    return rows


def markdown(report: dict) -> str:
    m = report["machine"]
    lines = ["```sh", report["command"], "```", "",
             f"Machine: {m['cpus']} cores, {m['mem_gib']} GiB, Python {m['python']}, {m['date']}. Each tool in its "
             "own process, one after the other; wall time around the whole process (start-up, reading, "
             "writing included), peak RSS = the process's own ru_maxrss from wait4 (submapslam: at least its peak "
             "when its odometry process ended plus that process's peak). False closures: the submaps' "
             f"ground-truth paths more than 2 x the submap extent apart, or the relative pose off by > {MAX_TRANS_ERR_M:g} m / "
             f"{MAX_ROT_ERR_DEG:g} deg. Peers: default config, deskew false, same scans (submapslam's reader)."]
    for e in report["logs"]:
        lines += ["", f"### {e['name']}: {e['scans']} scans, {e['path_length_m'] / 1000:.3f} km (ground truth)", "",
                  "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
        lines += ["| " + " | ".join(r) + " |" for r in table_rows(e)]
        notes = []
        sub = e["tools"].get("submapslam", {})
        if sub.get("status") == "ok":
            fc = sub["false_closure_check"]
            notes.append(f"submapslam: {sub['submaps']} submaps, extent {fc['extent_m']:.1f} m, "
                         f"{sub['loop_candidates_tested']} loop candidates tested; closures = loop edges of "
                         "graph.g2o (loops.csv accepted rows in brackets); memory growth: "
                         + sub["memory_growth_source"])
        ks = e["tools"].get("kiss-slam", {})
        if ks.get("status") == "ok" and ks.get("false_closure_check"):
            notes.append(f"KISS-SLAM: {ks['submaps']} local maps, extent {ks['false_closure_check']['extent_m']:.1f} m")
        if e.get("peers_read_identical_points") is not None:
            notes.append("peers read identical points: " + ("yes" if e["peers_read_identical_points"] else "NO"))
        if notes:
            lines += [""] + [f"* {n}" for n in notes]
    return "\n".join(lines) + "\n"


def _machine() -> dict:
    try:
        mem = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (ValueError, OSError):
        mem = None
    return {"cpus": os.cpu_count(), "mem_gib": mem, "python": platform.python_version(),
            "platform": platform.platform(), "date": _dt.date.today().isoformat()}


def _rel(p: str | Path) -> str:
    try:
        return os.path.relpath(p)
    except ValueError:
        return str(p)


# --------------------------------------------------------------------------- logs to run

def resolve_logs(args) -> list[Path]:
    logs = list(args.logs)
    for seq in args.generate or []:
        seq = f"{int(seq):02d}" if str(seq).isdigit() else str(seq)
        folder = args.data_root / f"kitti{seq}_{args.rings}"
        if not folder.exists():
            try:
                try:
                    from datasets_synth import generate_kitti_drive
                except ImportError:
                    from datasets_synth.city import generate_kitti_drive
            except ImportError as exc:
                raise SystemExit(f"bench_city: cannot generate {folder}: datasets_synth.generate_kitti_drive "
                                 f"is not available yet ({exc})") from None
            path_file = args.kitti_gt / f"{seq}.txt.xz"
            if not path_file.exists():
                path_file = args.kitti_gt / f"{seq}.txt"
            _say(f"generating {folder} along {path_file} ({args.rings} rings) ...")
            generate_kitti_drive(path_file, folder, rings=args.rings)
            (args.data_root / f"{folder.name}.READY").write_text("written by tools/bench_city.py\n")
        elif not (args.data_root / f"{folder.name}.READY").exists():
            _say(f"warning: {folder} has no {folder.name}.READY marker beside it; it may be incomplete")
        logs.append(folder)
    if not logs:
        raise SystemExit("bench_city: no logs; give LOG folders or --generate NN")
    for log in logs:
        if not (log / "groundtruth_tum.txt").exists() and reference_file(log) is None:
            raise SystemExit(f"bench_city: {log}: no groundtruth_tum.txt nor any of {', '.join(REFERENCE_FILES)} "
                             "(not a synthetic cloud-folder log nor a real log with reference poses?)")
    return logs


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("logs", nargs="*", type=Path, metavar="LOG")
    ap.add_argument("--tools", nargs="+", default=list(TOOLS), choices=TOOLS)
    ap.add_argument("--max-scans", type=int)
    ap.add_argument("--out", type=Path, help="per log and tool output folders (default: a new temporary folder)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--markdown", type=Path)
    ap.add_argument("--config", type=Path, help="config file passed to submapslam run")
    ap.add_argument("--generate", nargs="+", metavar="NN", help="KITTI path numbers: DATA_ROOT/kittiNN_RR, generated if missing")
    ap.add_argument("--rings", type=int, default=16)
    ap.add_argument("--data-root", type=Path, default=Path("/work/bench_data"))
    ap.add_argument("--kitti-gt", type=Path, default=DEFAULT_KITTI_GT, help="folder of KITTI ground-truth NN.txt(.xz)")
    ap.add_argument("--peer-venv", type=Path, default=DEFAULT_PEER_VENV,
                    help="separate venv for kiss-slam (its map_closures pins numpy<2.3)")
    ap.add_argument("--no-peer-install", action="store_true", help="do not create/install the kiss-slam venv; skip it")
    args = ap.parse_args(argv)
    args._peer_python, args._peer_note = None, ""
    logs = resolve_logs(args)
    args.out = (args.out or Path(tempfile.mkdtemp(prefix="bench_city_"))).resolve()
    command = shlex.join([_rel(sys.executable), _rel(__file__), *argv])
    report = {"command": command, "machine": _machine(), "out": str(args.out),
              "criteria": {"false_closure": f"paths > 2 x submap extent apart, or relative pose off by > "
                                            f"{MAX_TRANS_ERR_M} m / {MAX_ROT_ERR_DEG} deg",
                           "default_submap_extent_m": DEFAULT_SUBMAP_EXTENT_M},
              "logs": []}
    for log in logs:
        report["logs"].append(bench_log(log.resolve(), args))
        if args.json:  # written after every log, so a long run leaves what it has
            args.json.write_text(json.dumps(report, indent=1, default=_jsonable) + "\n")
    text = markdown(report)
    print(text, end="")
    if args.markdown:
        args.markdown.write_text(text)
    _say(f"outputs in {args.out}")
    return 0


def _jsonable(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return str(o)


if __name__ == "__main__":
    raise SystemExit(main())
