"""A city around a real vehicle path: KITTI odometry ground truth, ray-cast with a Velodyne.

:func:`generate_kitti_drive` reads a KITTI pose file (12 numbers per line, row-major 3x4
``T_world_camera`` in the camera frame: x right, y down, z forward; 10 Hz), flattens it into a
planar vehicle path (world x = camera z, world y = -camera x, yaw = the camera's forward axis
in that plane; the elevation is dropped), builds streets around every part of the path
(:mod:`datasets_synth.streets`), and writes the same log folder as :func:`datasets_synth.generate`.

With ``terrain=True`` the elevation is kept: the ground follows the path's real height (world
z = camera -y; :class:`datasets_synth.terrain.PathTerrain` interpolates it smoothly off the
path), everything stands on the local ground and the vehicle takes the road's pitch and roll.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np

from submapslam.errors import InputError, SubmapSlamError
from submapslam.geometry import se2_array_to_matrices
from submapslam.io.trajectory import read_kitti

from .motion import OdometryNoise, wheel_odometry
from .movers import city_movers
from .sensors import LIDAR_PRESETS, Lidar3D, LivoxLike, RayCaster
from .streets import StreetBuilder, StreetStyle, building_templates
from .terrain import PathTerrain, keyframe_schedule, lift_odometry, terrain_poses
from .worlds import World
from .writer import cast_scans, odometry_summary, write_landmarks, write_meta, write_trajectories

log = logging.getLogger(__name__)

KITTI_RATE_HZ = 10.0
TERRAIN_RADIUS = 90.0  # [m] ground is modelled this far from the path (bounds the mesh)
CITY_MARGIN = 60.0  # [m] around the path's bounding box: room for buildings and parks


def read_kitti_path(path_file: str | Path) -> np.ndarray:
    """Planar vehicle path ``(N, 3)`` ``(x, y, yaw)`` from a KITTI pose file (plain or .xz/.gz/.bz2).

    World x = camera z (forward), world y = -camera x (left), yaw = heading of the camera's
    z axis in that plane (unwrapped). Raises :class:`InputError` naming the file (and the line)
    when it is missing, malformed or holds fewer than two poses.
    """
    path = Path(path_file)
    if not path.is_file():
        raise InputError(path, "no such KITTI pose file")
    traj = read_kitti(path)
    if len(traj) < 2:
        raise InputError(path, "a drive needs at least 2 poses")
    R = traj.poses[:, :3, :3]
    bad = np.flatnonzero(np.abs(np.linalg.det(R) - 1.0) > 0.05)
    if len(bad):
        raise InputError(path, "the 3x3 part is not a rotation (12 numbers per line: row-major 3x4 T_world_camera)",
                         int(bad[0]) + 1)
    t = traj.poses[:, :3, 3]
    yaw = np.unwrap(np.arctan2(-R[:, 0, 2], R[:, 2, 2]))
    return np.stack([t[:, 2], -t[:, 0], yaw], axis=1)


def read_kitti_height(path_file: str | Path) -> np.ndarray:
    """Height ``(N,)`` [m] of each KITTI pose above the first: camera -y (the camera's y axis points
    down; KITTI's world frame is the first camera's). The file is checked as :func:`read_kitti_path` does."""
    read_kitti_path(path_file)
    return -read_kitti(Path(path_file)).poses[:, 1, 3]


def kitti_city(path_xyt: np.ndarray, *, seed: int = 0, repeated_buildings: bool = True, templates: int = 5,
               style: StreetStyle = StreetStyle(), terrain: PathTerrain | None = None) -> World:
    """A city along the planar path ``(N, 3)``: streets lined with buildings, parked cars, poles and
    trees; the road corridor (``style.road_half_width``) around every path point is kept free.

    ``repeated_buildings``: buildings come from a catalogue of ``templates`` footprints and heights
    (streets alias, as real ones do); otherwise every building is drawn on its own. ``terrain``:
    the ground's height (everything stands on it); None: flat.
    """
    xy = np.asarray(path_xyt, dtype=np.float64)[:, :2]
    lo, hi = xy.min(axis=0) - CITY_MARGIN, xy.max(axis=0) + CITY_MARGIN
    rng = np.random.default_rng([seed, 4201])
    catalogue = building_templates(rng, templates, style) if repeated_buildings else None
    builder = StreetBuilder(xy, (lo[0], lo[1], hi[0], hi[1]), rng, style)
    builder.street(xy, catalogue)
    boxes, labels, cylinders = builder.parts()
    desc = (f"city along a real vehicle path: {int((labels == 'building').sum())} buildings "
            f"({'from ' + str(templates) + ' templates' if repeated_buildings else 'all different'}), "
            f"{int((labels == 'car').sum())} parked cars, {len(cylinders)} poles and trees (3D)")
    return World("kitti_city", False, xy, (lo[0], lo[1], hi[0], hi[1]), cylinders=cylinders, ground=True,
                 oriented_boxes=boxes, box_labels=labels, closed=False, terrain_radius=TERRAIN_RADIUS,
                 description=desc + (" on terrain" if terrain is not None else ""),
                 ground_height=None if terrain is None else terrain.height)


SENSORS = ("livox",)  # besides the ring counts of LIDAR_PRESETS


def generate_kitti_drive(path_file: str | Path, out_dir: str | Path, *, rings: int | str = 16, seed: int = 0,
                         max_scans: int | None = None, odometry_noise: float = 1.0, repeated_buildings: bool = True,
                         movers: int = 0, progress: Callable[[int, int], None] | None = None,
                         terrain: bool = False, keyframes: bool = False) -> Path:
    """Drive a KITTI ground-truth path through a synthetic city and write the log; returns ``out_dir``.

    The folder is the one :func:`datasets_synth.generate` writes: ``scans/NNNNNN.ply`` (float32
    x y z time, sensor frame, time in [0, 1], not motion distorted), ``times.txt`` (10 Hz, the
    KITTI rate), ``odometry_tum.txt`` (wheel odometry), ``groundtruth_tum.txt``,
    ``groundtruth_kitti.txt`` (``T_world_base``, base = sensor at 1.73 m over flat ground),
    ``landmarks_groundtruth.csv`` (poles and tree trunks) and ``meta.yaml``.

    Args:
        path_file: KITTI pose file (``NN.txt`` or ``NN.txt.xz``).
        rings: 16 (VLP-16 like: -15..+15 deg, 100 m, 4 cm noise), 64 (HDL-64E like: -24.8..+2 deg,
            120 m, 2 cm noise), both 1800 columns, 128 (OS1-128 like: +-22.5 deg, 1024 columns), or
            ``"livox"``: a forward-looking 70 x 77 deg non-repetitive rosette (:class:`LivoxLike`).
        seed: seeds the city, sensor noise and odometry noise (same seed, same files).
        max_scans: drive only the first N poses (the city is built along those only).
        odometry_noise: multiplies the default :class:`OdometryNoise` (0 = perfect odometry).
        repeated_buildings: buildings from a small catalogue of templates (streets alias).
        movers: cars driving both ways, pedestrians and parked cars that leave
            (:func:`datasets_synth.movers.city_movers`); every scan's per-point SemanticKITTI
            classes are written to ``labels/NNNNNN.label`` (with or without movers).
        progress: called as ``progress(done, total)`` while scans are written.
        terrain: the ground follows the KITTI path's real height (its poses' camera -y), smoothly
            interpolated off the path; buildings, cars, poles and trees stand on the local ground;
            the vehicle takes the road's pitch and roll (ground truth is then fully 3D, and the
            wheel odometry's error is applied to the true 3D steps). Not with ``movers``.
        keyframes: write irregular keyframes instead of every 10 Hz pose: 0.2-0.5 s apart, with
            stops where the vehicle stands still for 6-13 s (a few scans of one pose; the clock
            runs on). ``times.txt`` holds the keyframes' times; the scans are the keyframes'.
    """
    if rings not in LIDAR_PRESETS and rings not in SENSORS:
        raise SubmapSlamError(f"rings must be {', '.join(map(str, LIDAR_PRESETS))} or livox, not {rings}")
    if max_scans is not None and max_scans < 2:
        raise SubmapSlamError(f"max_scans must be at least 2, not {max_scans}")
    if odometry_noise < 0:
        raise SubmapSlamError(f"odometry_noise must be >= 0, not {odometry_noise}")
    if movers < 0:
        raise SubmapSlamError(f"movers must be >= 0, not {movers}")
    path_xyt = read_kitti_path(path_file)
    ground = None
    if terrain:
        ground = PathTerrain(np.column_stack([path_xyt[:, :2], read_kitti_height(path_file)]))
    if max_scans is not None:
        path_xyt = path_xyt[:max_scans]
    world = kitti_city(path_xyt, seed=seed, repeated_buildings=repeated_buildings, terrain=ground)
    dev = LivoxLike() if rings == "livox" else Lidar3D.preset(int(rings))
    rng = np.random.default_rng(seed + 7919)
    noise = OdometryNoise().scaled(odometry_noise)
    odom = wheel_odometry(path_xyt, noise, rng)
    truth = se2_array_to_matrices(path_xyt)
    truth[:, 2, 3] = dev.mount_height
    if ground is not None:
        flat = truth.copy()
        flat[:, 2, 3] = 0.0
        truth = terrain_poses(path_xyt, ground, dev.mount_height)
        odom = lift_odometry(odom, flat, truth)
    times = None
    if keyframes:
        index, times = keyframe_schedule(len(truth), KITTI_RATE_HZ, np.random.default_rng([seed, 8111]))
        truth, odom = truth[index], odom[index]
    out = Path(out_dir)
    tracks = None
    if movers:
        parked = np.flatnonzero(world.box_labels == "car")
        tracks, left = city_movers(path_xyt, KITTI_RATE_HZ, movers, np.random.default_rng([seed, 2525]),
                                   world.oriented_boxes[parked])
        tracks.ground_height = None if ground is None else ground.height  # movers stand on the terrain
        stay = np.ones(len(world.oriented_boxes), dtype=bool)
        stay[parked[left]] = False
        world.oriented_boxes, world.box_labels = world.oriented_boxes[stay], world.box_labels[stay]
    mesh, triangle_labels = world.labelled_mesh()
    caster = RayCaster(mesh)
    total = len(truth)
    cast_scans(out, caster, dev, truth, rng, progress=None if progress is None else (lambda k: progress(k, total)),
               triangle_labels=triangle_labels, movers=tracks)
    write_trajectories(out, truth, odom, KITTI_RATE_HZ, times)
    summary = odometry_summary(truth, odom)
    labels = world.box_labels
    duration = (total - 1) / KITTI_RATE_HZ if times is None else float(times[-1] - times[0])
    extra = {}
    if terrain:
        z = truth[:, 2, 3]
        extra["terrain"] = {"relief_m": round(float(z.max() - z.min()), 3), "sigma_along_m": ground.sigma,
                            "sigma_across_m": ground.sigma_across}
    if keyframes:
        gaps = np.diff(times)
        extra["keyframes"] = {"median_gap_s": round(float(np.median(gaps)), 3), "max_gap_s": round(float(gaps.max()), 3),
                              "still_scans": int((np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1) < 1e-9).sum())}
    write_meta(out, {
        "world": world.name, "description": world.description, "seed": seed, "laps": 1,
        "source_path": Path(path_file).name, "repeated_buildings": repeated_buildings,
        "sensor": {"type": "livox" if rings == "livox" else "lidar3d", **asdict(dev)}, "planar": False,
        "motion_distorted": False,
        "n_scans": int(total), "rate_hz": KITTI_RATE_HZ,
        "speed_mps": round(summary["path_length_m"] / max(duration, 1e-9), 3),
        **extra,
        "path_length_m": summary["path_length_m"], "loop_length_m": summary["path_length_m"],
        "odometry_noise": asdict(noise), "odometry_end_drift_m": summary["odometry_end_drift_m"],
        "T_base_sensor": np.eye(4).tolist(),
        "city": {"buildings": int((labels == "building").sum()), "cars": int((labels == "car").sum()),
                 "poles_and_trees": len(world.cylinders), "road_half_width_m": StreetStyle().road_half_width,
                 "mesh_triangles": int(caster.triangles)},
        "movers": tracks.counts() if tracks is not None else {},
        "labels": "labels/NNNNNN.label: SemanticKITTI uint32 per point (40 road, 50 building, 10 parked car, "
                  "70 vegetation, 80 pole; 252 moving car, 254 moving person: anything not in one place all log)",
    })
    write_landmarks(out, world.cylinders)
    log.info("wrote %d scans along %s to %s", total, path_file, out)
    return out
