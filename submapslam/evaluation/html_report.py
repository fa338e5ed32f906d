"""One self-contained HTML page per run (``submapslam report``): the map with trajectory,
anchors, uncertainty and loops; error against a reference; the loop hypotheses; where time and
memory went; the effective config and where the input came from.

Takes a :class:`~submapslam.evaluation.run_record.RunRecord` (read by
:func:`submapslam.io.run_folder.read_run_folder`); writes only the page.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import SubmapSlamError
from ..trajectory import Trajectory
from . import html_page as hp
from . import run_figures as rf
from .metrics import Alignment, AlignMode, ate, kitti_segment_error, rpe
from .run_record import RunRecord

LOOP_COLUMNS = ("submap_i", "submap_j", "source", "accepted", "fitness", "overlap", "inlier_rmse", "reason")


def trajectory_errors(reference: Trajectory, series: dict[str, Trajectory], mode: AlignMode
                      ) -> tuple[dict[str, dict], dict[str, tuple[Trajectory, dict]], dict[str, dict]]:
    """ATE, RPE and KITTI segment errors of each trajectory in ``series`` against ``reference``.

    Returns ``(rows: name -> figures, ate per name: name -> (trajectory, ate dict),
    segments: name -> {length [m]: (trans %, deg/m)})``; a series that matches no reference time
    is left out of all three.
    """
    rows, ates, segments = {}, {}, {}
    for name, traj in series.items():
        try:
            a = ate(traj, reference, align=mode)
            p = rpe(traj, reference)
        except SubmapSlamError:
            continue
        row = {"ATE RMSE [m]": a["rmse"], "ATE mean [m]": a["mean"], "ATE max [m]": a["max"],
               "ATE rot RMSE [deg]": a["rotation_rmse_deg"], "RPE [m/frame]": p["rmse"],
               "RPE [deg/frame]": p["rotation_rmse"], "segment [%]": float("nan"),
               "segment [deg/m]": float("nan"), "poses": a["n"]}
        per_length = {}
        try:
            seg = kitti_segment_error(traj, reference)
            row["segment [%]"], row["segment [deg/m]"] = seg["trans_percent"], seg["rot_deg_per_m"]
            for length in seg["lengths_m"]:
                s = kitti_segment_error(traj, reference, lengths=(length,))
                per_length[length] = (s["trans_percent"], s["rot_deg_per_m"])
        except SubmapSlamError:
            pass
        rows[name], ates[name], segments[name] = row, (traj, a), per_length
    return rows, ates, segments


def worse_than_odometry(rows: dict[str, dict]) -> str | None:
    """A warning when the run's ATE is more than 5 % above its own odometry's (before loop
    closure): the loop closures made the trajectory worse. None otherwise."""
    run = next((r for name, r in rows.items() if not name.startswith("odometry")), None)
    odo = next((r for name, r in rows.items() if name.startswith("odometry")), None)
    if run is None or odo is None or not odo["ATE RMSE [m]"] > 0:
        return None
    if run["ATE RMSE [m]"] <= 1.05 * odo["ATE RMSE [m]"]:
        return None
    return (f"this run's ATE ({run['ATE RMSE [m]']:.3f} m) is worse than its odometry's before loop closure "
            f"({odo['ATE RMSE [m]']:.3f} m): a wrong loop closure, or one that was right but badly weighted; "
            "the loop table below says which were accepted")


def _overview(rec: RunRecord) -> str:
    s = rec.summary
    if rec.kind == "ekf":
        keys = [(k, s[k]) for k in s if not isinstance(s[k], dict | list)]
        return hp.key_values(keys)
    pairs = [("scans", s.get("scans")), ("submaps", s.get("submaps")), ("planar (2D laser)", s.get("planar")),
             ("loop hypotheses tested", s.get("loop_candidates_tested")),
             ("accepted", s.get("loop_closures_accepted")), ("rejected", s.get("loop_closures_rejected")),
             ("path length [m]", s.get("path_length_m")), ("wall time [s]", s.get("wall_time_total_s")),
             ("scans/s", s.get("scans_per_second")), ("peak memory [MiB]", s.get("peak_memory_mb"))]
    if s.get("input_error"):
        pairs.append(("input stopped early", s["input_error"]))
    consistency = s.get("consistency") or {}
    if "odometry_chi2_max" in consistency:
        pairs.append(("odometry edges after optimisation (largest chi2, mean per DOF)",
                      f"{consistency['odometry_chi2_max']}, {consistency['odometry_chi2_mean_per_dof']}"))
    if consistency.get("disagrees_with_odometry"):
        pairs.append(("WARNING", consistency["message"]))
    level = level_priors_in_words(s.get("ground_priors") or {})
    if level:
        pairs.append(("level priors (3D)", level))
    return hp.key_values(pairs)


def level_priors_in_words(test: dict) -> str | None:
    """``summary.json``'s ``ground_priors`` (a 3D run's level test and what it decided) in a
    sentence, or None when the run had none: where the world's up came from, whether the ground
    was level, untested or not, and whether the ground priors stayed, and why."""
    if not test:
        return None
    source = {"walls": "the walls' vertical", "ground": "the ground planes"}.get(test.get("level_priors_from"))
    level = test.get("level")
    ratio = test.get("level_ratio")
    if level is None:
        found = "untested (too few anchors saw the ground)"
    else:
        found = f"{'level' if level else 'not level'} (turn {ratio} of the odometry's allowance)"
    words = f"up from {source}; ground {found}" if source else f"ground {found}"
    priors = test.get("priors")
    restored = test.get("odometry_tilt_restored")
    tilt = f"; the {restored} odometry edges' tilt weighed like their yaw again" if restored else ""
    if priors == 0:
        return f"{words}; no ground prior to test (the walls' level priors are no bet on level ground: they stay){tilt}"
    if test.get("kept", True):
        why = ""
        if level is not True and test.get("loop_chi2_with") is not None:
            why = (f": the closures fit them (chi2 {test['loop_chi2_with']} with, "
                   f"{test['loop_chi2_without']} without)")
        return f"{words}; the ground priors stayed{why}"
    allowed = test.get("allowance")
    why = ("no closure vouched for them" if not test.get("loops") else
           f"they took the closures' chi2 from {test.get('loop_chi2_without')} to {test.get('loop_chi2_with')}"
           + ("" if allowed is None else f" ({'must lower it' if allowed == 0 else f'at most +{allowed} allowed'})"))
    count = f"{priors} " if priors else ""
    return f"{words}; the {count}ground priors left the graph: {why}{tilt}"


def _uncertainty(rec: RunRecord) -> str:
    """σ of every pose along the path (``poses_cov.txt``) with its largest values."""
    from .uncertainty_figures import sigma_along_path_figure, sigmas

    planar = bool(rec.summary.get("planar", True))
    s = sigmas(rec.pose_covariances)
    fig = hp.figure(sigma_along_path_figure(rec.poses.positions, rec.pose_covariances, planar),
                    "1σ of each scan pose along the path, about the scan's own axes (x forward, y left"
                    + (")" if planar else ", z up; roll, pitch, yaw)") + ", as poses_cov.txt reports it; the map "
                    "above draws 3σ ellipses of every few scans (orange)", "uncertainty-sigma")
    finite = np.isfinite(s).all(axis=1)
    pairs = [("poses with a covariance", f"{int(finite.sum())} of {len(s)}")]
    if finite.any():
        pairs += [("largest σ x, y [m]", f"{np.max(s[finite, 3]):.4g}, {np.max(s[finite, 4]):.4g}"),
                  ("largest σ yaw [deg]", float(np.degrees(np.max(s[finite, 2]))))]
        if not planar:
            pairs += [("largest σ z [m]", float(np.max(s[finite, 5]))),
                      ("largest σ roll, pitch [deg]", f"{np.degrees(np.max(s[finite, 0])):.4g}, "
                                                      f"{np.degrees(np.max(s[finite, 1])):.4g}")]
    return fig + hp.key_values(pairs)


def _loop_table(rec: RunRecord) -> str:
    if not rec.loops:
        return "<p>No loop hypotheses were tested in this run (loops.csv is empty or absent).</p>"
    sources = sorted({r.get("source", "") for r in rec.loops})
    options = "".join(f'<option value="{hp.esc(x)}">{hp.esc(x)}</option>' for x in sources)
    filters = ('<div class="filters">filter <input id="lq" oninput="filterLoops()" placeholder="text in any column">'
               ' <select id="ls" onchange="filterLoops()"><option value="all">all</option>'
               '<option value="1">accepted</option><option value="0">rejected</option></select>'
               f' <select id="lsrc" onchange="filterLoops()"><option value="all">any source</option>{options}</select>'
               '<span class="count" id="lcount"></span>'
               ' <button type="button" onclick="loopPageStep(-1)">&lsaquo; previous</button>'
               '<span class="count" id="lpage"></span>'
               ' <button type="button" onclick="loopPageStep(1)">next &rsaquo;</button></div>')
    rows, attrs = [], []
    for r in rec.loops:
        ok = r.get("accepted") == "1"
        rows.append([r.get(c, "") if c != "accepted" else ("yes" if ok else "no") for c in LOOP_COLUMNS])
        attrs.append(f'class="{"ok" if ok else "no"}" data-accepted="{"1" if ok else "0"}" '
                     f'data-source="{hp.esc(r.get("source", ""))}"')
    header = ("submap i", "submap j", "source", "accepted", "fitness", "overlap", "inlier RMSE [m]", "reason")
    return filters + hp.table(header, rows, ident="loops", text_columns=(2, 3, 7), row_attrs=attrs)


def _performance(summary: dict) -> str:
    """Stage wall times as bars, scans/s along the run and memory along the path as inline SVG
    charts (drawn without matplotlib: a third of a second less per report)."""
    stages = summary.get("wall_time_s") or {}
    if not isinstance(stages, dict):  # a localize folder: the total here, the stages under time_s
        stages = {k: v for k, v in (summary.get("time_s") or {}).items() if k != "total"}
    html = hp.bar_rows(sorted(stages.items(), key=lambda kv: -kv[1]), "wall time [s]")
    html += ('<p class="sub">Stages overlap: a closed submap\'s graph work (odometry edge, loop tests, iSAM2) '
             "runs beside the next scans' registration, so they add up to more than the wall time "
             f"({hp.fmt(summary.get('wall_time_total_s'))} s).</p>")
    charts = []
    progress = np.asarray(summary.get("scans_by_wall_time_s") or [], dtype=np.float64).reshape(-1, 2)
    if len(progress) > 1:
        t, n = progress[:, 0], progress[:, 1]
        rate = np.diff(n) / np.maximum(np.diff(t), 1e-9)
        charts.append(hp.svg_line_chart(np.r_[t[0], t[1:]], np.r_[rate[0], rate], xlabel="time since start [s]",
                                        ylabel="scans/s (per submap)", step=True))
    else:
        charts.append("<p>scans/s along the run: not recorded (a run made before it was written)</p>")
    memory = np.asarray(summary.get("memory_mb_by_km") or [], dtype=np.float64).reshape(-1, 2)
    if len(memory) > 1:
        growth = summary.get("memory_growth_mb_per_km")
        caption = (f"<figcaption>grows {growth:.1f} MiB/km from the first km on</figcaption>"
                   if growth is not None else "")
        charts.append(hp.svg_line_chart(memory[:, 0] * 1000.0, memory[:, 1], xlabel="distance travelled [m]",
                                        ylabel="resident memory [MiB]", color="#6a3d9a",
                                        hline=summary.get("peak_memory_mb")) + caption)
    figs = "".join(f"<figure>{c}</figure>" for c in charts)
    return f'<div class="figs">{figs}</div>' + html


def _provenance(rec: RunRecord) -> str:
    p = rec.provenance
    if p is None:
        source = rec.summary.get("source") or rec.summary.get("log")
        return hp.key_values([("input", source or "not recorded"), ("scans", rec.summary.get("scans")),
                              ("size, hash, duration", "not recorded (input.json is written by runs since "
                                                       "the report command exists)")])
    size = p.get("size_bytes")
    return hp.key_values([
        ("input", p.get("path")), ("absolute path", p.get("absolute_path")), ("kind", p.get("kind")),
        ("size", f"{size / 1e6:.2f} MB ({size} bytes)" if size is not None else None),
        (f"SHA-256 ({p.get('hash_of', 'content')})", p.get("sha256")), ("files", p.get("files")),
        ("scans", p.get("scans")), ("duration [s]", p.get("duration_s")),
        ("first / last timestamp", f"{p.get('first_timestamp')} / {p.get('last_timestamp')}")])


def build_run_report(rec: RunRecord, reference: Trajectory | Callable[[], Trajectory] | None = None, *,
                     align: AlignMode = Alignment.SE3, reference_name: str = "reference",
                     scan_check: dict | Callable[[], dict | None] | None = None) -> str:
    """The report page of ``rec`` as HTML text; with ``reference`` the error sections too.

    ``reference`` may be a callable that returns it (e.g. a future's ``result``): it is called
    only after the map is drawn, so a reference read in a background thread overlaps the drawing.
    """
    mode = Alignment(align)
    sections: list[tuple[str, str]] = [("Overview", _overview(rec))]
    if rec.kind == "ekf":
        sections.append(("Stochastic map: landmarks",
                         hp.figure(rf.landmarks_figure(rec), "Features with 3σ ellipses coloured by credibility "
                                   "(red: about to be removed, green: confirmed)"
                                   + ("; black crosses: the true landmarks" if rec.truth_landmarks is not None else ""),
                                   "map")))
        if rec.pose_nees is not None:
            t, nees = rec.pose_nees
            sections.append(("NEES of the robot pose against the truth", hp.figure(
                rf.pose_nees_figure(t, nees), "NEES per step of this run (3 DOF: a consistent filter averages 3; "
                "grey: the 95 % band of one step)") + hp.key_values([
                    ("steps with truth", len(nees)), ("mean NEES", float(np.mean(nees))),
                    ("median NEES", float(np.median(nees))),
                    ("share inside the 95 % band", float(np.mean((nees >= 0.2158) & (nees <= 9.348))))])))
        if rec.nees:
            sections.append(("NEES", hp.figure(rf.nees_figure(rec.nees), "Mean NEES of the robot pose per step")
                             + hp.key_values([(k, v) for k, v in rec.nees.items() if not isinstance(v, list)])))
    else:
        what = ("occupancy grid" if rec.grid is not None and rec.cloud is None
                else "map.ply from above (grey: ground, colour: height)")
        sections.append(("Map, trajectory, submaps and loops", hp.layered_figure(
            rf.map_layers(rec), f"The {what}; blue: trajectory, dashed grey: odometry before loop closure, "
            "green: accepted loops, red: rejected hypotheses (reasons in the table below), purple: submap "
            "anchors with 3σ ellipses, orange: 3σ ellipses of every few scans (poses_cov.txt); the boxes above "
            "show and hide the layers")))
        if rec.poses is not None and rec.pose_covariances is not None:
            sections.append(("Uncertainty along the path", _uncertainty(rec)))
    if callable(reference):
        reference = reference()
    if reference is not None and rec.poses is not None:
        series = {"submapslam" if rec.kind != "ekf" else "EKF": rec.poses}
        if rec.odometry is not None:
            series["odometry (before loop closure)"] = rec.odometry
        rows, ates, segments = trajectory_errors(reference, series, mode)
        if not rows:
            sections.append((f"Error against {reference_name}",
                             '<p class="note">No pose of this run matches a reference timestamp (within 0.02 s).</p>'))
        else:
            header = ["trajectory", *next(iter(rows.values()))]
            table = hp.table(header, [[name, *row.values()] for name, row in rows.items()])
            figs = "".join(hp.figure(uri, cap) for uri, cap in rf.error_figures(reference, ates, segments, mode))
            first = next(iter(ates))
            figs += "".join(hp.figure(uri, cap, ident) for uri, cap, ident
                            in rf.evo_figures(reference, ates[first][0], first, mode))
            degenerate = rf.degenerate_alignment(reference, mode)
            warn = f'<p class="note" id="degenerate-alignment">warning: {hp.esc(degenerate)}</p>' if degenerate else ""
            worse = worse_than_odometry(rows)
            warn += f'<p class="note" id="worse-than-odometry">warning: {hp.esc(worse)}</p>' if worse else ""
            sections.append((f"Error against {reference_name} ({mode} alignment)",
                             warn + table + f'<div class="figs">{figs}</div>'))
        if callable(scan_check):
            scan_check = scan_check()
        if scan_check:
            sections.append((f"The log's own scans: this run and {reference_name}",
                             _scan_check(scan_check, reference_name)))
    if rec.kind != "ekf":
        n_ok = sum(r.get("accepted") == "1" for r in rec.loops)
        sections.append((f"Loop hypotheses ({len(rec.loops)} tested, {n_ok} accepted)", _loop_table(rec)))
        sections.append(("Time and memory", _performance(rec.summary)))
    if rec.config_text is not None:
        sections.append(("Effective configuration (config.yaml)", f"<pre>{hp.esc(rec.config_text)}</pre>"))
    sections.append(("Input", _provenance(rec)))
    title = f"submapslam report: {Path(rec.folder).resolve().name}"
    subtitle = f"run folder {rec.folder}; made {time.strftime('%Y-%m-%d %H:%M:%S')}"
    return hp.page(title, subtitle, sections)


def _scan_check(m: dict, reference_name: str) -> str:
    """The loop-pair misfit of the run and of the reference
    (:func:`~submapslam.evaluation.scan_consistency.loop_pair_comparison`) as a short table and a note."""
    table = hp.table(["trajectory", "median misfit [m]", f"pairs {100 * m['margin_m']:.0f} cm worse than the other"],
                     [["this run", f"{m['estimate_median_m']:.4f}", m["estimate_worse"]],
                      [reference_name, f"{m['reference_median_m']:.4f}", m["reference_worse"]]], ident="scan-check")
    verdict = ("The reference is no more consistent with the log's scans than this run: the error above is the "
               "distance between two maps, not this run's error alone."
               if m["reference_median_m"] >= m["estimate_median_m"] else
               "This run parts the log's scans more than the reference does where the robot came back.")
    worst = m.get("at_worst")
    if worst is not None:
        verdict += (f" Where this run is farthest from the reference (its {100 * m['worst_share']:.0f} % largest errors, "
                    f"{worst['compared']} pairs) the median misfit is {worst['estimate_median_m']:.4f} m under this run "
                    f"and {worst['reference_median_m']:.4f} m under {hp.esc(reference_name)}; "
                    f"{worst['estimate_worse']} / {worst['reference_worse']} pairs are worse under each.")
    return (f'<p class="note">Scans of one place on passes at least 30 s apart ({m["compared"]} of {m["pairs"]} '
            f"pairs compared, those one trajectory brings within {m['overlap_m']} m): the median distance from one "
            "scan's points to the other's, each placed by its trajectory. A corrected log is another SLAM system's "
            f"estimate, not the truth. {verdict} (<code>submapslam eval --scans LOG --derive-relations "
            "--match-relations</code> scores both on relations measured by matching the scans.)</p>" + table)


def write_run_report(rec: RunRecord, out_path: str | Path,
                     reference: Trajectory | Callable[[], Trajectory] | None = None, *,
                     align: AlignMode = Alignment.SE3, reference_name: str = "reference",
                     scan_check: dict | Callable[[], dict | None] | None = None) -> Path:
    """Write :func:`build_run_report`'s page to ``out_path``; return the path."""
    out = Path(out_path)
    out.write_text(build_run_report(rec, reference, align=align, reference_name=reference_name,
                                    scan_check=scan_check), encoding="utf-8")
    return out


def build_comparison_report(reference: Trajectory, estimates: dict[str, Trajectory], rows: dict[str, dict],
                            mode: AlignMode, reference_name: str = "reference") -> str:
    """The comparison page: the sortable table of ``rows`` (name -> figures), every estimate over the
    reference, side by side and overlaid, and the error along the path of all of them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .metrics import associate

    mode = Alignment(mode)
    names = {"ate_rmse": "ATE RMSE [m]", "ate_mean": "ATE mean [m]", "ate_max": "ATE max [m]",
             "rpe_trans_rmse": "RPE [m/frame]", "rpe_rot_rmse_deg": "RPE [deg/frame]",
             "segment_trans_percent": "segment [%]", "segment_rot_deg_per_m": "segment [deg/m]"}
    header = ["trajectory", *(names.get(k, k) for k in next(iter(rows.values())))] if rows else ["trajectory"]
    table = hp.table(header, [[name, *row.values()] for name, row in rows.items()], ident="compare")
    fig, ax = plt.subplots(figsize=(9, 9))
    ax.plot(reference.positions[:, 0], reference.positions[:, 1], "k-", lw=1.2, label=reference_name)
    aligned = {}
    for name, est in estimates.items():
        aligned[name], _ = rf.aligned_positions(est, reference, mode)
        ax.plot(aligned[name][:, 0], aligned[name][:, 1], lw=0.8,
                label=f"{name} (ATE {rows[name]['ate_rmse']:.3f} m)")
    ax.set_aspect("equal")
    ax.legend(fontsize=8)
    overlay = hp.figure(hp.png_data_uri(fig), "All estimates over the reference", "map")
    cols = min(3, max(1, len(estimates)))
    nrows = int(np.ceil(len(estimates) / cols))
    fig, axes = plt.subplots(nrows, cols, figsize=(4.6 * cols, 4.6 * nrows), squeeze=False)
    for ax, (name, est) in zip(axes.flat, estimates.items()):
        a = ate(est, reference, align=mode)
        i_e, _ = associate(est, reference)
        ax.plot(reference.positions[:, 0], reference.positions[:, 1], color="0.6", lw=0.8)
        sc = ax.scatter(aligned[name][i_e, 0], aligned[name][i_e, 1], c=a["errors"], s=2, cmap="inferno_r")
        fig.colorbar(sc, ax=ax, shrink=0.8, label="error [m]")
        ax.set_title(f"{name}\nATE {a['rmse']:.3f} m", fontsize=9)
        ax.set_aspect("equal")
    for ax in list(axes.flat)[len(estimates):]:
        ax.axis("off")
    fig.tight_layout()
    side = hp.figure(hp.png_data_uri(fig), "Each estimate on its own, coloured by its position error")
    fig, ax = plt.subplots(figsize=(10, 3.8))
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(reference.positions, axis=0), axis=1))])
    for name, est in estimates.items():
        a = ate(est, reference, align=mode)
        _, i_r = associate(est, reference)
        ax.plot(dist[i_r], a["errors"], lw=0.8, label=name)
    ax.set_xlabel("distance along the reference path [m]")
    ax.set_ylabel("position error [m]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    along = hp.figure(hp.png_data_uri(fig), "Position error along the path")
    sections = [("Figures (click a column to sort)", table), ("Trajectories", f'<div class="figs">{overlay}</div>'),
                ("Side by side", side), ("Error along the path", along)]
    return hp.page(f"Trajectory comparison ({len(estimates)} estimates)",
                   f"reference: {reference_name}; {mode} alignment; made {time.strftime('%Y-%m-%d %H:%M:%S')}",
                   sections)
