"""A map on disk: every session's submaps, scans and graph, to be loaded again and extended.

``save_map(session_map, folder)`` writes, and ``load_map(folder)`` reads, a folder (``OUT/map/``
of a ``run``) in open formats, no pickles:

* ``manifest.json`` — format name and version, the sessions (name, source log, scan and submap
  ranges, placed or not), counts; written last, so a folder without it is not a map;
* ``config.yaml`` — the effective configuration (as ``dump-config`` writes it);
* ``scans.npz`` — per scan: ``timestamps (N,)`` (each session's own), ``poses (N, 4, 4)``
  (map frame), ``odometry_poses (N, 4, 4)`` (the session's odometry frame);
* ``submaps.npz`` — per submap: ``anchor_poses (S, 4, 4)``, ``covariances (S, 6, 6)`` (GTSAM
  order), ``descriptors (S, rings, sectors)``, the clouds (anchor frame, stored in their own
  float type), the scan indices and ``T_anchor_scan`` of the scans fused into each, and the
  scans' grid points (sensor frame) the occupancy grids are built from, with, for a 2D laser
  whose log has no-return readings, each grid scan's no-return beam ends
  (``no_return_points``, ``no_return_counts``: free space in the grids);
* ``graph.npz`` — the edges exactly (``i, j, T_i_j, information (GTSAM order), kind``);
  ``graph.g2o`` — the same graph for g2o/GTSAM tools (the loader reads ``graph.npz``);
* ``loops.json`` — every tested hypothesis (the map's loops.csv, with the constraint).

The NPZ files are zip archives with fixed member dates: saving a loaded map gives the same bytes.
"""

from __future__ import annotations

import itertools
import json
import zipfile
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from ..config import config_from_dict, dump_config
from ..errors import InputError
from ..mapping.scan_spill import SpilledScans
from ..result import LoopRecord, SlamResult
from ..session_map import SessionInfo, SessionMap
from .g2o import write_g2o

FORMAT = "submapslam-map"
VERSION = 1
_FILES = ("config.yaml", "scans.npz", "submaps.npz", "graph.npz", "graph.g2o", "loops.json")
_DTYPES = ("float16", "float32", "float64")


def _write_npz(path: Path, arrays: dict[str, np.ndarray] | Iterable[tuple[str, np.ndarray]]) -> None:
    """An ``.npz`` numpy reads (``np.load``), byte-for-byte the same for the same arrays.

    ``arrays``: a dict, or ``(name, array)`` pairs made one at a time (a generator), so that only
    one of several large arrays (a city's concatenated clouds) exists at once."""
    items = arrays.items() if isinstance(arrays, dict) else arrays
    with zipfile.ZipFile(path, "w") as zf:
        for name, array in items:
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info._compresslevel = 1  # fast: the clouds are most of the bytes
            with zf.open(info, "w", force_zip64=True) as fh:
                if isinstance(array, _Stacked):
                    array.write(fh)
                else:
                    np.lib.format.write_array(fh, np.ascontiguousarray(array), allow_pickle=False)
            del array  # before the next one is made


class _Stacked:
    """Arrays to be stored as one ``np.concatenate``-d array, written piece by piece: the same
    ``.npy`` bytes without the copy (a city's clouds and grid scans are 100 MB and more).

    ``arrays``: a list, or any iterable made as it is written (scans spilled to disk, read back a
    submap at a time) with ``rows``, their total number of rows, given."""

    def __init__(self, arrays: Iterable[np.ndarray], width: tuple[int, ...], dtype, rows: int | None = None) -> None:
        self.arrays, self.width, self.dtype = arrays, width, np.dtype(dtype)
        self.rows = rows if rows is not None else sum(len(a) for a in arrays)

    def write(self, fh) -> None:
        header = {"descr": np.lib.format.dtype_to_descr(self.dtype), "fortran_order": False,
                  "shape": (self.rows, *self.width)}
        np.lib.format.write_array_header_1_0(fh, header)
        for a in self.arrays:
            fh.write(np.ascontiguousarray(np.asarray(a, dtype=self.dtype).reshape(-1, *self.width)).tobytes("C"))


def _concat(arrays: list[np.ndarray], width: tuple[int, ...], dtype) -> tuple[np.ndarray, np.ndarray]:
    """Arrays stacked along axis 0 and the ``(len + 1,)`` offsets of each."""
    offsets = np.concatenate([[0], np.cumsum([len(a) for a in arrays])]).astype(np.int64)
    data = np.concatenate([np.asarray(a, dtype=dtype).reshape(-1, *width) for a in arrays]) if arrays \
        else np.zeros((0, *width), dtype=dtype)
    return data, offsets


def _split(data: np.ndarray, offsets: np.ndarray) -> list[np.ndarray]:
    return [data[offsets[k]:offsets[k + 1]] for k in range(len(offsets) - 1)]


def _submap_arrays(session_map: SessionMap) -> Iterator[tuple[str, np.ndarray]]:
    """The arrays of ``submaps.npz`` in file order, each made when it is written."""
    r = session_map.result
    yield "anchor_poses", r.submap_poses.reshape(-1, 4, 4)
    yield "covariances", r.submap_covariances.reshape(-1, 6, 6)
    yield "descriptors", session_map.descriptors
    # clouds: each submap keeps its float type (3D clouds are float16 or float32)
    dtype_code = np.array([_DTYPES.index(np.asarray(p).dtype.name) for p in r.submap_points], dtype=np.int8)
    yield "point_dtype", dtype_code
    yield "point_counts", np.array([len(p) for p in r.submap_points], dtype=np.int64)
    for code, name in enumerate(_DTYPES):
        yield f"points_{name}", _Stacked([p for p, c in zip(r.submap_points, dtype_code) if c == code], (3,), name)
    indices, offsets = _concat([np.asarray(s, dtype=np.int64) for s in r.submap_scan_indices], (), np.int64)
    yield "scan_indices", indices
    yield "scan_offsets", offsets
    yield "scan_poses", _concat(list(r.submap_scan_poses), (4, 4), np.float64)[0]
    # grid scans (spilled to disk during the run) are read back a submap at a time as they are written
    grid_counts = np.array([n for scans in r.submap_scan_points for n in _lengths(scans)], dtype=np.int64)
    first = next((scans[0] for scans in r.submap_scan_points if len(scans)), None)
    grid_dtype = np.asarray(first).dtype.name if first is not None else "float32"
    yield "grid_points", _Stacked(itertools.chain.from_iterable(r.submap_scan_points), (3,), grid_dtype,
                                  rows=int(grid_counts.sum()))
    yield "grid_counts", grid_counts
    yield "grid_scans_per_submap", np.array([len(s) for s in r.submap_scan_points], dtype=np.int64)
    held = [r.no_returns_of(k) for k in range(r.n_submaps)]
    if any(len(ends) for ends in held):
        # each grid scan's no-return beam ends, in the order of grid_points (none for submaps without)
        empty = np.zeros((0, 3), dtype=np.float32)
        per_submap = [ends if len(ends) else [empty] * len(scans) for scans, ends in zip(r.submap_scan_points, held)]
        counts = np.array([n for ends in per_submap for n in _lengths(ends)], dtype=np.int64)
        yield "no_return_points", _Stacked(itertools.chain.from_iterable(per_submap), (3,), "float32",
                                           rows=int(counts.sum()))
        yield "no_return_counts", counts


def _lengths(scans: Sequence[np.ndarray]) -> list[int]:
    """Each array's number of rows; spilled scans (:class:`~submapslam.mapping.scan_spill.SpilledScans`)
    say it without being read."""
    return scans.lengths() if isinstance(scans, SpilledScans) else [len(p) for p in scans]


def save_map(session_map: SessionMap, folder: str | Path) -> dict[str, Path]:
    """Write ``session_map`` into ``folder`` (created); return ``{file name: path}``."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    r = session_map.result
    paths = {name: out / name for name in (*_FILES, "manifest.json")}
    paths["config.yaml"].write_text(dump_config(r.config))
    _write_npz(paths["scans.npz"], {"timestamps": np.asarray(r.timestamps, dtype=np.float64),
                                    "poses": r.poses.reshape(-1, 4, 4), "odometry_poses": r.odometry_poses.reshape(-1, 4, 4)})
    _write_npz(paths["submaps.npz"], _submap_arrays(session_map))
    n_edges = len(r.edges)
    _write_npz(paths["graph.npz"], {
        "i": np.array([e[0] for e in r.edges], dtype=np.int64), "j": np.array([e[1] for e in r.edges], dtype=np.int64),
        "T_i_j": np.array([e[2] for e in r.edges], dtype=np.float64).reshape(n_edges, 4, 4),
        "information": np.array([e[3] for e in r.edges], dtype=np.float64).reshape(n_edges, 6, 6),
        "kind": np.array([e[4] for e in r.edges], dtype="<U16")})
    write_g2o(paths["graph.g2o"], r.submap_poses, r.edges)
    paths["loops.json"].write_text(json.dumps([_loop_dict(lp) for lp in r.loops], indent=0) + "\n")
    manifest = {
        "format": FORMAT, "version": VERSION, "planar": r.planar, "scans": r.n_scans, "submaps": r.n_submaps,
        "map_voxel_size": r.map_voxel_size, "path_length_m": r.path_length_m, "source": r.source,
        "covariance_model": r.covariance_model,  # how the anchors' covariances were made (scan covariances follow it)
        "sessions": [s.to_dict() for s in session_map.sessions],
    }
    paths["manifest.json"].write_text(json.dumps(manifest, indent=2) + "\n")
    return paths


def _loop_dict(lp: LoopRecord) -> dict:
    def num(v: float):
        return v if np.isfinite(v) else str(v)

    return {"i": lp.i, "j": lp.j, "source": lp.source, "accepted": lp.accepted, "fitness": num(lp.fitness),
            "overlap": num(lp.overlap), "inlier_rmse": num(lp.inlier_rmse), "reason": lp.reason,
            "T_i_j": None if lp.T_i_j is None else np.asarray(lp.T_i_j).tolist(),
            "structure_overlap": num(lp.structure_overlap), "plane_rmse": num(lp.plane_rmse),
            "information": None if lp.information is None else np.asarray(lp.information).tolist()}


def _loop_record(d: dict) -> LoopRecord:
    def arr(v):
        return None if v is None else np.array(v, dtype=np.float64)

    return LoopRecord(d["i"], d["j"], d["source"], d["accepted"], float(d["fitness"]), float(d["overlap"]),
                      float(d["inlier_rmse"]), d["reason"], arr(d["T_i_j"]), float(d["structure_overlap"]),
                      float(d["plane_rmse"]), arr(d["information"]))


def read_manifest(folder: str | Path) -> dict:
    """The map's manifest; :class:`InputError` (one line) when ``folder`` holds no map of a
    version this code reads. A run folder (with ``map/`` inside) is accepted too."""
    folder = Path(folder)
    if not folder.exists():
        raise InputError(folder, "no such map folder")
    if not (folder / "manifest.json").is_file() and (folder / "map" / "manifest.json").is_file():
        folder = folder / "map"
    path = folder / "manifest.json"
    if not path.is_file():
        raise InputError(folder, "not a submapslam map (no manifest.json; a map is the map/ folder a `run` writes)")
    try:
        manifest = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise InputError(path, "not a submapslam map manifest (not JSON)") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise InputError(path, f"not a submapslam map manifest (format is not {FORMAT!r})")
    version = manifest.get("version")
    if not isinstance(version, int):
        raise InputError(path, "map manifest has no format version")
    if version > VERSION:
        raise InputError(path, f"map format version {version} is newer than this submapslam reads ({VERSION}); "
                               "upgrade submapslam")
    if version < VERSION:
        raise InputError(path, f"map format version {version} is older than this submapslam reads ({VERSION}); "
                               "rebuild the map with `submapslam run`")
    manifest["_folder"] = str(folder)
    return manifest


def load_map(folder: str | Path) -> SessionMap:
    """Read a map written by :func:`save_map` (the ``map/`` folder or the run folder holding it)."""
    manifest = read_manifest(folder)
    folder = Path(manifest["_folder"])
    for name in _FILES:
        if not (folder / name).is_file():
            raise InputError(folder / name, "missing: the map folder is incomplete")
    import yaml

    config = config_from_dict(yaml.safe_load((folder / "config.yaml").read_text()), str(folder / "config.yaml"))
    try:
        with np.load(folder / "scans.npz", allow_pickle=False) as f:
            scans = {k: f[k] for k in f.files}
        with np.load(folder / "submaps.npz", allow_pickle=False) as f:
            sub = {k: f[k] for k in f.files}
        with np.load(folder / "graph.npz", allow_pickle=False) as f:
            graph = {k: f[k] for k in f.files}
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        raise InputError(folder, f"cannot read the map's arrays ({exc})") from None
    groups = {name: iter(_split(sub[f"points_{name}"], np.concatenate(
        [[0], np.cumsum(sub["point_counts"][sub["point_dtype"] == code])]))) for code, name in enumerate(_DTYPES)}
    points = [next(groups[_DTYPES[code]]) for code in sub["point_dtype"]]
    scan_indices = [[int(i) for i in s] for s in _split(sub["scan_indices"], sub["scan_offsets"])]
    scan_poses = _split(sub["scan_poses"], sub["scan_offsets"])
    grid_all = _split(sub["grid_points"], np.concatenate([[0], np.cumsum(sub["grid_counts"])]))
    per = np.concatenate([[0], np.cumsum(sub["grid_scans_per_submap"])])
    grid_points = [grid_all[per[k]:per[k + 1]] for k in range(len(per) - 1)]
    no_returns: list[list[np.ndarray]] = []
    if "no_return_points" in sub:  # maps of 2D logs with no-return readings (older maps: none kept)
        ends = _split(sub["no_return_points"], np.concatenate([[0], np.cumsum(sub["no_return_counts"])]))
        no_returns = [ends[per[k]:per[k + 1]] for k in range(len(per) - 1)]
        no_returns = [scans if any(len(e) for e in scans) else [] for scans in no_returns]
    edges = [(int(i), int(j), T, info, str(kind)) for i, j, T, info, kind in
             zip(graph["i"], graph["j"], graph["T_i_j"], graph["information"], graph["kind"])]
    loops = [_loop_record(d) for d in json.loads((folder / "loops.json").read_text())]
    result = SlamResult(
        timestamps=scans["timestamps"], poses=scans["poses"], odometry_poses=scans["odometry_poses"],
        submap_poses=sub["anchor_poses"], submap_covariances=sub["covariances"], submap_points=points,
        submap_scan_indices=scan_indices, submap_scan_poses=scan_poses, submap_scan_points=grid_points,
        submap_scan_no_returns=no_returns,
        edges=edges, loops=loops, planar=bool(manifest["planar"]), config=config,
        map_voxel_size=float(manifest["map_voxel_size"]), path_length_m=float(manifest["path_length_m"]),
        source=manifest.get("source", ""), covariance_model=manifest.get("covariance_model") or {})
    sessions = [SessionInfo(**s) for s in manifest["sessions"]]
    return SessionMap(result, sessions, sub["descriptors"])
