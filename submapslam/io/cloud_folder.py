"""Folders of point-cloud scans: KITTI ``.bin``, ``.ply``, ``.pcd``.

Accepted layouts (``LOG`` is the path given):
    LOG/*.bin|*.ply|*.pcd                      scans directly in the folder
    LOG/{scans,Scans,velodyne,points}/*.ext    scans in a subfolder (synthetic logs, KITTI, MulRan)
Optional beside the scans (in LOG or the scans folder):
    times.txt           one timestamp [s] per scan (plain or ``.xz``); else the index is used
    odometry_tum.txt    wheel odometry ``T_odom_base`` per scan, TUM format
    meta.yaml           ``planar: true`` marks 2D laser logs; ``motion_distorted: false`` marks scans
                        taken from one pose (their per-point times are not used to deskew);
                        ``T_base_sensor`` (4x4 list): the
                        sensor's mounting on the robot base; points are moved into the base
                        frame, the frame the odometry describes
Scans are sorted by file name. Per-point times come from a PLY/PCD ``time``/``t``/``timestamp``/
``offset_time`` field (normalised to [0, 1] over the sweep; ``odometry.deskew`` uses them).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import yaml

from ..errors import InputError
from .cloud_header import check_cloud_file, header_point_count
from .compression import open_text
from .pcd import read_pcd_records
from .ply import read_ply_vertices
from .registry import register_reader
from .scan import Scan, apply_mounting, check_transform

log = logging.getLogger(__name__)

SCAN_SUFFIXES = (".bin", ".ply", ".pcd")
_SUBFOLDERS = ("scans", "Scans", "velodyne", "points", "clouds")
_TIME_FIELDS = ("time", "t", "timestamp", "offset_time")  # offset_time: Livox drivers' [ns]
_PLY_HEADER_BYTES = 65536


def _scan_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in SCAN_SUFFIXES and p.is_file())


def _find_scans(root: Path, warn: bool = True) -> tuple[Path, list[Path]]:
    """The folder holding the scans (``root`` or a scans subfolder) and its scan files, sorted.

    Where both hold scan files, the one with more wins: a stray ``preview.ply`` beside a
    ``scans/`` folder does not make a one-scan log.
    """
    if not root.is_dir():
        raise InputError(root, "is a file, not a folder of scans (a CARMEN log is read as --format carmen)")
    candidates = [(root, _scan_files(root))]
    candidates += [(root / sub, _scan_files(root / sub)) for sub in _SUBFOLDERS if (root / sub).is_dir()]
    candidates = [(folder, files) for folder, files in candidates if files]
    if not candidates:
        raise InputError(root, f"no {'/'.join(SCAN_SUFFIXES)} scans in the folder or its scans/ subfolder")
    folder, files = max(candidates, key=lambda c: len(c[1]))  # ties: the first, the folder itself
    ignored = [f"{len(fs)} in {f.name or f}" for f, fs in candidates if f != folder]
    if ignored and warn:
        log.warning("%s: reading the %d scans in %s; ignoring the scan files elsewhere (%s)",
                    root, len(files), folder.name or folder, ", ".join(ignored))
    return folder, files


def _find_file(names: tuple[str, ...], folders: tuple[Path, ...]) -> Path | None:
    for folder in folders:
        for name in names:
            if (folder / name).is_file():
                return folder / name
    return None


def read_bin(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """KITTI velodyne ``.bin``: float32 ``(x, y, z, intensity)`` records -> ``(N, 3)`` points."""
    size = path.stat().st_size
    if size % 16 != 0:
        raise InputError(path, f"size {size} bytes is not a whole number of 16-byte (float32 x, y, z, "
                         "intensity) records")
    raw = np.fromfile(path, dtype=np.float32)
    return raw.reshape(-1, 4)[:, :3].astype(np.float64), None


def read_cloud(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """PLY/PCD -> ``(N, 3)`` float64 points and ``(N,)`` per-point times (or None)."""
    from .._deps import open3d

    if path.stat().st_size == 0:
        raise InputError(path, "empty file")
    check_cloud_file(path)  # a header claiming more points than the file holds would stall open3d
    if path.suffix.lower() == ".ply":
        with open(path, "rb") as fh:
            records = read_ply_vertices(path, fh.read(_PLY_HEADER_BYTES))
        if records is not None:  # binary x/y/z records: numpy reads them ~20x faster than open3d
            points = np.stack([records["x"], records["y"], records["z"]], axis=1).astype(np.float64)
            name = next((n for n in _TIME_FIELDS if n in records.dtype.names), None)
            return points, None if name is None else records[name].astype(np.float64)
    elif path.suffix.lower() == ".pcd":
        records = read_pcd_records(path)
        if records is not None and {"x", "y", "z"} <= set(records.dtype.names):
            points = np.stack([records["x"], records["y"], records["z"]], axis=1).astype(np.float64)
            name = next((n for n in _TIME_FIELDS if n in records.dtype.names and records[n].ndim == 1), None)
            return points, None if name is None else records[name].astype(np.float64)
    pcd = open3d().t.io.read_point_cloud(str(path))
    if "positions" not in pcd.point:
        raise InputError(path, "no x/y/z points could be read (not a valid PLY/PCD file?)")
    points = pcd.point.positions.numpy().astype(np.float64).reshape(-1, 3)
    times = None
    for name in _TIME_FIELDS:
        if name in pcd.point:
            times = pcd.point[name].numpy().astype(np.float64).reshape(-1)
            break
    return points, times


class CloudFolderReader:
    """Iterate a folder of scans (see module docstring) as :class:`Scan` objects."""

    name = "cloud_folder"

    def __init__(self, path: Path, sensor_frame: bool = False, skip_bad: bool = False) -> None:
        """``sensor_frame=True`` leaves the points in the sensor frame (``T_base_sensor`` is
        still read, e.g. for a converter that stores the mounting separately).
        ``skip_bad=True`` skips unreadable scan files (counted in :attr:`log_info`) instead of
        stopping at the first with an :class:`InputError`."""
        self.path = Path(path)
        self.scan_dir, self.files = _find_scans(self.path)
        _refuse_pointless(self.path, self.files)
        self.skip_bad = skip_bad
        self.skipped_files: list[str] = []
        self.nan_only_files: list[str] = []  # scan files whose every point was NaN/inf
        folders = (self.path, self.scan_dir)
        self.meta = self._read_meta(_find_file(("meta.yaml",), folders))
        self.planar = bool(self.meta.get("planar", False))
        # per-point times are for deskewing; a log whose scans were taken from one pose says so
        # (``motion_distorted: false``; the synthetic logs written before that key: a ``world``
        # and a ``sensor`` entry and no key); their times are then not passed on
        distorted = self.meta.get("motion_distorted")
        self.motion_distorted = bool(distorted) if distorted is not None else not (
            "world" in self.meta and "sensor" in self.meta)
        mounting = self.meta.get("T_base_sensor")
        self.T_base_sensor = np.eye(4) if mounting is None else check_transform(mounting, self.path / "meta.yaml")
        self._mounted = not sensor_frame and not np.array_equal(self.T_base_sensor, np.eye(4))
        times_file = _find_file(("times.txt", "times.txt.xz"), folders)
        self.timed = times_file is not None  # else each scan's timestamp is its index
        self.timestamps = self._read_times(times_file)
        self.odometry = self._read_odometry(_find_file(("odometry_tum.txt",), folders))

    def __len__(self) -> int:
        return len(self.files)

    def _read_meta(self, path: Path | None) -> dict:
        if path is None:
            return {}
        try:
            meta = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise InputError(path, f"not valid YAML ({str(exc).splitlines()[0]})") from None
        if not isinstance(meta, dict):
            raise InputError(path, "meta.yaml must be a mapping")
        return meta

    def _read_times(self, path: Path | None) -> np.ndarray:
        if path is None:
            return np.arange(len(self.files), dtype=np.float64)
        values = []
        with open_text(path) as fh:
            for lineno, line in enumerate(fh, start=1):
                tok = line.split()
                if not tok or tok[0].startswith("#"):
                    continue
                try:
                    values.append(float(tok[0]))
                except ValueError:
                    raise InputError(path, f"not a timestamp: {tok[0][:30]!r}", lineno) from None
                if not np.isfinite(values[-1]):
                    raise InputError(path, f"not a finite timestamp: {tok[0][:30]!r}", lineno)
        times = np.asarray(values)
        if len(times) < len(self.files):
            raise InputError(path, f"{len(times)} timestamps for {len(self.files)} scans")
        return times[: len(self.files)]

    def _read_odometry(self, path: Path | None) -> np.ndarray | None:
        if path is None:
            return None
        from .trajectory import read_tum

        traj = read_tum(path)
        if len(traj.poses) < len(self.files):
            raise InputError(path, f"{len(traj.poses)} odometry poses for {len(self.files)} scans")
        return traj.poses[: len(self.files)]

    @property
    def log_info(self) -> dict:
        """What ``summary.json`` reports about the reading: the format, scan files skipped."""
        return {"log_format": self.name, "skipped_records": len(self.skipped_files),
                "skipped_files": self.skipped_files[:20], "nan_only_files": self.nan_only_files[:20],
                "nan_only_scans": len(self.nan_only_files)}

    def __iter__(self) -> Iterator[Scan]:
        self.skipped_files = []
        self.nan_only_files = []
        index = 0
        for k, path in enumerate(self.files):
            try:
                points, times = read_bin(path) if path.suffix.lower() == ".bin" else read_cloud(path)
            except InputError as exc:
                if not self.skip_bad:
                    raise
                self.skipped_files.append(path.name)
                log.debug("skipped %s", exc)
                continue
            finite = np.all(np.isfinite(points), axis=1)
            if not finite.all():  # NaN/inf points are no returns
                if times is not None and len(times) == len(points):
                    times = times[finite]
                points = points[finite]
                if len(points) == 0:
                    self.nan_only_files.append(path.name)
            if (self.motion_distorted and times is not None and len(times) == len(points)
                    and np.all(np.isfinite(times))):
                span = times.max() - times.min() if len(times) else 0.0
                times = ((times - times.min()) / span if 0 < span < np.inf else np.zeros_like(times))
            else:
                times = None
            if self._mounted:
                points = apply_mounting(points, self.T_base_sensor, self.planar)
            yield Scan(
                index=index,
                timestamp=float(self.timestamps[k]),
                points=points,
                point_times=times,
                odometry=None if self.odometry is None else self.odometry[k],
                planar=self.planar,
                source=str(path.name),
                timed=self.timed,
            )
            index += 1
        if index == 0 and self.skipped_files:
            raise InputError(self.path, f"none of the {len(self.files)} scan files could be read")


def _refuse_pointless(root: Path, files: list[Path], first: int = 20) -> None:
    """An :class:`InputError` when no scan file holds a point (header-only files): such a log
    would make an empty map. Reads the first ``first`` headers, all of them only if those are empty."""
    for subset in (files[:first], files[first:]):
        if any(header_point_count(p) != 0 for p in subset):
            return
    raise InputError(root, f"none of the {len(files)} scan files holds a point (header-only or empty files)")


def _sniff(path: Path) -> bool:
    if not path.is_dir():
        return False
    try:
        _find_scans(path, warn=False)
    except InputError:
        return False
    return True


register_reader("cloud_folder", _sniff, CloudFolderReader)
