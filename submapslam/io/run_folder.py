"""Read a results folder (what ``run`` or ``ekf`` wrote) into a
:class:`~submapslam.evaluation.run_record.RunRecord` for the reports."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import yaml

from ..errors import InputError
from ..evaluation.run_record import GridImage, RunRecord
from ..trajectory import Trajectory
from .grid import read_pgm
from .trajectory import read_tum, read_tum_cov

_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1", "uint8": "u1",
              "char": "i1", "int8": "i1", "ushort": "<u2", "uint16": "<u2", "short": "<i2", "int16": "<i2",
              "uint": "<u4", "uint32": "<u4", "int": "<i4", "int32": "<i4"}


def read_ply_points(path: str | Path) -> np.ndarray:
    """``(N, 3)`` float32 ``x y z`` of a binary little-endian PLY point cloud (as :func:`~submapslam.
    io.ply.write_ply` and open3d write them), read with numpy."""
    path = Path(path)
    with open(path, "rb") as fh:
        if fh.readline().strip() != b"ply":
            raise InputError(path, "not a PLY file")
        fields, count, fmt = [], None, None
        for _ in range(200):
            line = fh.readline().decode("ascii", "replace").split()
            if not line:
                continue
            if line[0] == "format":
                fmt = line[1]
            elif line[:2] == ["element", "vertex"]:
                count = int(line[2])
            elif line[0] == "element":
                break
            elif line[0] == "property" and count is not None:
                if line[1] not in _PLY_TYPES:
                    raise InputError(path, f"PLY property type {line[1]!r} not supported")
                fields.append((line[2], _PLY_TYPES[line[1]]))
            elif line[0] == "end_header":
                break
        if fmt != "binary_little_endian" or count is None:
            raise InputError(path, "only binary little-endian PLY point clouds are read here")
        data = np.fromfile(fh, dtype=np.dtype(fields), count=count)
    if len(data) < count:
        raise InputError(path, f"PLY truncated: {len(data)} of {count} points")
    return np.stack([data["x"], data["y"], data["z"]], axis=1).astype(np.float32, copy=False)


def _csv_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _columns(rows: list[dict[str, str]]) -> dict[str, np.ndarray]:
    if not rows:
        return {}
    return {k: np.array([float(r[k]) if r[k] not in ("", None) else np.nan for r in rows]) for k in rows[0]}


def read_run_folder(folder: str | Path, *, with_cloud: bool = True) -> RunRecord:
    """Everything a report shows from ``folder``; files a run did not write stay None/empty.

    Raises :class:`InputError` when ``folder`` is not a results folder (no ``summary.json``
    and no ``poses_tum.txt``).
    """
    root = Path(folder)
    if not root.is_dir():
        raise InputError(root, "no such folder (expected the output folder of `submapslam run` or `ekf`)")
    if not (root / "summary.json").is_file() and not (root / "poses_tum.txt").is_file():
        raise InputError(root, "not a results folder: no summary.json or poses_tum.txt in it")
    rec = RunRecord(folder=str(folder))

    def read_json(name: str) -> dict | None:
        p = root / name
        if not p.is_file():
            return None
        try:
            return json.loads(p.read_text())
        except json.JSONDecodeError as exc:
            raise InputError(p, f"not valid JSON ({exc.msg})", exc.lineno) from None

    rec.summary = read_json("summary.json") or {}
    rec.provenance = read_json("input.json")
    rec.nees = read_json("nees.json")
    if (root / "config.yaml").is_file():
        rec.config_text = (root / "config.yaml").read_text()
    if (root / "poses_tum.txt").is_file():
        rec.poses = read_tum(root / "poses_tum.txt")
    if rec.poses is not None and (root / "poses_cov.txt").is_file():
        cov_traj, covs = read_tum_cov(root / "poses_cov.txt")
        if len(cov_traj.timestamps) == len(rec.poses.timestamps):  # one covariance per pose, else none
            rec.pose_covariances = covs
    if (root / "odometry_tum.txt").is_file():
        rec.odometry = read_tum(root / "odometry_tum.txt")
    if (root / "submaps.csv").is_file():
        rec.submaps = _columns(_csv_rows(root / "submaps.csv"))
    if (root / "loops.csv").is_file():
        rec.loops = _csv_rows(root / "loops.csv")
    if (root / "landmarks.csv").is_file():
        rec.landmarks = [{k: float(v) for k, v in r.items()} for r in _csv_rows(root / "landmarks.csv")]
    if (root / "landmarks_truth.csv").is_file():
        rows = _csv_rows(root / "landmarks_truth.csv")
        rec.truth_landmarks = np.array([[float(r["x"]), float(r["y"])] for r in rows]).reshape(-1, 2)
    if (root / "nees.csv").is_file():
        from .nees_csv import read_nees_csv

        rec.pose_nees = read_nees_csv(root / "nees.csv")
    if (root / "map.pgm").is_file() and (root / "map.yaml").is_file():
        meta = yaml.safe_load((root / "map.yaml").read_text())
        rec.grid = GridImage(read_pgm(root / "map.pgm"), np.asarray(meta["origin"][:2], dtype=np.float64),
                             float(meta["resolution"]))
    if with_cloud and not rec.summary.get("planar", True) and (root / "map.ply").is_file():
        rec.cloud = read_ply_points(root / "map.ply")
    return rec


GROUND_TRUTH_NAMES = ("groundtruth_tum.txt", "groundtruth_kitti.txt", "poses_gt_kitti.txt")
"""Ground-truth files a log may ship beside its scans, in this order of preference: TUM (stamped),
then KITTI (one pose per scan file, in scan order)."""


def _shipped_log(folder: str | Path) -> Path | None:
    """The log the results folder ``folder`` was made from (its ``input.json``), when it exists."""
    try:
        doc = json.loads((Path(folder) / "input.json").read_text())
    except (OSError, ValueError):
        return None
    log = Path(doc.get("absolute_path") or doc.get("path") or "")
    return log if str(log) and log.exists() else None


def shipped_ground_truth(folder: str | Path) -> Path | None:
    """The ground truth the log of the results folder ``folder`` ships (its ``input.json`` names
    the log; a file of :data:`GROUND_TRUTH_NAMES` beside it, or in the log folder), or None."""
    log = _shipped_log(folder)
    if log is None:
        return None
    where = log if log.is_dir() else log.parent
    for name in GROUND_TRUTH_NAMES:
        if (where / name).is_file():
            return where / name
    return None


def read_shipped_ground_truth(path: str | Path) -> Trajectory:
    """A shipped ground-truth file as a stamped :class:`~submapslam.trajectory.Trajectory`. TUM
    carries its stamps; a KITTI file (no stamps, one pose per scan) takes the stamps of the scans
    of the cloud folder it sits in (``times.txt``, else the scan index, as the reader stamps the
    scans), so it pairs with a run of that folder by time. A KITTI file whose line count is not
    the folder's scan count is an :class:`InputError` naming both."""
    from .cloud_folder import CloudFolderReader
    from .trajectory import read_kitti, read_trajectory, trajectory_format

    path = Path(path)
    if trajectory_format(path) != "kitti":
        return read_trajectory(path)
    poses = read_kitti(path).poses
    try:
        stamps = CloudFolderReader(path.parent).timestamps
    except InputError as exc:
        raise InputError(path, f"KITTI poses carry no time, and the scans beside them cannot be read ({exc})") from None
    if len(stamps) != len(poses):
        raise InputError(path, f"{len(poses)} poses for the {len(stamps)} scans of {path.parent} (KITTI ground truth "
                         "is one pose per scan, in scan order)")
    return Trajectory(np.asarray(stamps, dtype=np.float64), poses)
