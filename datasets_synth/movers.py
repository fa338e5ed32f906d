"""Things that move: cars, pedestrians, parked cars that leave, people and boxes indoors.

A mover is an oriented box whose pose ``(x, y, yaw)`` and presence are known at every scan
(:class:`MoverTracks`); :class:`MoverCaster` ray-casts the movers present at one scan, so the
static world's mesh is built once and the movers are added scan by scan.

Ground-truth classes follow SemanticKITTI (``labels/NNNNNN.label``, lower 16 bits): 252 moving
car, 254 moving person, 259 (SemanticKITTI's moving-other-vehicle) any other moved object (boxes).
The rule is the static map's, not a per-scan motion flag: an object that does not hold one place
for the whole log is dynamic in every scan it is seen in, also while it stands still (a parked
car that leaves, a pedestrian waiting at a corner, a box moved between laps) — none of it is in
the world at the log's end where it was seen before. SemanticKITTI itself labels an object that
stands still in a scan with its static class (10 car, 30 person).

Doors (:func:`door_tracks`) follow the same rule. SemanticKITTI has no door class: a closed door
is a piece of wall (50 building) when it stays closed for the whole log; a door that opens and
closes during the log does not hold one state, so its leaf is 259 (moving other) in every scan
it is seen in, like a moved box — a map for planning should leave the doorway free, and the
scorer counts its cells among those to free. An open door is out of the way (a sliding door in
its wall pocket): no leaf in the doorway, nothing to hit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from submapslam.errors import SubmapSlamError

from .worlds import STATIC_CLASSES, _oriented_box_arrays, densify

MOVING_CAR = 252
MOVING_PERSON = 254
MOVING_OTHER = 259
DYNAMIC_CLASSES = range(252, 260)
STATIC_BUILDING = STATIC_CLASSES["building"]

CAR_SIZE = (4.2, 1.8, 0.3, 1.5)  # length, width, zmin, zmax [m]: the body above the wheels
PERSON_SIZE = (0.5, 0.5, 0.05, 1.75)
LANE_OFFSET = 3.2  # [m] lateral offset of a lane's centre from the driven path
SIDEWALK = (9.9, 10.5)  # [m] lateral offsets of pedestrians (between the kerb poles and the facades)


@dataclass
class MoverTracks:
    """Movers sampled at the scan times.

    Attributes:
        poses: ``(M, N, 3)`` world ``(x, y, yaw)`` of each mover's box centre at each of N scans.
        present: ``(M, N)`` whether the mover exists at that scan.
        sizes: ``(M, 4)`` ``(length, width, zmin, zmax)`` [m]; ``length`` along the yaw.
        classes: ``(M,)`` SemanticKITTI class of each mover (252-259).
        kinds: ``(M,)`` ``"car"``, ``"parked_car"``, ``"person"``, ``"box"``.
        ground_height: on terrain, the ground height [m] ``(B,)`` at world points ``(B, 2)``: each
            box stands on the ground at its centre (``zmin`` and ``zmax`` above it); None: flat.
    """

    poses: np.ndarray
    present: np.ndarray
    sizes: np.ndarray
    classes: np.ndarray
    kinds: np.ndarray
    ground_height: Callable[[np.ndarray], np.ndarray] | None = None

    @classmethod
    def empty(cls, n_scans: int) -> MoverTracks:
        return cls(np.zeros((0, n_scans, 3)), np.zeros((0, n_scans), dtype=bool), np.zeros((0, 4)),
                   np.zeros(0, dtype=np.uint32), np.zeros(0, dtype="<U10"))

    def __len__(self) -> int:
        return len(self.classes)

    def boxes_at(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Oriented boxes ``(B, 7)`` ``(cx, cy, yaw, length, width, zmin, zmax)`` present at scan k, and their classes."""
        on = self.present[:, k]
        boxes = np.column_stack([self.poses[on, k], self.sizes[on]])
        if self.ground_height is not None and len(boxes):
            boxes[:, 5:7] += self.ground_height(boxes[:, :2])[:, None]
        return boxes, self.classes[on]

    def counts(self) -> dict[str, int]:
        kinds, n = np.unique(self.kinds, return_counts=True)
        return {str(k): int(c) for k, c in zip(kinds, n)}

    @staticmethod
    def concat(parts: list[MoverTracks]) -> MoverTracks:
        return MoverTracks(*(np.concatenate([getattr(p, f) for p in parts])
                             for f in ("poses", "present", "sizes", "classes", "kinds")))


DOOR_THICKNESS = 0.04  # [m] door leaf
DOOR_HEIGHT = 2.0
DOOR_PERIOD = (10.0, 40.0)  # [s] how long a door stays open or closed


def door_tracks(doorways: np.ndarray, n_scans: int, rate: float, n: int, rng: np.random.Generator) -> MoverTracks:
    """Doors in ``n`` of the ``doorways`` ``(D, 4)`` ``(x0, y0, x1, y1)`` (chosen by ``rng``): a leaf
    the width of the doorway, :data:`DOOR_THICKNESS` thick, on the wall line, present while the
    door is closed. Each door starts open or closed at random and changes state after periods of
    :data:`DOOR_PERIOD` seconds (uniform), over ``n_scans`` scans at ``rate`` Hz. Class 259 for a
    door that changes state during the log, 50 (a piece of wall) for one that stays closed.
    """
    doorways = np.asarray(doorways, dtype=np.float64).reshape(-1, 4)
    if n > len(doorways):
        raise SubmapSlamError(f"{n} doors asked for, but the world has {len(doorways)} doorways")
    chosen = np.sort(rng.choice(len(doorways), size=n, replace=False))
    parts = []
    t = np.arange(n_scans) / rate
    for i in chosen:
        x0, y0, x1, y1 = doorways[i]
        closed = np.zeros(n_scans, dtype=bool)
        state, t0 = bool(rng.random() < 0.5), 0.0
        while t0 < (t[-1] if n_scans else 0.0) + 1e-9:
            t1 = t0 + rng.uniform(*DOOR_PERIOD)
            closed[(t >= t0) & (t < t1)] = state
            state, t0 = not state, t1
        pose = np.broadcast_to([(x0 + x1) / 2, (y0 + y1) / 2, np.arctan2(y1 - y0, x1 - x0)], (n_scans, 3))
        changes = closed.any() and not closed.all()
        size = (float(np.hypot(x1 - x0, y1 - y0)), DOOR_THICKNESS, 0.0, DOOR_HEIGHT)
        parts.append(MoverTracks(np.array(pose)[None], closed[None], np.array(size)[None],
                                 np.array([MOVING_OTHER if changes else STATIC_BUILDING], dtype=np.uint32),
                                 np.array(["door"])))
    return MoverTracks.concat(parts) if parts else MoverTracks.empty(n_scans)


class MoverCaster:
    """Ray-casts the movers present at one scan (a small scene built per scan)."""

    def __init__(self, tracks: MoverTracks, max_range: float) -> None:
        from submapslam._deps import open3d

        self._o3d = open3d()
        self.tracks = tracks
        self.max_range = max_range

    def cast(self, k: int, T_world_sensor: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances ``(R,)`` along sensor-frame unit ``directions`` to the movers of scan k (inf: no
        mover) and the class ``(R,)`` of the mover hit (0: none)."""
        boxes, classes = self.tracks.boxes_at(k)
        near = np.linalg.norm(boxes[:, :2] - T_world_sensor[:2, 3], axis=1) < self.max_range + 5.0
        boxes, classes = boxes[near], classes[near]
        far = np.full(len(directions), np.inf)
        if not len(boxes):
            return far, np.zeros(len(directions), dtype=np.uint32)
        o3d = self._o3d
        verts, tris = _oriented_box_arrays(boxes)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(tris.astype(np.uint32)))
        d_world = directions @ T_world_sensor[:3, :3].T
        origins = np.broadcast_to(T_world_sensor[:3, 3], d_world.shape)
        hit = scene.cast_rays(o3d.core.Tensor(np.hstack([origins, d_world]).astype(np.float32)))
        t = hit["t_hit"].numpy().astype(np.float64)
        prim = hit["primitive_ids"].numpy().astype(np.int64)
        ok = np.isfinite(t)
        cls = np.zeros(len(t), dtype=np.uint32)
        cls[ok] = classes[prim[ok] // 12]
        return t, cls


class Lane:
    """A polyline parametrised by arc length: poses at ``(s, lateral offset)``, offset > 0 to the left."""

    def __init__(self, polyline: np.ndarray, extend: float = 150.0, spacing: float = 0.5) -> None:
        p = np.asarray(polyline, dtype=np.float64)[:, :2]
        keep = np.concatenate([[True], np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-6])
        p = p[keep]
        if len(p) < 2:
            p = np.vstack([p[:1], p[:1] + (1.0, 0.0)])
        d0 = (p[1] - p[0]) / np.linalg.norm(p[1] - p[0])
        d1 = (p[-1] - p[-2]) / np.linalg.norm(p[-1] - p[-2])
        p = np.vstack([p[:1] - d0 * extend, p, p[-1:] + d1 * extend])
        self.points = densify(p, spacing)
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self.s = np.concatenate([[0.0], np.cumsum(seg)]) - extend
        # heading smoothed over +-2 m so offset lanes round the path's corners
        w = max(1, int(round(2.0 / spacing)))
        ahead = self.points[np.minimum(np.arange(len(self.points)) + w, len(self.points) - 1)]
        behind = self.points[np.maximum(np.arange(len(self.points)) - w, 0)]
        self.heading = np.unwrap(np.arctan2(ahead[:, 1] - behind[:, 1], ahead[:, 0] - behind[:, 0]))
        self.lo, self.hi = float(self.s[0]), float(self.s[-1])

    def pose(self, s: np.ndarray, offset: np.ndarray | float) -> np.ndarray:
        """``(K, 3)`` ``(x, y, heading)`` at arc lengths ``s`` ``(K,)`` and lateral ``offset`` [m]."""
        s = np.clip(np.asarray(s, dtype=np.float64), self.lo, self.hi)
        x = np.interp(s, self.s, self.points[:, 0])
        y = np.interp(s, self.s, self.points[:, 1])
        h = np.interp(s, self.s, self.heading)
        off = np.broadcast_to(np.asarray(offset, dtype=np.float64), s.shape)
        return np.stack([x - np.sin(h) * off, y + np.cos(h) * off, h], axis=1)

    def locate(self, xy: np.ndarray) -> tuple[float, float]:
        """Arc length and signed lateral offset of the point ``(2,)`` nearest on the lane."""
        i = int(np.argmin(np.linalg.norm(self.points - xy, axis=1)))
        h = self.heading[i]
        rel = np.asarray(xy) - self.points[i]
        return float(self.s[i]), float(-np.sin(h) * rel[0] + np.cos(h) * rel[1])


def _track(lane: Lane, s: np.ndarray, offset: np.ndarray | float, backwards: bool, size, cls: int, kind: str):
    pose = lane.pose(s, offset)
    if backwards:
        pose[:, 2] += np.pi
    present = (s > lane.lo) & (s < lane.hi)
    return MoverTracks(pose[None], present[None], np.asarray(size, dtype=np.float64)[None],
                       np.array([cls], dtype=np.uint32), np.array([kind]))


def city_movers(path_xyt: np.ndarray, rate: float, n: int, rng: np.random.Generator,
                parked_cars: np.ndarray) -> tuple[MoverTracks, np.ndarray]:
    """``n`` movers along the driven path ``(N, 3)`` sampled at ``rate`` Hz: half cars driving both ways
    in the two lanes (6-14 m/s), a third pedestrians on the sidewalks (1.0-1.6 m/s, half of them
    waiting 3-10 s while the vehicle passes), the rest parked cars (from ``parked_cars`` ``(P, 7)``,
    the world's) that pull out and drive away when the vehicle comes by (within 3 s before to 1 s
    after it is nearest, so their leaving is seen). Each mover meets the vehicle at a random
    scan. Returns the tracks and the indices into ``parked_cars`` that left (drop them from the
    static world).
    """
    N = len(path_xyt)
    t = np.arange(N) / rate
    lane = Lane(path_xyt[:, :2])
    ego_s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path_xyt[:, :2], axis=0), axis=1))])
    n_parked_wanted = max(0, n - n // 2 - n // 3) if n >= 3 else 0
    n_cars = n // 2
    n_people = n - n_cars - n_parked_wanted
    parts: list[MoverTracks] = []
    for _ in range(n_cars):
        forward = bool(rng.random() < 0.5)
        v = rng.uniform(6.0, 14.0)
        k_meet = int(rng.integers(N))
        s_meet = ego_s[k_meet] + rng.uniform(-5.0, 30.0)
        sign = 1.0 if forward else -1.0
        s = s_meet + sign * v * (t - t[k_meet])
        parts.append(_track(lane, s, -sign * LANE_OFFSET, not forward, CAR_SIZE, MOVING_CAR, "car"))
    for _ in range(n_people):
        forward = bool(rng.random() < 0.5)
        sign = 1.0 if forward else -1.0
        v = rng.uniform(1.0, 1.6)
        k_meet = int(rng.integers(N))
        s_meet = ego_s[k_meet] + rng.uniform(0.0, 30.0)
        u = t - t[k_meet]
        if rng.random() < 0.5:  # waits while the vehicle passes, then walks on
            start, dur = -rng.uniform(2.0, 6.0), rng.uniform(3.0, 10.0)
            u = u - np.clip(u - start, 0.0, dur)
        side = 1.0 if rng.random() < 0.5 else -1.0
        s = s_meet + sign * v * u
        parts.append(_track(lane, s, side * rng.uniform(*SIDEWALK), not forward, PERSON_SIZE, MOVING_PERSON,
                            "person"))
    left = _parked_leaving(lane, path_xyt, ego_s, t, n_parked_wanted, rng, parked_cars, parts)
    tracks = MoverTracks.concat(parts) if parts else MoverTracks.empty(N)
    return tracks, left


def _parked_leaving(lane: Lane, path_xyt, ego_s, t, wanted, rng, parked_cars, parts) -> np.ndarray:
    """Parked cars near the path that pull into the lane and drive off as the vehicle passes."""
    if wanted == 0 or not len(parked_cars):
        return np.zeros(0, dtype=int)
    xy = path_xyt[:, :2]
    dist = np.linalg.norm(parked_cars[:, None, :2] - xy[None], axis=2)
    nearest = dist.argmin(axis=1)
    ok = np.flatnonzero(dist.min(axis=1) < 12.0)
    chosen = rng.choice(ok, size=min(wanted, len(ok)), replace=False) if len(ok) else np.zeros(0, dtype=int)
    for i in chosen:
        cx, cy, yaw, length, width, z0, z1 = parked_cars[i]
        s_p, d_p = lane.locate(np.array([cx, cy]))
        forward = d_p < 0  # parked on the right of the path: leaves in the driving direction
        sign = 1.0 if forward else -1.0
        t_leave = t[nearest[i]] + rng.uniform(-3.0, 1.0)
        u = np.maximum(t - t_leave, 0.0)
        travel = np.where(u < 3.0, 0.5 * 2.0 * u**2, 9.0 + 6.0 * (u - 3.0))  # 2 m/s^2 to 6 m/s, then on
        blend = np.clip(u / 3.0, 0.0, 1.0)
        blend = blend * blend * (3 - 2 * blend)
        offset = d_p + (-sign * LANE_OFFSET - d_p) * blend
        track = _track(lane, s_p + sign * travel, offset, not forward, (length, width, z0, z1), MOVING_CAR,
                       "parked_car")
        parked = u <= 0.0
        track.poses[0, parked] = (cx, cy, yaw)  # exactly where the world had it until it leaves
        track.present[0, parked] = True
        parts.append(track)
    return np.sort(chosen)


BOX_SIZE = (0.6, 0.6, 0.0, 0.8)
INDOOR_PERSON = (0.5, 0.5, 0.0, 1.75)


def indoor_movers(path_xyt: np.ndarray, rate: float, n: int, rng: np.random.Generator,
                  corridor_half_width: float = 1.5) -> MoverTracks:
    """``n`` movers along a hallway path ``(N, 3)`` sampled at ``rate`` Hz: two thirds people
    walking the corridors 0.6-0.9 m beside the robot's line, both ways (0.8-1.4 m/s; half of them
    stand still for 5-20 s where the robot meets them, then walk on), one third boxes standing
    beside a wall that are moved to another place along the corridor halfway through the log
    (between laps). Each person meets the robot at a random scan.
    """
    N = len(path_xyt)
    t = np.arange(N) / rate
    lane = Lane(path_xyt[:, :2], extend=0.0)
    robot_s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path_xyt[:, :2], axis=0), axis=1))])
    n_boxes = n // 3
    parts: list[MoverTracks] = []
    for _ in range(n - n_boxes):
        forward = bool(rng.random() < 0.5)
        sign = 1.0 if forward else -1.0
        v = rng.uniform(0.8, 1.4)
        k_meet = int(rng.integers(N))
        s_meet = robot_s[k_meet] + rng.uniform(1.0, 6.0)
        u = t - t[k_meet]
        if rng.random() < 0.5:
            start, dur = -rng.uniform(2.0, 5.0), rng.uniform(5.0, 20.0)
            u = u - np.clip(u - start, 0.0, dur)
        s = s_meet + sign * v * u
        side = 1.0 if rng.random() < 0.5 else -1.0
        parts.append(_track(lane, s, side * rng.uniform(0.6, 0.9), not forward, INDOOR_PERSON, MOVING_PERSON,
                            "person"))
    half = N // 2
    for _ in range(n_boxes):
        side = 1.0 if rng.random() < 0.5 else -1.0
        offset = side * (corridor_half_width - 0.45)
        s_a, s_b = rng.uniform(lane.lo, lane.hi, 2)
        s = np.where(np.arange(N) < half, s_a, s_b)
        parts.append(_track(lane, s, offset, False, BOX_SIZE, MOVING_OTHER, "box"))
    return MoverTracks.concat(parts) if parts else MoverTracks.empty(N)
