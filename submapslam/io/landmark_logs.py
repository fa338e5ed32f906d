"""Landmark logs for the stochastic-map reference: UTIAS MR.CLAM, Victoria Park, synthetic.

Every reader returns the core type :class:`~submapslam.landmark_log.LandmarkLog` (re-exported
here with :class:`~submapslam.landmark_log.Step`): a time-ordered list of steps, each a motion
``(dx, dy, dtheta)`` in the robot frame with its covariance followed by the range-bearing
observations made at the step's end (with known landmark ids when the log gives them).
"""

from __future__ import annotations

import lzma
import math
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..landmark_log import LandmarkLog, Step
from .compression import open_text

__all__ = ["LandmarkLog", "Step", "read_cloud_pole_log", "read_landmark_log", "read_mrclam", "read_victoria_park"]


def _numeric_table(path: Path, ncols: int) -> np.ndarray:
    rows = []
    lineno = 0
    try:
        with open_text(path) as fh:
            for lineno, line in enumerate(fh, start=1):
                body = line.strip()
                if not body or body.startswith("#"):
                    continue
                tok = body.split()
                if len(tok) < ncols:
                    raise InputError(path, f"expected {ncols} columns, got {len(tok)}", lineno)
                try:
                    rows.append([float(v) for v in tok[:ncols]])
                except ValueError:
                    raise InputError(path, f"non-numeric value in {body[:40]!r}", lineno) from None
                if not all(math.isfinite(v) for v in rows[-1]):
                    raise InputError(path, f"NaN/inf value in {body[:40]!r}", lineno)
    except (lzma.LZMAError, EOFError, OSError) as exc:
        raise InputError(path, f"cannot read past line {lineno} ({exc}); truncated or corrupt?") from None
    if not rows:
        raise InputError(path, "no data rows")
    return np.array(rows)


def _find(folder: Path, name: str) -> Path:
    for cand in (folder / name, folder / (name + ".xz")):
        if cand.is_file():
            return cand
    raise InputError(folder / name, "missing (plain or .xz)")


def _unicycle(v: float, w: float, dt: float) -> np.ndarray:
    dth = w * dt
    if abs(w) > 1e-9:
        r = v / w
        return np.array([r * np.sin(dth), r * (1 - np.cos(dth)), dth])
    return np.array([v * dt, 0.0, 0.0])


# The robots' camera: measurements reach +-33 deg and 7.5 m (robot 1, dataset 7). Landmarks
# predicted inside +-30 deg and 6.5 m count as unobserved when missed; at the very edge of the
# view the barcode detector misses them too often for a miss to say anything.
MRCLAM_FOV = np.deg2rad(60.0)
MRCLAM_MAX_RANGE = 6.5


def read_mrclam(folder: str | Path, robot: int = 1, sigma_v: float = 0.05, sigma_w: float = 0.1,
                sigma_range: float = 0.15, sigma_bearing: float = 0.05) -> LandmarkLog:
    """UTIAS MR.CLAM dataset folder: odometry (v, w), range-bearing to barcoded landmarks.

    Measurements of barcodes belonging to robots (subjects 1-5) are ignored; landmark ids are
    subject numbers. The log starts at the first ground-truth pose (the filter then estimates
    in the ground-truth frame). Odometry is integrated between measurement times into one step.
    """
    folder = Path(folder)
    odo = _numeric_table(_find(folder, f"Robot{robot}_Odometry.dat"), 3)
    meas = _numeric_table(_find(folder, f"Robot{robot}_Measurement.dat"), 4)
    gt = _numeric_table(_find(folder, f"Robot{robot}_Groundtruth.dat"), 4)
    barcodes = _numeric_table(_find(folder, "Barcodes.dat"), 2)
    lm_gt = _numeric_table(_find(folder, "Landmark_Groundtruth.dat"), 3)
    subject_of = {int(b): int(s) for s, b in barcodes}
    # start where both ground truth and odometry exist, at the ground-truth pose of that time
    t0 = max(gt[0, 0], odo[0, 0])
    k0 = int(np.searchsorted(gt[:, 0], t0))
    gt = gt[k0:]
    t0 = gt[0, 0]
    odo = odo[odo[:, 0] >= t0 - 1.0]
    meas = meas[meas[:, 0] >= t0]
    steps: list[Step] = []
    Q_vw = np.diag([sigma_v**2, sigma_w**2])
    # group measurements by timestamp
    times = np.unique(meas[:, 0])
    oi = 0
    last_t = t0
    v = w = 0.0
    prev = odo[odo[:, 0] <= t0]
    if len(prev):
        v, w = prev[-1, 1], prev[-1, 2]
    odo = odo[odo[:, 0] > t0]
    for t in times:
        motion = np.zeros(3)
        cov = np.zeros((3, 3))
        # integrate odometry commands up to t, composing increments in the robot frame
        while True:
            t_next = odo[oi, 0] if oi < len(odo) else np.inf
            t_end = min(t_next, t)
            dt = t_end - last_t
            if dt > 0:
                u = _unicycle(v, w, dt)
                c, s = np.cos(motion[2]), np.sin(motion[2])
                F = np.array([[1, 0, -s * u[0] - c * u[1]], [0, 1, c * u[0] - s * u[1]], [0, 0, 1]])
                G = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
                # white velocity noise: variance grows linearly with time (sigma^2 per second)
                Qu = np.diag([Q_vw[0, 0] * dt, 0.1 * Q_vw[0, 0] * dt, Q_vw[1, 1] * dt])
                cov = F @ cov @ F.T + G @ Qu @ G.T
                motion = np.array([motion[0] + c * u[0] - s * u[1], motion[1] + s * u[0] + c * u[1], motion[2] + u[2]])
                last_t = t_end
            if t_next <= t:
                v, w = odo[oi, 1], odo[oi, 2]
                oi += 1
            else:
                break
        rows = meas[meas[:, 0] == t]
        keep = [(r, b, subject_of.get(int(code), -1)) for _, code, r, b in rows]
        keep = [(r, b, s) for r, b, s in keep if s > 5]
        rb = np.array([(r, b) for r, b, _ in keep]).reshape(-1, 2)
        steps.append(Step(float(t), motion, cov + np.eye(3) * 1e-12, rb, [s for _, _, s in keep]))
    return LandmarkLog(
        name=f"MR.CLAM robot {robot}", initial_pose=gt[0, 1:4].copy(), steps=steps,
        measurement_cov=np.diag([sigma_range**2, sigma_bearing**2]), truth_times=gt[:, 0], truth_poses=gt[:, 1:4],
        truth_landmarks={int(s): np.array([x, y]) for s, x, y in lm_gt},
        max_range=MRCLAM_MAX_RANGE, fov=MRCLAM_FOV,
    )


def read_victoria_park(path: str | Path) -> LandmarkLog:
    """gtsam's ``victoria_park.txt``: ODOMETRY i j dx dy dth + covariance, LANDMARK i l lx ly + covariance.

    Landmark positions in the robot frame become range-bearing as gtsam's loader does
    (bearing sigma sqrt(v1/10), range sigma sqrt(v1)).
    """
    path = Path(path)
    steps: dict[int, Step] = {}
    sig_r2 = sig_b2 = None
    try:
        with open_text(path) as fh:
            for lineno, line in enumerate(fh, start=1):
                tok = line.split()
                if not tok:
                    continue
                try:
                    if tok[0] == "ODOMETRY":
                        j = int(tok[2])
                        dx, dy, dth, c11, c12, c13, c22, c23, c33 = map(float, tok[3:12])
                        cov = np.array([[c11, c12, c13], [c12, c22, c23], [c13, c23, c33]])
                        if not (np.isfinite([dx, dy, dth]).all() and np.isfinite(cov).all()):
                            raise ValueError("NaN/inf motion or covariance")
                        if np.linalg.eigvalsh(cov).min() < -1e-12:
                            raise ValueError("the motion covariance is not positive semi-definite")
                        steps[j] = Step(float(j), np.array([dx, dy, dth]), cov, np.zeros((0, 2)), [])
                    elif tok[0] == "LANDMARK":
                        i, lid = int(tok[1]), int(tok[2])
                        lx, ly, v1 = float(tok[3]), float(tok[4]), float(tok[5])
                        if not (np.isfinite([lx, ly, v1]).all() and v1 >= 0):
                            raise ValueError("NaN/inf landmark or a negative variance")
                        step = steps.setdefault(i, Step(float(i), np.zeros(3), np.eye(3) * 1e-12, np.zeros((0, 2)), []))
                        step.ranges_bearings = np.vstack([step.ranges_bearings, [np.hypot(lx, ly), np.arctan2(ly, lx)]])
                        step.ids.append(lid)
                        sig_r2, sig_b2 = v1, v1 / 10.0
                    else:
                        raise ValueError(f"unknown record {tok[0][:20]!r}")
                except (ValueError, IndexError) as exc:
                    raise InputError(path, f"malformed line ({exc})", lineno) from None
    except (lzma.LZMAError, EOFError) as exc:
        raise InputError(path, f"cannot decompress ({exc})") from None
    if not steps:
        raise InputError(path, "no ODOMETRY/LANDMARK lines")
    ordered = [steps[k] for k in sorted(steps)]
    R = np.diag([sig_r2 or 0.1, sig_b2 or 0.01])
    return LandmarkLog("Victoria Park", np.zeros(3), ordered, R)


def read_cloud_pole_log(path: str | Path, sigma_range: float = 0.05, sigma_bearing: float = 0.02,
                        odometry_sigma: tuple[float, float, float] = (0.05, 0.02, 0.03)) -> LandmarkLog:
    """A point-cloud log folder (scans + ``odometry_tum.txt``) -> a LandmarkLog of pole observations.

    The files are read here and handed to :func:`~submapslam.ekf.features.landmark_log_from_scans`:
    the scans and wheel odometry (the folder reader), the laser's field of view (``sensor:
    fov_deg`` in the reader's meta.yaml), ``groundtruth_tum.txt`` and
    ``landmarks_groundtruth.csv`` (``id,x,y``, world frame) when present.
    """
    from ..ekf.features import landmark_log_from_scans
    from .registry import open_log
    from .trajectory import read_tum

    path = Path(path)
    reader = open_log(path, "cloud_folder")
    if reader.odometry is None:
        raise InputError(path, "the log has no odometry_tum.txt: the EKF needs odometry")
    sensor = reader.meta.get("sensor") or {}
    fov_deg = sensor.get("fov_deg", 360.0) if isinstance(sensor, dict) else None
    if not isinstance(fov_deg, int | float):
        raise InputError(path / "meta.yaml", f"sensor.fov_deg must be a number of degrees, got {fov_deg!r}")
    gt_file = path / "groundtruth_tum.txt"
    truth = read_tum(gt_file) if gt_file.is_file() else None
    return landmark_log_from_scans(reader, f"poles from {path.name}", fov_deg=fov_deg, truth=truth,
                                   truth_landmarks=_truth_poles(path / "landmarks_groundtruth.csv"),
                                   sigma_range=sigma_range, sigma_bearing=sigma_bearing, odometry_sigma=odometry_sigma)


def _truth_poles(path: Path) -> dict[int, np.ndarray]:
    """``landmarks_groundtruth.csv`` (``id,x,y``, world frame) written by the synthetic generator, if any."""
    if not path.is_file():
        return {}
    out = {}
    for lineno, line in enumerate(path.read_text().splitlines()[1:], start=2):
        try:
            k, x, y = line.split(",")[:3]
            out[int(k)] = np.array([float(x), float(y)])
        except ValueError:
            raise InputError(path, f"expected id,x,y, got {line[:40]!r}", lineno) from None
    return out


LANDMARK_FORMATS = ("an MR.CLAM folder (RobotN_Odometry.dat, RobotN_Measurement.dat), a victoria_park-format "
                    "file (ODOMETRY/LANDMARK lines; `synth landmarks --out DIR` writes DIR/landmarks.txt), "
                    "or a point-cloud log folder with scans/ and odometry_tum.txt")
"""What ``ekf`` reads, in words for the error lines."""


def sniff_landmark_log(path: Path, robot: int = 1) -> tuple[Path, str]:
    """``(the file or folder to read, its format)`` for an existing ``path``; a path that is none of
    :data:`LANDMARK_FORMATS` (a CARMEN laser log, an empty folder) is an :class:`InputError`
    naming the formats. A folder holding ``landmarks.txt`` (``synth landmarks``) reads that file."""
    if path.is_dir():
        if (path / "scans").is_dir():
            return path, "cloud"
        if any(path.glob("Robot*_Odometry.dat*")):
            return path, "mrclam"
        if (path / "landmarks.txt").is_file():
            return path / "landmarks.txt", "synth"
        raise InputError(path, f"is not a landmark log; ekf reads {LANDMARK_FORMATS}")
    first = ""
    try:
        with open_text(path) as fh:
            for _ in range(50):
                line = fh.readline()
                if not line:
                    break
                if line.strip() and not line.lstrip().startswith("#"):
                    first = line.split()[0]
                    break
    except (OSError, EOFError, lzma.LZMAError, ValueError):
        return path, "victoria"  # the reading proper reports it
    if first in ("ODOMETRY", "LANDMARK") or not first:
        return path, "victoria"
    from .registry import open_log

    try:
        kind = open_log(path).name
    except InputError:
        kind = None
    what = f"a {kind} log (read it with `submapslam run`)" if kind else f"not a landmark log (it starts {first[:20]!r})"
    raise InputError(path, f"is {what}; ekf reads {LANDMARK_FORMATS}")


def read_landmark_log(path: str | Path, format: str | None = None, robot: int = 1) -> LandmarkLog:
    """Read a landmark log: ``mrclam`` (a folder), ``victoria`` or ``synth`` (a victoria_park-format
    file), ``cloud`` (a point-cloud log folder: pole features, unknown association).

    ``format=None`` sniffs: a folder with ``scans/`` is ``cloud``, another folder ``mrclam``, a
    file ``victoria``. ``robot`` is the MR.CLAM robot number.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file or directory")
    if format is None:
        path, format = sniff_landmark_log(path, robot)
    if format == "mrclam":
        return read_mrclam(path, robot)
    if format in ("victoria", "synth"):
        return with_synthetic_truth(read_victoria_park(path), path)
    if format == "cloud":
        return read_cloud_pole_log(path)
    raise InputError(path, f"unknown landmark log format {format!r}; use mrclam, victoria, synth or cloud")


def with_synthetic_truth(log: LandmarkLog, path: str | Path) -> LandmarkLog:
    """``log`` with the ground truth that ``datasets_synth.landmarks`` writes beside ``path``
    (``poses_truth.txt``: ``k x y theta``; ``landmarks_truth.csv``: ``id,x,y[,vanishes,appears,
    first_step,end_step]``), moved into the log's frame (the log starts at the origin, the truth at
    its first pose), and the sensor range of ``landmarks_meta.yaml`` (``max_range_m``) as the
    log's ``max_range``; ``log`` unchanged when either truth file is missing."""
    from dataclasses import replace

    folder = Path(path).parent
    poses_file, lm_file = folder / "poses_truth.txt", folder / "landmarks_truth.csv"
    if not (poses_file.is_file() and lm_file.is_file()):
        return log
    try:
        raw = np.loadtxt(poses_file, ndmin=2)
        if raw.shape[1] != 4 or not np.isfinite(raw).all():
            raise ValueError("expected 4 finite numbers per line: k x y theta")
    except ValueError as exc:
        raise InputError(poses_file, str(exc)) from None
    lines = lm_file.read_text().splitlines()
    header = lines[0].split(",") if lines else []
    if header[:3] != ["id", "x", "y"]:
        raise InputError(lm_file, f"expected a header starting id,x,y, got {lines[0][:60] if lines else ''!r}", 1)
    lifetime_cols = ("first_step" in header and "end_step" in header)
    c, s = np.cos(raw[0, 3]), np.sin(raw[0, 3])
    Rt = np.array([[c, s], [-s, c]])  # world -> log frame rotation

    def to_log(xy: np.ndarray) -> np.ndarray:
        return Rt @ (np.asarray(xy, dtype=np.float64) - raw[0, 1:3])

    landmarks, lifetimes = {}, {}
    for lineno, line in enumerate(lines[1:], start=2):
        tok = line.split(",")
        try:
            lid = int(tok[0])
            landmarks[lid] = to_log([float(tok[1]), float(tok[2])])
            if lifetime_cols:
                lifetimes[lid] = (float(tok[header.index("first_step")]), float(tok[header.index("end_step")]))
        except (ValueError, IndexError):
            raise InputError(lm_file, f"expected {','.join(header)}, got {line[:60]!r}", lineno) from None
    poses = np.column_stack([(raw[:, 1:3] - raw[0, 1:3]) @ Rt.T, np.unwrap(raw[:, 3]) - raw[0, 3]])
    max_range = log.max_range
    meta_file = folder / "landmarks_meta.yaml"
    if meta_file.is_file():
        import yaml

        try:
            meta = yaml.safe_load(meta_file.read_text()) or {}
            max_range = float(meta.get("max_range_m", max_range))
        except (yaml.YAMLError, AttributeError, TypeError, ValueError) as exc:
            raise InputError(meta_file, f"expected a mapping with max_range_m ({str(exc)[:80]})") from None
    return replace(log, name=f"synthetic landmarks {Path(path).name}", truth_times=raw[:, 0], truth_poses=poses,
                   truth_landmarks=landmarks, truth_lifetimes=lifetimes, max_range=max_range)
