"""Write a map of several sessions: the usual results of the placed sessions, one trajectory per
session, a sessions table, and the map itself (``map/``, :mod:`.map_store`).

Files (beside :func:`~submapslam.io.results.write_results`' own):

* ``poses_tum.txt`` (and the other run files) — every *placed* session's scans in the map frame,
  sessions in input order, each line with its log's own timestamp;
* ``poses_tum_<session>.txt`` — each session's own trajectory (an unplaced session's in its own
  frame), ``<session>`` the log's file name without its extensions;
* ``sessions.csv`` — per session: name, log, scans, submaps, placed, links, first and last
  timestamp, and why it was (not) placed;
* ``map/`` — the map to extend with ``run LOG --map OUT`` (every session, placed or not).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

from ..mapping.global_map import MapOutputs
from ..session_map import SessionMap
from .map_store import save_map
from .results import write_results
from .trajectory import Trajectory, write_tum


def write_session_results(session_map: SessionMap, out_dir: str | Path, maps: MapOutputs,
                          map_paths: dict[str, Path] | None = None) -> dict[str, Path]:
    """Write the map of ``session_map`` (``maps``: fused from its placed sessions) into ``out_dir``;
    ``map_paths``: :func:`~.map_store.save_map`'s return when ``out_dir/map/`` is already written."""
    out = Path(out_dir)
    placed = session_map.placed_result()
    paths = write_results(placed, out, maps)
    r = session_map.result
    for s in session_map.sessions:
        path = out / f"poses_tum_{s.name}.txt"
        write_tum(path, Trajectory(r.timestamps[s.scans], r.poses[s.scans]))
        paths[path.name] = path
    paths["sessions.csv"] = out / "sessions.csv"
    with open(paths["sessions.csv"], "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["session", "log", "scans", "submaps", "placed", "links", "first_timestamp", "last_timestamp", "note"])
        for s in session_map.sessions:
            stamps = r.timestamps[s.scans]
            w.writerow([s.name, s.source, s.scan_end - s.scan_start, s.submap_end - s.submap_start, int(s.placed),
                        s.links, f"{stamps[0]:.6f}" if len(stamps) else "", f"{stamps[-1]:.6f}" if len(stamps) else "",
                        s.note])
    summary = json.loads(paths["summary.json"].read_text())
    summary["sessions"] = [{"name": s.name, "log": s.source, "scans": s.scan_end - s.scan_start,
                            "submaps": s.submap_end - s.submap_start, "placed": s.placed, "links": s.links,
                            "note": s.note} for s in session_map.sessions]
    if "merge" in r.stage_seconds:
        summary["wall_time_s"]["merge"] = round(r.stage_seconds["merge"], 3)
    paths["summary.json"].write_text(json.dumps(summary, indent=2) + "\n")
    paths.update({f"map/{k}": v for k, v in (map_paths or save_map(session_map, out / "map")).items()})
    return paths
