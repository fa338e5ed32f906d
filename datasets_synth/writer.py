"""Generate a synthetic log folder that submapslam's readers load (and other tools can read).

Layout written by :func:`generate`::

    OUT/scans/000000.ply     binary little-endian PLY, float32 x y z time (sensor frame, time in [0, 1])
    OUT/times.txt            one timestamp per scan [s]
    OUT/odometry_tum.txt     wheel odometry T_odom_base per scan (TUM)
    OUT/groundtruth_tum.txt  ground truth T_world_base per scan (TUM)
    OUT/groundtruth_kitti.txt  the same, KITTI 3x4
    OUT/meta.yaml            world, seed, sensor, planar flag, loop and driven path length, noise, T_base_sensor
    OUT/landmarks_groundtruth.csv  worlds with poles: ``id,x,y`` of each pole centre (world frame)
    OUT/log.clf              2D lasers with a 180-degree field of view: the same data as CARMEN

The base frame is the sensor frame (T_base_sensor = identity); for 3D worlds the base moves
at the sensor's mount height.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np
import yaml

from submapslam.errors import SubmapSlamError
from submapslam.geometry import matrix_to_se2, se2_array_to_matrices
from submapslam.io.trajectory import Trajectory, write_kitti, write_tum

from .motion import OdometryNoise, loop_path, open_path, wheel_odometry
from .movers import MoverCaster, MoverTracks, door_tracks, indoor_movers
from .sensors import Laser2D, Lidar3D, LivoxLike, RayCaster, measure
from .worlds import WORLDS, World

log = logging.getLogger(__name__)

START_TIME = 1000.0
NO_RETURN = 81.91  # CARMEN/SICK convention for "no return"; readers drop readings >= 80 m


def write_ply_xyzt(path: Path, points: np.ndarray, times: np.ndarray) -> None:
    """Binary little-endian PLY with float32 ``x y z time`` vertices."""
    rec = np.zeros(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("time", "<f4")])
    rec["x"], rec["y"], rec["z"], rec["time"] = points[:, 0], points[:, 1], points[:, 2], times
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(rec)}\n"
        "property float x\nproperty float y\nproperty float z\nproperty float time\nend_header\n"
    )
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(rec.tobytes())


def write_labels(path: Path, classes: np.ndarray) -> None:
    """SemanticKITTI ``.label``: one little-endian uint32 per point, the class in the lower 16 bits."""
    np.asarray(classes, dtype="<u4").tofile(path)


def _carmen_lines(stamps, ranges_list, odom, max_range) -> list[str]:
    lines = ["# CARMEN log written by datasets_synth",
             "# FLASER num_readings [range_readings] x y theta odom_x odom_y odom_theta ipc_timestamp host logger_timestamp",
             "PARAM robot_frontlaser_offset 0.0 synth 0.000000"]
    xyt = matrix_to_se2(odom)
    for t, r, (x, y, th) in zip(stamps, ranges_list, xyt):
        rel = t - stamps[0]
        lines.append(f"ODOM {x:.6f} {y:.6f} {th:.6f} 0.0 0.0 0.0 {t:.6f} synth {rel:.6f}")
        rs = " ".join(f"{v:.3f}" for v in r)
        lines.append(f"FLASER {len(r)} {rs} {x:.6f} {y:.6f} {th:.6f} {x:.6f} {y:.6f} {th:.6f} {t:.6f} synth {rel:.6f}")
    return lines


def cast_scans(out: Path, caster: RayCaster, dev: Laser2D | Lidar3D | LivoxLike, T_world_sensor: np.ndarray,
               rng: np.random.Generator, *, keep_ranges: bool = False,
               progress: Callable[[int], None] | None = None, triangle_labels: np.ndarray | None = None,
               movers: MoverTracks | None = None) -> list[np.ndarray]:
    """Ray-cast ``dev`` from every pose ``(N, 4, 4)`` and write ``out/scans/NNNNNN.ply``.

    Points are in the sensor frame with a per-point sweep time in [0, 1] (a 2D laser: 0); the
    scans are not motion distorted. ``keep_ranges``: also return each scan's noisy ranges, with
    :data:`NO_RETURN` where a beam has no return (for the CARMEN copy); then the list holds
    ``(ranges, beam_labels)`` pairs when labels are written. ``progress(k)`` is called
    after every 100th scan and the last.

    ``triangle_labels`` ``(T,)``: the SemanticKITTI class of each triangle of the caster's mesh;
    given, every scan's per-point classes are written to ``out/labels/NNNNNN.label`` (uint32,
    the points' order). ``movers``: objects that move, cast scan by scan in front of the world.
    A :class:`LivoxLike` sensor casts its own pattern for every scan (the pattern's clock is the
    scan index).
    """
    (out / "scans").mkdir(parents=True, exist_ok=True)
    if triangle_labels is not None:
        (out / "labels").mkdir(parents=True, exist_ok=True)
    if isinstance(dev, Laser2D):
        dirs = dev.directions()
        times = np.zeros(len(dirs))
    elif isinstance(dev, LivoxLike):
        dirs, times = dev.directions_at(0)
    else:
        dirs, times = dev.directions()
    mover_caster = MoverCaster(movers, dev.max_range) if movers is not None and len(movers) else None
    kept = []
    for k, T in enumerate(T_world_sensor):
        if isinstance(dev, LivoxLike) and k:
            dirs, times = dev.directions_at(k)
        t_hit, prim = caster.cast(T, dirs)
        cls = None
        if triangle_labels is not None:
            cls = np.zeros(len(t_hit), dtype=np.uint32)
            hit = np.isfinite(t_hit)
            cls[hit] = triangle_labels[prim[hit]]
        if mover_caster is not None:
            t_mover, cls_mover = mover_caster.cast(k, T, dirs)
            closer = t_mover < t_hit
            t_hit = np.where(closer, t_mover, t_hit)
            if cls is not None:
                cls = np.where(closer, cls_mover, cls)
        r, valid = measure(t_hit, dev.max_range, dev.range_noise, dev.dropout, rng)
        write_ply_xyzt(out / "scans" / f"{k:06d}.ply", dirs[valid] * r[valid, None], times[valid])
        if cls is not None:
            cls[~valid] = 0
            write_labels(out / "labels" / f"{k:06d}.label", cls[valid])
        if keep_ranges:
            kept.append(np.where(valid, r, NO_RETURN) if cls is None else (np.where(valid, r, NO_RETURN), cls))
        if progress is not None and ((k + 1) % 100 == 0 or k + 1 == len(T_world_sensor)):
            progress(k + 1)
    return kept


def write_trajectories(out: Path, truth: np.ndarray, odom: np.ndarray, rate: float,
                       times: np.ndarray | None = None) -> np.ndarray:
    """``times.txt``, ``odometry_tum.txt``, ``groundtruth_tum.txt`` and ``groundtruth_kitti.txt``
    for ``truth`` ``T_world_base`` and ``odom`` ``T_odom_base`` ``(N, 4, 4)`` at ``rate`` Hz (or at
    ``times`` ``(N,)`` [s from the start] when given: irregular keyframes); returns the timestamps ``(N,)``."""
    stamps = START_TIME + (np.arange(len(truth)) / rate if times is None else np.asarray(times, dtype=np.float64))
    (out / "times.txt").write_text("".join(f"{t:.6f}\n" for t in stamps))
    write_tum(out / "odometry_tum.txt", Trajectory(stamps, odom))
    write_tum(out / "groundtruth_tum.txt", Trajectory(stamps, truth))
    write_kitti(out / "groundtruth_kitti.txt", truth)
    return stamps


def odometry_summary(truth: np.ndarray, odom: np.ndarray) -> dict:
    """Driven path length and wheel odometry's end drift [m], rounded for ``meta.yaml``."""
    end_drift = float(np.linalg.norm(odom[-1][:2, 3] - (np.linalg.inv(truth[0]) @ truth[-1])[:2, 3]))
    length = float(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1).sum())  # 3D: terrain climbs
    return {"path_length_m": round(length, 3), "odometry_end_drift_m": round(end_drift, 3)}


def write_meta(out: Path, meta: dict) -> None:
    (out / "meta.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))


def write_landmarks(out: Path, cylinders: np.ndarray | None) -> None:
    """``landmarks_groundtruth.csv`` (``id,x,y`` of each pole centre, world frame), when there are poles."""
    if cylinders is not None and len(cylinders):
        rows = "".join(f"{k},{x:.4f},{y:.4f}\n" for k, (x, y) in enumerate(np.asarray(cylinders)[:, :2]))
        (out / "landmarks_groundtruth.csv").write_text("id,x,y\n" + rows)


def generate(world: str, out_dir: str | Path, *, seed: int = 0, laps: int = 2, sensor: str | None = None,
             speed: float | None = None, rate: float = 10.0, odometry_noise: float = 1.0,
             max_scans: int | None = None, sensor_options: dict | None = None, movers: int = 0,
             doors: int = 0, progress: Callable[[int, int], None] | None = None, **world_options) -> Path:
    """Write a synthetic log of ``world`` into ``out_dir``; returns ``out_dir``.

    Args:
        world: a name in :data:`WORLDS`.
        seed: seeds the world layout, sensor noise and odometry noise (same seed, same files).
        laps: laps around the loop (a world with an open path, e.g. ``aliased``, is driven once).
        sensor: ``"laser2d"`` or ``"lidar3d"`` (default: the world's own).
        speed: [m/s] (default 1.0 indoors, 8.0 outdoors); ``rate``: scans per second.
        odometry_noise: multiplies the default :class:`OdometryNoise` (0 = perfect odometry).
        progress: called as ``progress(done, total)`` while the scans are cast.
        max_scans: cut the log after this many scans (small test logs).
        sensor_options: overrides of :class:`Laser2D` / :class:`Lidar3D` fields (e.g. max_range).
        movers: planar worlds: people walking the hallways (some standing, then leaving) and
            boxes moved halfway through the log (:func:`datasets_synth.movers.indoor_movers`).
            Every scan's per-point SemanticKITTI classes go to ``labels/NNNNNN.label`` (254 person,
            259 moved box, 50 walls and pillars); the CARMEN copy gets ``log.clf.labels``.
        doors: worlds with doorways (``rooms``): doors in that many of them that open and
            close during the log (:func:`datasets_synth.movers.door_tracks`; their leaves are
            labelled 259 when they change state), drawn from their own random stream, so the
            rest of the log is the same with and without doors.
        world_options: passed to the world builder (e.g. size, feature_density).
    """
    if world not in WORLDS:
        raise SubmapSlamError(f"unknown world {world!r}; known worlds: {', '.join(WORLDS)}")
    builder, default_sensor, _ = WORLDS[world]
    sensor = sensor or default_sensor
    if sensor not in ("laser2d", "lidar3d"):
        raise SubmapSlamError(f"unknown sensor {sensor!r}; use laser2d or lidar3d")
    try:
        w: World = builder(seed=seed, **world_options)
    except TypeError as exc:
        raise SubmapSlamError(f"world {world!r} does not take these options: {exc}") from None
    rng = np.random.default_rng(seed + 7919)
    speed = speed or (1.0 if w.planar else 8.0)
    if w.closed:
        truth_xyt = loop_path(w.waypoints, laps, speed / rate, w.corner_radius)
    else:
        truth_xyt = open_path(w.waypoints, speed / rate, w.corner_radius)
        laps = 1
    if max_scans is not None:
        truth_xyt = truth_xyt[:max_scans]
    noise = OdometryNoise().scaled(odometry_noise)
    odom = wheel_odometry(truth_xyt, noise, rng)
    try:
        dev = (Laser2D if sensor == "laser2d" else Lidar3D)(**(sensor_options or {}))
    except TypeError as exc:
        raise SubmapSlamError(f"bad sensor option: {exc}") from None
    truth = se2_array_to_matrices(truth_xyt)
    truth[:, 2, 3] = dev.mount_height if not w.planar else 0.0
    T_cast = truth.copy()
    if sensor == "laser2d" or w.planar:
        T_cast[:, 2, 3] = dev.mount_height
    out = Path(out_dir)
    tracks = None
    if movers:
        if not w.planar:
            raise SubmapSlamError("movers are built for the planar worlds (rectangle, rooms, figure8) and synth kitti")
        tracks = indoor_movers(truth_xyt, rate, movers, np.random.default_rng([seed, 3131]))
    if doors:
        if not len(w.doorways):
            raise SubmapSlamError(f"world {world!r} has no doorways for doors (rooms has)")
        door = door_tracks(w.doorways, len(truth_xyt), rate, doors, np.random.default_rng([seed, 6007]))
        tracks = door if tracks is None else MoverTracks.concat([tracks, door])
    mesh, triangle_labels = w.labelled_mesh()
    total = len(T_cast)
    cast = cast_scans(out, RayCaster(mesh), dev, T_cast, rng, keep_ranges=sensor == "laser2d",
                      triangle_labels=triangle_labels, movers=tracks,
                      progress=None if progress is None else (lambda k: progress(k, total)))
    carmen_ranges = [r for r, _ in cast]
    stamps = write_trajectories(out, truth, odom, rate)
    summary = odometry_summary(truth, odom)
    write_meta(out, {
        "world": world, "description": w.description, "seed": seed, "laps": laps,
        "sensor": {"type": sensor, **asdict(dev)}, "planar": sensor == "laser2d", "motion_distorted": False,
        "n_scans": int(len(truth)), "rate_hz": rate, "speed_mps": speed,
        "loop_length_m": round(w.loop_length(), 3), "odometry_noise": asdict(noise),
        "odometry_end_drift_m": summary["odometry_end_drift_m"], "T_base_sensor": np.eye(4).tolist(),
        "path_length_m": summary["path_length_m"],
        "movers": tracks.counts() if tracks is not None else {},
    })
    write_landmarks(out, w.cylinders)
    if sensor == "laser2d" and abs(dev.fov_deg - 180.0) < 1e-9:
        (out / "log.clf").write_text("\n".join(_carmen_lines(stamps, carmen_ranges, odom, dev.max_range)) + "\n")
        (out / "log.clf.labels").write_text(
            "# one line per FLASER line of log.clf: num_readings, then the SemanticKITTI class of each beam "
            "(0: no return; 254 person, 259 moved object or a door that opens and closes; 50 wall)\n"
            + "".join(f"{len(c)} {' '.join(map(str, c.tolist()))}\n" for _, c in cast))
    log.info("wrote %d scans of %s to %s", len(truth), world, out)
    return out
