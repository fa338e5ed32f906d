"""Trajectory files: TUM, KITTI, CARMEN (poses in FLASER lines), and CARMEN references.

Readers return the core types :class:`~submapslam.trajectory.Trajectory` (``timestamps (N,)``
plus ``poses (N, 4, 4)`` ``T_world_base``) and :class:`~submapslam.trajectory.Relations`, which
are re-exported here for compatibility.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import numpy as np

from ..errors import ConfigError, InputError
from ..geometry import matrix_to_quat, poses_from_xyz_quats, se2_to_matrix
from ..trajectory import Relations, Trajectory
from .compression import base_suffix, open_text

__all__ = [
    "Relations", "Trajectory", "carmen_reference_trajectory", "read_carmen_trajectory", "read_kitti",
    "read_relations", "read_trajectory", "read_tum", "trajectory_format", "write_kitti", "write_tum",
]


def _rows(path: Path, ncols: tuple[int, ...]) -> list[tuple[int, np.ndarray]]:
    rows = []
    with open_text(path) as fh:
        for lineno, line in enumerate(fh, start=1):
            body = line.strip()
            if not body or body.startswith("#"):
                continue
            tok = body.replace(",", " ").split()
            if len(tok) not in ncols:
                raise InputError(path, f"expected {' or '.join(map(str, ncols))} numbers, got {len(tok)}", lineno)
            try:
                values = np.array(tok, dtype=np.float64)
            except ValueError:
                raise InputError(path, f"non-numeric value in {body[:40]!r}", lineno) from None
            if not np.all(np.isfinite(values)):
                raise InputError(path, "NaN or infinite value", lineno)
            rows.append((lineno, values))
    if not rows:
        raise InputError(path, "no poses in the file")
    return rows


def read_tum(path: str | Path) -> Trajectory:
    """TUM: ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments allowed."""
    path = Path(path)
    rows = _rows(path, (8,))
    for lineno, r in rows:
        norm = float(np.linalg.norm(r[4:8]))
        if not 1e-6 < norm < 1e150:  # normalised below; zero (or overflowing) has no rotation
            raise InputError(path, f"quaternion qx qy qz qw has length {norm:.3g}: not a rotation", lineno)
    values = np.array([r for _, r in rows])
    return Trajectory(values[:, 0], poses_from_xyz_quats(values[:, 1:4], values[:, 4:8]))


def write_tum(path: str | Path, traj: Trajectory) -> None:
    """Write TUM lines; timestamps with 6 decimals, poses with 9 significant digits."""
    Path(path).write_text("".join(_tum_lines(traj)) or "\n")


_TUM_LINE = "%.6f" + " %.9g" * 7


def _tum_lines(traj: Trajectory, extra: np.ndarray | None = None) -> list[str]:
    """One TUM line a pose, newline included; ``extra`` ``(N, K)``: K more numbers a line (``%.9g``)."""
    fmt = _TUM_LINE + " %.9g" * (0 if extra is None else extra.shape[1]) + "\n"
    rows = np.empty((len(traj.poses), 8 + (0 if extra is None else extra.shape[1])))
    rows[:, 0] = traj.timestamps
    rows[:, 1:4] = traj.poses[:, :3, 3]
    if len(rows):
        rows[:, 4:8] = [matrix_to_quat(T[:3, :3]) for T in traj.poses]
    if extra is not None:
        rows[:, 8:] = extra
    return [fmt % tuple(row) for row in rows.tolist()]


#: ``poses_cov.txt``: the 6x6 in the order (x, y, z, rx, ry, rz) of ROS ``PoseWithCovariance``;
#: GTSAM's tangent order is (rx, ry, rz, x, y, z), so entry ``i`` of the file is GTSAM's ``COV_ORDER[i]``
COV_ORDER = (3, 4, 5, 0, 1, 2)
_UPPER = np.triu_indices(6)


def write_tum_cov(path: str | Path, traj: Trajectory, covariances: np.ndarray) -> None:
    """Write ``poses_cov.txt``: per pose its TUM line (``t x y z qx qy qz qw``) and the 21
    upper-triangular entries, row by row, of its ``(6, 6)`` covariance in the pose's own frame
    (right perturbation ``T_true = T Exp(xi)``), in the order ``(x, y, z, rx, ry, rz)`` [m, rad;
    ``rx, ry, rz`` a rotation vector about the pose's own axes]: ``c_xx c_xy c_xz c_xrx c_xry c_xrz
    c_yy ... c_rzrz``. ``covariances``: ``(N, 6, 6)`` in GTSAM order ``(rx, ry, rz, x, y, z)``."""
    covs = np.asarray(covariances, dtype=np.float64)
    if covs.shape != (len(traj.poses), 6, 6):
        raise ValueError(f"{len(traj.poses)} poses but covariances of shape {covs.shape}")
    order = list(COV_ORDER)
    upper = covs[:, order][:, :, order][:, _UPPER[0], _UPPER[1]]  # (N, 21)
    header = ("# t x y z qx qy qz qw, then the upper triangle (21 entries, row by row) of the 6x6 pose covariance "
              "in the pose's own frame, order x y z rx ry rz [m, rad]\n")
    Path(path).write_text(header + "".join(_tum_lines(traj, upper)))


def read_tum_cov(path: str | Path) -> tuple[Trajectory, np.ndarray]:
    """Read ``poses_cov.txt`` (:func:`write_tum_cov`): the trajectory and ``(N, 6, 6)`` covariances
    in GTSAM order ``(rx, ry, rz, x, y, z)``, each in its pose's frame."""
    path = Path(path)
    rows = _rows(path, (29,))
    data = np.array([r for _, r in rows]).reshape(-1, 29)
    poses = poses_from_xyz_quats(data[:, 1:4], data[:, 4:8])
    covs = np.zeros((len(data), 6, 6))
    file_order = np.zeros((len(data), 6, 6))
    file_order[:, _UPPER[0], _UPPER[1]] = data[:, 8:]
    file_order[:, _UPPER[1], _UPPER[0]] = data[:, 8:]
    inv = np.argsort(COV_ORDER)
    covs[:] = file_order[:, inv][:, :, inv]
    return Trajectory(data[:, 0], poses), covs


def read_kitti(path: str | Path, timestamps: np.ndarray | None = None) -> Trajectory:
    """KITTI: 12 numbers per line (row-major 3x4); timestamps default to the line index."""
    path = Path(path)
    rows = _rows(path, (12,))
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = np.array([r for _, r in rows]).reshape(-1, 3, 4)
    stamps = np.arange(len(rows), dtype=np.float64) if timestamps is None else np.asarray(timestamps)
    if len(stamps) != len(poses):
        raise InputError(path, f"{len(poses)} poses but {len(stamps)} timestamps")
    return Trajectory(stamps, poses)


def write_kitti(path: str | Path, poses: np.ndarray) -> None:
    """Write ``(N, 4, 4)`` poses as KITTI lines (row-major 3x4)."""
    poses = np.asarray(poses).reshape(-1, 4, 4)
    fmt = " ".join(["%.9g"] * 12) + "\n"
    Path(path).write_text("".join(fmt % tuple(row) for row in poses[:, :3, :].reshape(-1, 12).tolist()) or "\n")


def _ranges_key(tokens: list[str]) -> bytes:
    """The range readings of a laser line as a hashable key (millimetres), for matching scans."""
    return np.round(np.asarray(tokens, dtype=np.float64) * 1000.0).astype(np.int64).tobytes()


def _carmen_flaser_rows(path: Path, with_ranges: bool = False) -> list[tuple]:
    """(ipc_timestamp, logger_timestamp, (x, y, theta)) of every FLASER line; of every
    ROBOTLASER1 line (its robot pose) in a log without FLASER lines. With ``with_ranges`` each row
    has a fourth item, the readings' :func:`_ranges_key` (None for ROBOTLASER1 rows)."""
    from .carmen import parse_robotlaser

    out, robotlaser = [], []
    with open_text(path) as fh:
        for lineno, line in enumerate(fh, start=1):
            tok = line.split()
            if not tok or tok[0] not in ("FLASER", "ROBOTLASER1"):
                continue
            if tok[0] == "ROBOTLASER1":
                if not out:  # FLASER lines win where both are present
                    reading = parse_robotlaser(tok, path, lineno)
                    try:
                        logger = float(tok[-1])
                    except ValueError:
                        raise InputError(path, "malformed ROBOTLASER1 logger timestamp", lineno) from None
                    robotlaser.append((reading.stamp, logger, reading.robot_pose) + ((None,) if with_ranges else ()))
                continue
            try:
                n = int(tok[1])
                pose = np.array(tok[2 + n : 5 + n], dtype=np.float64)
                ipc, logger = float(tok[8 + n]), float(tok[10 + n])
            except (ValueError, IndexError):
                raise InputError(path, "malformed or truncated FLASER line", lineno) from None
            if len(pose) != 3 or not (np.all(np.isfinite(pose)) and math.isfinite(ipc)):
                raise InputError(path, "malformed FLASER pose", lineno)
            row = (ipc, logger, pose)
            if with_ranges:
                try:
                    row += (_ranges_key(tok[2 : 2 + n]),)
                except ValueError:
                    raise InputError(path, "malformed FLASER ranges", lineno) from None
            out.append(row)
    if not out and not robotlaser:
        raise InputError(path, "no FLASER or ROBOTLASER1 lines: not a CARMEN laser log")
    return out or robotlaser


def read_carmen_trajectory(path: str | Path, timestamp: Literal["ipc", "logger"] = "ipc") -> Trajectory:
    """Poses of a CARMEN log's FLASER lines (``x y theta``; without FLASER lines the robot pose of
    its ROBOTLASER1 lines), stamped with ``ipc`` or ``logger`` time."""
    if timestamp not in ("ipc", "logger"):
        raise ConfigError(f"unknown CARMEN timestamp {timestamp!r}: use ipc or logger")
    rows = _carmen_flaser_rows(Path(path))
    col = 0 if timestamp == "ipc" else 1
    return Trajectory(np.array([r[col] for r in rows]), np.array([se2_to_matrix(*r[2]) for r in rows]))


def carmen_reference_trajectory(corrected_path: str | Path, raw_path: str | Path, tolerance: float = 0.01) -> Trajectory:
    """Corrected Freiburg log -> reference stamped with the *raw* log's ipc_timestamps.

    Each corrected FLASER line is matched to the raw FLASER line with identical range readings
    (all of Intel's and FR079's lines, 406 of MIT CSAIL's 407; when several raw lines share
    them, e.g. a robot standing still, the one nearest in logger time), else to the raw line with
    the nearest logger time within ``tolerance`` s (the corrected logs carry the raw
    logger_timestamp, rounded: the files differ by up to 5 ms, scans are ~100 ms apart; MIT
    CSAIL's prints its times with 6 significant digits, so time alone cannot match it). The
    reference takes the matched raw line's ipc_timestamp.
    """
    corrected = _carmen_flaser_rows(Path(corrected_path), with_ranges=True)
    raw = _carmen_flaser_rows(Path(raw_path), with_ranges=True)
    raw_logger = np.array([r[1] for r in raw])
    raw_ipc = np.array([r[0] for r in raw])
    order = np.argsort(raw_logger)
    sorted_logger = raw_logger[order]
    by_ranges: dict[bytes, list[int]] = {}
    for k, r in enumerate(raw):
        if r[3] is not None:
            by_ranges.setdefault(r[3], []).append(k)
    stamps, poses = [], []
    for _ipc, logger, pose, key in corrected:
        same = by_ranges.get(key, []) if key is not None else []
        if same:
            match = min(same, key=lambda j: abs(raw_logger[j] - logger))
        else:
            k = int(np.searchsorted(sorted_logger, logger))
            best = min((j for j in (k - 1, k) if 0 <= j < len(sorted_logger)),
                       key=lambda j: abs(sorted_logger[j] - logger))
            match = int(order[best]) if abs(sorted_logger[best] - logger) <= tolerance else None
        if match is not None:
            stamps.append(raw_ipc[match])
            poses.append(se2_to_matrix(*pose))
    if not stamps:
        raise InputError(corrected_path, f"no scan matched the raw log {raw_path} by identical ranges or by logger "
                         "timestamp")
    return Trajectory(np.array(stamps), np.array(poses))


def read_trajectory(path: str | Path, format: str | None = None) -> Trajectory:
    """Read TUM, KITTI or CARMEN (sniffed from the suffix and the column count)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such trajectory file")
    fmt = format or trajectory_format(path)
    if fmt == "tum":
        return read_tum(path)
    if fmt == "kitti":
        return read_kitti(path)
    if fmt == "carmen":
        return read_carmen_trajectory(path)
    raise InputError(path, "unknown trajectory format (expected TUM: 8 columns, KITTI: 12, or a CARMEN log)")


def trajectory_format(path: str | Path) -> str | None:
    """``"tum"``, ``"kitti"`` or ``"carmen"`` from the suffix and the first line's columns (None: unknown)."""
    path = Path(path)
    if base_suffix(path) in {".clf", ".log", ".carmen"}:
        return "carmen"
    with open_text(path) as fh:
        for line in fh:
            tok = line.split()
            if tok and not tok[0].startswith("#"):
                if tok[0] in ("FLASER", "ROBOTLASER1", "ODOM", "PARAM"):
                    return "carmen"
                return {8: "tum", 12: "kitti"}.get(len(tok))
    return None


def read_relations(path: str | Path) -> Relations:
    """Lines ``t_a t_b x y z roll pitch yaw`` (a leading non-numeric tag is allowed)."""
    from ..geometry import so3_exp

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such relations file")
    ta, tb, Ts = [], [], []
    with open_text(path) as fh:
        for lineno, line in enumerate(fh, start=1):
            tok = line.split()
            if not tok or tok[0].startswith("#"):
                continue
            if not _is_number(tok[0]):
                tok = tok[1:]
            if len(tok) != 8:
                raise InputError(path, f"expected 't_a t_b x y z roll pitch yaw', got {len(tok)} values", lineno)
            try:
                v = np.array(tok, dtype=np.float64)
            except ValueError:
                raise InputError(path, "non-numeric value", lineno) from None
            roll, pitch, yaw = v[5:8]
            R = so3_exp([0, 0, yaw]) @ so3_exp([0, pitch, 0]) @ so3_exp([roll, 0, 0])
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = v[2:5]
            ta.append(v[0])
            tb.append(v[1])
            Ts.append(T)
    if not Ts:
        raise InputError(path, "no relations in the file")
    return Relations(np.array(ta), np.array(tb), np.array(Ts))


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True
