"""Regression bench of the real 2D CARMEN logs: each at defaults, against its corrected log.

Usage:
    python tools/bench_real2d.py [--data ../shared/data/carmen] [--logs intel fr079 mit-csail]
                                 [--config FILE] [--out DIR] [--json FILE] [--markdown FILE]
                                 [--numeric native avx2 sse] [--every 1 2 3] [--sensor beams4 range20 noise3]

Each log runs in its own child process (``submapslam.api.run_log``, all output files written);
the parent measures the child's wall time and peak resident set (``os.wait4``). Reported per
log: ATE (RMSE after SE(3) alignment) of the run and of its odometry before loop closure
against the corrected log (scans matched by logger time, CSAIL's by identical ranges), loop
hypotheses tested / accepted, and the relations error on relations *derived* from the corrected
log (:func:`submapslam.evaluation.derived_relations.derive_relations`: pairs close in time plus
pairs across loops; not the benchmark's own relation files), and what the log's own scans say of the run and
of the corrected log alike (:mod:`submapslam.evaluation.scan_consistency`; computed after the
child exits, so outside its wall time): the error on the derived relations *measured by matching
their two scans* (the benchmark's own method; only the relations scan matching fixes are kept),
and the loop-pair misfit (how far the scans part where the robot came back). Prints one markdown table.

``--numeric`` runs every log once per *numeric variant*: the same code and wheels with numpy's
SIMD kernels and OpenBLAS's core type held to what another CPU would pick (environment variables
``NPY_DISABLE_CPU_FEATURES`` and ``OPENBLAS_CORETYPE``). Sums and products then differ in their
last bits, as they do between two users' machines; a run's ATE spread over the variants says how
much of a difference between two figures is the machine and not the code.

``--sensor`` also runs every log as another scanner would have recorded it
(``tools/carmen_sensor_variant.py``, written under ``OUT/variants`` once): ``beamsK`` every K-th
beam, ``rangeR`` ranges beyond R metres as no-returns, ``noiseC`` C centimetres of Gaussian range
noise on every return (a cheaper scanner; seed 0). Its scans keep their times, and the
corrected log is matched to the original log's scans (MIT CSAIL's by their ranges), so a variant
is scored against the same reference poses.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))  # cut_carmen_log, when this file is loaded as a module

#: log name -> (raw log file, corrected log file) inside the carmen data folder
LOGS = {
    "intel": ("intel.clf.bz2", "corrected/intel-corrected.log.gz"),
    "fr079": ("fr079.clf.bz2", "corrected/freiburg-079-corrected.log.gz"),
    "mit-csail": ("mit-csail.clf.bz2", "corrected/mit-csail-corrected.log.gz"),
}
#: numeric variant -> environment of the child (see the module docstring); "native": as the CPU picks
NUMERIC = {
    "native": {},
    "avx2": {"NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR", "OPENBLAS_CORETYPE": "Haswell"},
    "sse": {"NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR", "OPENBLAS_CORETYPE": "Nehalem"},
}
#: Cartographer's published figures (Hess et al. 2016): ATE-like absolute error [m], rotation [deg]
CARTOGRAPHER = {"intel": "0.0229 m / 0.453°", "fr079": "0.0452 m", "mit-csail": "0.0319 m"}


def sensor_variant(spec: str) -> dict:
    """``beamsK`` / ``rangeR`` / ``noiseC`` -> the keyword arguments of ``carmen_sensor_variant.write_variant``."""
    try:
        if spec.startswith("beams"):
            return {"every_beam": int(spec[len("beams"):])}
        if spec.startswith("range"):
            return {"max_range": float(spec[len("range"):])}
        if spec.startswith("noise"):
            return {"range_noise": float(spec[len("noise"):]) / 100.0}
    except ValueError:
        pass
    raise ValueError(f"sensor variant {spec!r}: use beamsK (every K-th beam), rangeR (ranges beyond R m) "
                     "or noiseC (C cm of range noise)")


def child(log: Path, ref: Path, out: Path, config: Path | None, result_json: Path, key_log: Path | None = None) -> None:
    """Run ``log`` at defaults (or ``config``) into ``out`` and write the figures to ``result_json``;
    the corrected log ``ref`` is matched to the scans of ``key_log`` (a sensor variant's original
    log), else of ``log``."""
    from submapslam.api import run_log
    from submapslam.evaluation.derived_relations import count_loop_relations, derive_relations
    from submapslam.evaluation.metrics import ate, relations_error
    from submapslam.io.trajectory import Trajectory, carmen_reference_trajectory

    t0 = time.perf_counter()
    result, _ = run_log(log, out, config=config, overwrite=True)
    wall = time.perf_counter() - t0
    s = result.summary()
    reference = carmen_reference_trajectory(ref, key_log or log)
    relations = derive_relations(reference)
    est = Trajectory(result.timestamps, result.poses)
    odo = Trajectory(result.timestamps, result.odometry_poses)
    doc = {
        "log": log.name, "wall_s_run": wall, "scans": s["scans"], "submaps": s["submaps"],
        "loops_tested": s["loop_candidates_tested"], "loops_accepted": s["loop_closures_accepted"],
        "reference_poses": len(reference), "relations": len(relations),
        "loop_relations": count_loop_relations(relations),
        "ate": ate(est, reference)["rmse"], "ate_odometry": ate(odo, reference)["rmse"],
        "relations_error": relations_error(est, relations),
        "relations_error_odometry": relations_error(odo, relations),
        "consistency": s.get("consistency"),
    }
    result_json.write_text(json.dumps(doc, indent=1, default=float) + "\n")


def variant_log(name: str, data: Path, out: Path, sensor: str) -> Path:
    """``OUT/variants/NAME-SENSOR.clf``: the log as the ``sensor`` variant records it, written once."""
    from carmen_sensor_variant import write_variant

    log = out / "variants" / f"{name}-{sensor}.clf"
    if not log.exists():
        log.parent.mkdir(parents=True, exist_ok=True)
        write_variant(data / LOGS[name][0], log, **sensor_variant(sensor))
    return log


def run_child(name: str, data: Path, out: Path, config: Path | None, numeric: str = "native", every: int = 1,
              sensor: str | None = None) -> dict:
    """One log in a child process under the ``numeric`` variant, at every ``every``-th scan (a cut
    written under ``out/cuts`` by ``tools/cut_carmen_log.py``) or as the ``sensor`` variant records
    it (:func:`variant_log`); its figures plus ``wall_s`` and ``peak_rss_mib``."""
    raw, ref = LOGS[name]
    log = data / raw
    tag = name if every == 1 else f"{name}-every{every}"
    if every > 1:
        log = out / "cuts" / f"{tag}.clf"
        if not log.exists():
            from cut_carmen_log import cut

            log.parent.mkdir(parents=True, exist_ok=True)
            cut(data / raw, log, every)
    key = []
    if sensor is not None:
        try:
            log = variant_log(name, data, out, sensor)
        except ValueError as exc:  # e.g. a beam count the log's beam layout cannot keep
            raise SystemExit(f"{name}: {exc}") from None
        tag, key = f"{tag}-{sensor}", ["--key-log", str(data / raw)]
    tag = tag if numeric == "native" else f"{tag}-{numeric}"
    result_json = out / f"{tag}.json"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(log), str(data / ref),
           str(out / tag), str(result_json)] + (["--config", str(config)] if config else []) + key
    env = {k: v for k, v in os.environ.items() if k not in ("NPY_DISABLE_CPU_FEATURES", "OPENBLAS_CORETYPE")}
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env={**env, **NUMERIC[numeric]})
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"{name}: child exited with {proc.returncode}")
    doc = json.loads(result_json.read_text())
    label = name if every == 1 else f"{name} (1 scan in {every})"
    doc.update(name=label if sensor is None else f"{label} ({sensor})", numeric=numeric, every=every, sensor=sensor,
               log_path=str(log),
               wall_s=wall, peak_rss_mib=usage.ru_maxrss / 1024.0, out=str(out / tag))
    return doc


def scan_judged(name: str, data: Path, run_out: Path) -> dict:
    """What the log's own scans say of the run and of the corrected log (in this process, after the
    child exits: outside its wall time): the loop-pair misfit of both on the same pairs
    (:func:`~submapslam.evaluation.scan_consistency.loop_pair_check`: also at the run's largest
    errors) and both trajectories' error on the derived relations measured by scan matching
    (:func:`~submapslam.evaluation.scan_consistency.scan_matched_relations`)."""
    from submapslam.evaluation.derived_relations import count_loop_relations, derive_relations
    from submapslam.evaluation.metrics import ate, relations_error
    from submapslam.evaluation.scan_consistency import loop_pair_check, scan_matched_relations
    from submapslam.io.scan_lookup import scans_read_once
    from submapslam.io.trajectory import carmen_reference_trajectory, read_trajectory

    raw, ref = LOGS[name]
    run, reference = read_trajectory(run_out / "poses_tum.txt"), carmen_reference_trajectory(data / ref, data / raw)
    scans = scans_read_once(data / raw, reference.timestamps)  # both measures ask only for reference times
    matched, counts = scan_matched_relations(reference, derive_relations(reference), scans)
    return {"loop_pair_misfit": loop_pair_check(run, reference, scans, ate(run, reference)),
            "matched_relations": {**counts, "loops": count_loop_relations(matched),
                                  "run": relations_error(run, matched),
                                  "corrected": relations_error(reference, matched)}}


def table(rows: list[dict]) -> str:
    """The markdown table of :func:`run_child` results."""
    head = ("| log | numeric | scans | wall [s] | peak RSS [MiB] | loops accepted / tested | ATE [m] | odometry-only ATE [m] "
            "| derived relations: trans [m] | rot [deg] | (count, across loops) "
            "| scan-matched relations (kept of derived, across loops): run | corrected log "
            "| loop-pair misfit [m]: run / corrected log (pairs compared; 3 cm worse: run / corrected) | Cartographer (published) |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for d in rows:
        rel = d["relations_error"]
        lines.append(
            f"| {d['name']} | {d.get('numeric', 'native')} | {d['scans']} | {d['wall_s']:.1f} | {d['peak_rss_mib']:.0f} "
            f"| {d['loops_accepted']} / {d['loops_tested']} | **{d['ate']:.3f}** | {d['ate_odometry']:.3f} "
            f"| {rel['trans_mean']:.4f} ± {rel['trans_std']:.4f} | {rel['rot_mean_deg']:.3f} ± {rel['rot_std_deg']:.3f} "
            f"| {d['relations']}, {d['loop_relations']} | {_matched_cells(d.get('matched_relations'))} "
            f"| {_misfit_cell(d.get('loop_pair_misfit'))} "
            f"| {CARTOGRAPHER.get(d['name'], '–')} |")
    return "\n".join(lines)


def _matched_cells(m: dict | None) -> str:
    if not m:
        return "– | –"
    run, ref = m["run"], m["corrected"]
    return (f"({m['matched']} of {m['relations']}, {m['loops']}): {run['trans_mean']:.4f} m, {run['rot_mean_deg']:.3f}° "
            f"| {ref['trans_mean']:.4f} m, {ref['rot_mean_deg']:.3f}°")


def _misfit_cell(m: dict | None) -> str:
    if not m:
        return "–"
    cell = (f"{m['estimate_median_m']:.4f} / {m['reference_median_m']:.4f} ({m['compared']} of {m['pairs']}; "
            f"{m['estimate_worse']} / {m['reference_worse']})")
    worst = m.get("at_worst")
    if worst:
        cell += (f"; at the run's worst {100 * m['worst_share']:.0f} %: {worst['estimate_median_m']:.4f} / "
                 f"{worst['reference_median_m']:.4f} ({worst['compared']}; {worst['estimate_worse']} / "
                 f"{worst['reference_worse']})")
    return cell


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "carmen")
    ap.add_argument("--logs", nargs="+", choices=sorted(LOGS), default=list(LOGS))
    ap.add_argument("--config", type=Path)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--markdown", type=Path)
    ap.add_argument("--numeric", nargs="+", choices=list(NUMERIC), default=["native"],
                    help="numeric variants to run each log under (default: native)")
    ap.add_argument("--every", nargs="+", type=int, default=[1], metavar="K",
                    help="also run each log at every K-th scan (1: the log itself; 2 3: at a half and a third of "
                    "its scan rate, the motion between scans that much larger; the scan-matched columns are left "
                    "out for cuts)")
    ap.add_argument("--sensor", nargs="+", default=[], metavar="VARIANT",
                    help="also run each log as another scanner records it: beamsK (every K-th beam), rangeR (ranges "
                    "beyond R m as no-returns); the scan-matched columns are left out for variants")
    ap.add_argument("--child", nargs=4, metavar=("LOG", "REF", "OUT", "RESULT_JSON"), help=argparse.SUPPRESS)
    ap.add_argument("--key-log", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        log, ref, out, result_json = (Path(p) for p in args.child)
        child(log, ref, out, args.config, result_json, args.key_log)
        return 0
    for spec in args.sensor:
        try:
            sensor_variant(spec)
        except ValueError as exc:
            ap.error(str(exc))
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_real2d_"))
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.logs:  # one after the other: the machine's cores are shared
        for every in args.every:
            for numeric in args.numeric:
                rows.append(run_child(name, args.data, out, args.config, numeric, every))
                if every == 1:
                    rows[-1].update(scan_judged(name, args.data, Path(rows[-1]["out"])))
                print(f"{rows[-1]['name']} ({numeric}): ATE {rows[-1]['ate']:.3f} m, odometry "
                      f"{rows[-1]['ate_odometry']:.3f} m, {rows[-1]['wall_s']:.1f} s", file=sys.stderr)
        for sensor in args.sensor:
            rows.append(run_child(name, args.data, out, args.config, "native", 1, sensor))
    md = table(rows)
    print(md)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    if args.markdown:
        args.markdown.write_text(md + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
