"""Per-point ground-truth labels (SemanticKITTI ``.label``) and the maps that are scored against them.

Layout (SemanticKITTI's): one ``NNNNNN.label`` per scan, named like the scan, in ``LOG/labels/``
or in a ``labels/`` folder beside the scans folder (``sequences/00/velodyne`` and
``sequences/00/labels``); little-endian uint32 per point in the scan's order, the class in the
lower 16 bits (the upper 16 are an instance id). Moving classes are 252-259.

2D CARMEN logs written by ``datasets_synth`` carry ``log.clf.labels`` beside ``log.clf``: one
line per FLASER line, ``num_readings`` then one class per beam (0 where the beam has no return);
their ``scans/`` + ``labels/`` copy is what the scorer reads.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import InputError


def read_label_file(path: str | Path, expected: int | None = None) -> np.ndarray:
    """``(N,)`` uint32 labels of one scan; ``expected``: the scan's point count (checked)."""
    path = Path(path)
    size = path.stat().st_size
    if size % 4:
        raise InputError(path, f"size {size} bytes is not a whole number of uint32 labels")
    labels = np.fromfile(path, dtype="<u4")
    if expected is not None and len(labels) != expected:
        raise InputError(path, f"{len(labels)} labels for a scan of {expected} points")
    return labels


def find_label_folder(log_path: str | Path, scan_dir: str | Path) -> Path:
    """The ``labels/`` folder of a cloud-folder log (in the log folder or beside its scans)."""
    for folder in (Path(log_path) / "labels", Path(scan_dir).parent / "labels"):
        if folder.is_dir():
            return folder
    raise InputError(Path(log_path), "no labels/ folder with NNNNNN.label files (SemanticKITTI) in the log")


def labelled_scans(log_path: str | Path) -> Iterator[tuple[int, np.ndarray, np.ndarray, bool]]:
    """``(index, points (N, 3) in the base frame, labels (N,), planar)`` for every scan of a labelled log."""
    from .cloud_folder import CloudFolderReader

    reader = CloudFolderReader(Path(log_path))
    folder = find_label_folder(log_path, reader.scan_dir)
    for scan, path in zip(reader, reader.files):
        label_path = folder / (path.stem + ".label")
        if not label_path.is_file():
            raise InputError(label_path, f"no labels for scan {path.name}")
        yield scan.index, scan.points, read_label_file(label_path, len(scan.points)), reader.planar


def read_map_points(path: str | Path) -> tuple[np.ndarray, float | None]:
    """The points ``(M, 3)`` of a map to score, and the grid resolution (None for a cloud).

    A ``.ply``/``.pcd`` cloud gives its points; a ROS map_server ``.yaml`` (or its ``.pgm``)
    gives the centres of its occupied cells (pixel value 0, the ``write_pgm_yaml`` convention,
    or darker than ``occupied_thresh``) at z = 0.
    """
    import yaml

    from .grid import read_pgm

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such map file")
    suffix = path.suffix.lower()
    if suffix in (".ply", ".pcd"):
        from .cloud_folder import read_cloud

        return read_cloud(path)[0], None
    if suffix == ".pgm":
        path = path.with_suffix(".yaml")
        if not path.is_file():
            raise InputError(path, "a .pgm map needs its .yaml (resolution, origin) beside it")
    elif suffix not in (".yaml", ".yml"):
        raise InputError(path, "a map is a .ply/.pcd cloud or a map_server .yaml/.pgm grid")
    try:
        meta = yaml.safe_load(path.read_text())
        resolution = float(meta["resolution"])
        origin = np.asarray(meta["origin"], dtype=np.float64)[:2]
        image = path.parent / meta["image"]
        thresh = float(meta.get("occupied_thresh", 0.65))
        negate = int(meta.get("negate", 0))
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as exc:
        raise InputError(path, f"not a map_server YAML (needs image, resolution, origin): {exc}") from None
    img = read_pgm(image).astype(np.float64)
    occupancy = img / 255.0 if negate else (255.0 - img) / 255.0
    rows, cols = np.nonzero(occupancy[::-1] > thresh)  # image row 0 is the top (highest y)
    centres = origin + (np.column_stack([cols, rows]) + 0.5) * resolution
    return np.column_stack([centres, np.zeros(len(centres))]), resolution


def scan_poses(log_path: str | Path, poses: str | Path | None, n_scans: int) -> np.ndarray:
    """``T_world_base`` ``(n_scans, 4, 4)``, one per scan in scan order, from a TUM or KITTI file.

    ``poses`` None: the log's own ground truth (``groundtruth_tum.txt`` or ``groundtruth_kitti.txt``
    in the log folder, as ``datasets_synth`` writes). A file with fewer poses than scans is an
    error naming both counts; extra poses beyond the last scan are an error too (wrong file).
    """
    from .trajectory import read_trajectory

    if poses is None:
        for name in ("groundtruth_tum.txt", "groundtruth_kitti.txt"):
            if (Path(log_path) / name).is_file():
                poses = Path(log_path) / name
                break
        else:
            raise InputError(Path(log_path), "no groundtruth_tum.txt / groundtruth_kitti.txt in the log; give the poses")
    traj = read_trajectory(poses)
    if len(traj.poses) != n_scans:
        raise InputError(Path(poses), f"{len(traj.poses)} poses for {n_scans} scans (one pose per scan, in scan order)")
    return traj.poses


def map_made_at(map_path: str | Path) -> Path | None:
    """The poses file a ``clean`` map was made at (``summary.json`` beside it), None for any other
    map. The map is in that file's frame, so that is the frame to score it in."""
    import json

    from .output_folder import written_by

    folder = Path(map_path).parent
    if written_by(folder) != "clean" or not (folder / "summary.json").is_file():
        return None
    try:
        summary = json.loads((folder / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    made = summary.get("poses_resolved") or summary.get("poses")
    return Path(made) if isinstance(made, str) else None


def count_scans(log_path: str | Path) -> int:
    """How many scans a cloud-folder log holds (without reading them)."""
    from .cloud_folder import CloudFolderReader

    return len(CloudFolderReader(Path(log_path)))
