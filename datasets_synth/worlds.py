"""Synthetic worlds: triangle meshes plus a path that revisits places.

Planar worlds are built from 2D wall segments extruded to a height; the 3D worlds from boxes
(buildings, parked cars; axis-aligned or oriented), cylinders (poles, tree trunks) and rough
ground. Everything is deterministic from a seed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


@dataclass
class World:
    """A world to drive through.

    Attributes:
        name: registry name.
        planar: True for worlds meant for a 2D laser (vertical walls only, no ground).
        boxes: ``(K, 6)`` axis-aligned boxes ``(xmin, ymin, zmin, xmax, ymax, zmax)`` [m].
        segments: ``(S, 4)`` wall segments ``(x0, y0, x1, y1)`` extruded to ``wall_height``.
        cylinders: ``(C, 4)`` vertical cylinders ``(x, y, radius, height)``.
        oriented_boxes: ``(B, 7)`` boxes ``(cx, cy, yaw, length, width, zmin, zmax)`` turned by
            ``yaw`` [rad] about their vertical centre line; ``length`` runs along the yaw direction.
        box_labels: ``(B,)`` what each oriented box is (``"building"``, ``"car"``, ``"canopy"``).
        ground: add rough ground (z ~ 0) covering the world.
        terrain_radius: keep the ground only within this distance [m] of the waypoints polyline
            (bounds the mesh of long drives); None: everywhere.
        waypoints: ``(W, 2)`` path the robot follows: a loop (``closed``, the last point connects
            to the first) or, with ``closed=False``, an open path driven once from first to last.
        corner_radius: [m] how far before and after a waypoint the path starts rounding it.
        extent: ``(xmin, ymin, xmax, ymax)``.
        doorways: ``(D, 4)`` ``(x0, y0, x1, y1)``: openings in the walls where a door can hang
            (the room doors of ``rooms``), on the wall line.
        ground_height: terrain: the ground height [m] ``(M,)`` at world points ``(M, 2)``, added to
            the rough ground; oriented boxes and cylinders stand on it (buildings sunk to their
            lowest corner, cars, canopies and poles lifted by the height at their centre).
            None: flat ground at z ~ 0.
    """

    name: str
    planar: bool
    waypoints: np.ndarray
    extent: tuple[float, float, float, float]
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    segments: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    cylinders: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    ground: bool = False
    wall_height: float = 2.5
    description: str = ""
    oriented_boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    box_labels: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=str))
    closed: bool = True
    corner_radius: float = 1.2
    terrain_radius: float | None = None
    doorways: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    ground_height: Callable[[np.ndarray], np.ndarray] | None = None

    def loop_length(self) -> float:
        """Length [m] of the waypoint polygon (closed: with the edge back to the start)."""
        w = np.vstack([self.waypoints, self.waypoints[:1]]) if self.closed else self.waypoints
        return float(np.linalg.norm(np.diff(w, axis=0), axis=1).sum())

    def mesh(self):
        """The world as an open3d legacy ``TriangleMesh``."""
        return self.labelled_mesh()[0]

    def labelled_mesh(self):
        """The world mesh and each triangle's SemanticKITTI class ``(T,)`` uint32 (:data:`STATIC_CLASSES`):
        walls and axis-aligned boxes 50 building, cylinders 80 pole, oriented boxes by their label
        (building 50, car 10, canopy 70 vegetation, else 99 other object), the ground 40 road."""
        from submapslam._deps import open3d

        o3d = open3d()
        mesh = o3d.geometry.TriangleMesh()
        labels: list[np.ndarray] = []

        def add(part, cls) -> None:
            nonlocal mesh
            before = len(mesh.triangles)
            mesh += part
            labels.append(np.broadcast_to(np.asarray(cls, dtype=np.uint32), (len(mesh.triangles) - before,)))

        for x0, y0, z0, x1, y1, z1 in self.boxes:
            b = o3d.geometry.TriangleMesh.create_box(x1 - x0, y1 - y0, z1 - z0)
            b.translate((x0, y0, z0))
            add(b, STATIC_CLASSES["building"])
        for x0, y0, x1, y1 in self.segments:
            add(_wall_quad(o3d, x0, y0, x1, y1, self.wall_height), STATIC_CLASSES["building"])
        base = np.zeros(len(self.cylinders))
        if self.ground_height is not None and len(self.cylinders):
            base = self.ground_height(np.asarray(self.cylinders)[:, :2]) - SINK
        for (x, y, r, h), z0 in zip(self.cylinders, base):
            h = h + (SINK if self.ground_height is not None else 0.0)
            c = o3d.geometry.TriangleMesh.create_cylinder(radius=r, height=h, resolution=16)
            c.translate((x, y, z0 + h / 2))
            add(c, STATIC_CLASSES["pole"])
        if len(self.oriented_boxes):
            per_box = np.array([STATIC_CLASSES.get(str(lab), STATIC_CLASSES["other"]) for lab in self.box_labels]
                               if len(self.box_labels) == len(self.oriented_boxes)
                               else [STATIC_CLASSES["other"]] * len(self.oriented_boxes), dtype=np.uint32)
            add(_triangle_mesh(o3d, *_oriented_box_arrays(self.grounded_boxes())), np.repeat(per_box, 12))
        if self.ground:
            keep = None
            if self.terrain_radius is not None:
                keep = _near_polyline(self.waypoints, self.terrain_radius, self.closed)
            add(_terrain(o3d, self.extent, keep=keep, height=self.ground_height), STATIC_CLASSES["road"])
        tri_labels = np.concatenate(labels) if labels else np.zeros(0, dtype=np.uint32)
        return mesh, tri_labels


    def grounded_boxes(self) -> np.ndarray:
        """``oriented_boxes`` ``(B, 7)`` standing on the terrain (unchanged without ``ground_height``):
        a building's bottom sinks to its lowest footprint corner minus :data:`SINK`, its top rises
        by the height at its centre; every other box is lifted by the height at its centre."""
        boxes = np.array(self.oriented_boxes, dtype=np.float64).reshape(-1, 7)
        if self.ground_height is None or not len(boxes):
            return boxes
        centre = self.ground_height(boxes[:, :2])
        corners = _oriented_box_arrays(boxes)[0].reshape(-1, 8, 3)[:, :4, :2]
        lowest = self.ground_height(corners.reshape(-1, 2)).reshape(-1, 4).min(axis=1)
        building = (self.box_labels == "building") if len(self.box_labels) == len(boxes) else np.zeros(len(boxes), bool)
        boxes[:, 5] = np.where(building, lowest - SINK, boxes[:, 5] + centre)
        boxes[:, 6] += centre
        return boxes


SINK = 0.5  # [m] on terrain, buildings and poles reach this far below the ground (no gap under them)

STATIC_CLASSES: dict[str, int] = {"building": 50, "car": 10, "canopy": 70, "pole": 80, "road": 40, "other": 99}
"""SemanticKITTI classes of the static world parts (``labels/NNNNNN.label``, lower 16 bits)."""


def _triangle_mesh(o3d, verts: np.ndarray, tris: np.ndarray):
    g = o3d.geometry.TriangleMesh()
    g.vertices = o3d.utility.Vector3dVector(np.ascontiguousarray(verts, dtype=np.float64))
    g.triangles = o3d.utility.Vector3iVector(np.ascontiguousarray(tris, dtype=np.int32))
    return g


_BOX_CORNERS = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0],
                         [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=np.float64)
_BOX_TRIANGLES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                           [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


def _oriented_box_arrays(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(8B, 3)`` and triangles ``(12B, 3)`` of oriented boxes ``(B, 7)`` (one array op)."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    cx, cy, yaw, length, width, z0, z1 = b.T
    lx = _BOX_CORNERS[None, :, 0] * (length / 2)[:, None]
    ly = _BOX_CORNERS[None, :, 1] * (width / 2)[:, None]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    x = cx[:, None] + c * lx - s * ly
    y = cy[:, None] + s * lx + c * ly
    z = np.where(_BOX_CORNERS[None, :, 2] > 0, z1[:, None], z0[:, None])
    verts = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    tris = (_BOX_TRIANGLES[None] + 8 * np.arange(len(b))[:, None, None]).reshape(-1, 3)
    return verts, tris


def box_footprint(box: np.ndarray) -> np.ndarray:
    """The 4 ground corners ``(4, 2)`` of an oriented box ``(cx, cy, yaw, length, width, ...)``."""
    return _oriented_box_arrays(np.asarray(box, dtype=np.float64)[None, :7])[0][:4, :2]


def _near_polyline(points: np.ndarray, radius: float, closed: bool) -> Callable[[np.ndarray], np.ndarray]:
    """Mask function: which ``(N, 2)`` points lie within ``radius`` of the polyline ``points``."""
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64)
    if closed:
        p = np.vstack([p, p[:1]])
    dense = densify(p, 0.5 * min(radius, 2.0))
    tree = cKDTree(dense)
    slack = 0.5 * min(radius, 2.0)
    return lambda xy: np.isfinite(tree.query(xy, distance_upper_bound=radius + slack)[0])


def densify(polyline: np.ndarray, spacing: float) -> np.ndarray:
    """Points ``(M, 2)`` along ``polyline`` ``(K, 2)`` no more than ``spacing`` apart (its vertices included)."""
    p = np.asarray(polyline, dtype=np.float64).reshape(-1, 2)
    if len(p) < 2:
        return p.copy()
    seg = np.diff(p, axis=0)
    n = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / spacing).astype(int))
    t = np.concatenate([np.arange(k) / k for k in n])
    start = np.repeat(np.arange(len(seg)), n)
    return np.vstack([p[start] + seg[start] * t[:, None], p[-1:]])


def _terrain(o3d, extent, spacing: float = 0.5, amplitude: float = 0.08, roughness: float = 0.04,
             keep: Callable[[np.ndarray], np.ndarray] | None = None,
             height: Callable[[np.ndarray], np.ndarray] | None = None):
    """Undulating, rough ground (a height field). A flat plane gives every scan identical ground
    rings, which pin point-to-point ICP at zero motion; real ground has kerbs, grass and bumps.

    ``keep`` (a mask function of ``(N, 2)`` points) drops the cells whose centre it rejects;
    ``height`` (``(N, 2)`` -> ``(N,)`` [m]) adds the terrain's large-scale height."""
    xmin, ymin, xmax, ymax = extent
    xs = np.arange(xmin - 40, xmax + 40 + spacing, spacing)
    ys = np.arange(ymin - 40, ymax + 40 + spacing, spacing)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    Z = amplitude * (np.sin(X / 3.1) * np.cos(Y / 4.3) + 0.5 * np.sin(X / 1.7 + Y / 2.3))
    Z += np.random.default_rng(12345).normal(0.0, roughness, Z.shape)
    verts = np.stack([X, Y, Z], axis=-1).reshape(-1, 3)
    nx, ny = len(xs), len(ys)
    idx = np.arange(nx * ny).reshape(nx, ny)
    if keep is not None:
        centres = np.stack([X[:-1, :-1] + spacing / 2, Y[:-1, :-1] + spacing / 2], axis=-1).reshape(-1, 2)
        cells = keep(centres).reshape(nx - 1, ny - 1)
    else:
        cells = np.ones((nx - 1, ny - 1), dtype=bool)
    if height is not None:  # only where a kept cell needs it (long drives: millions of far vertices)
        used = np.zeros((nx, ny), dtype=bool)
        for di in (0, 1):
            for dj in (0, 1):
                used[di:nx - 1 + di, dj:ny - 1 + dj] |= cells
        flat = verts.reshape(nx, ny, 3)
        flat[used, 2] += height(flat[used][:, :2])
        verts = flat.reshape(-1, 3)
    a, b, c, d = idx[:-1, :-1][cells], idx[1:, :-1][cells], idx[1:, 1:][cells], idx[:-1, 1:][cells]
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    if keep is not None:  # drop the vertices no kept cell uses
        used = np.zeros(len(verts), dtype=bool)
        used[tris.ravel()] = True
        remap = np.cumsum(used) - 1
        verts, tris = verts[used], remap[tris]
    return _triangle_mesh(o3d, verts, tris)


def _wall_quad(o3d, x0, y0, x1, y1, height):
    q = o3d.geometry.TriangleMesh()
    q.vertices = o3d.utility.Vector3dVector([[x0, y0, 0], [x1, y1, 0], [x1, y1, height], [x0, y0, height]])
    q.triangles = o3d.utility.Vector3iVector([[0, 1, 2], [0, 2, 3]])
    return q


def _polyline(points) -> list[tuple[float, float, float, float]]:
    p = np.asarray(points, dtype=np.float64)
    return [(*p[i], *p[i + 1]) for i in range(len(p) - 1)]


def _wall_with_features(a, b, inward, rng, *, recess_prob=0.35, pillar_prob=0.25, spacing=3.0,
                        fixed: list[tuple[float, str]] | None = None):
    """Segments of the straight wall a->b with door recesses and pillars, pseudo-random, the
    pillars' squares and the doorways ``(x0, y0, x1, y1)`` of its rooms.

    ``inward`` is the unit normal pointing into the hallway. ``fixed`` replaces the random
    layout by ``(position along the wall [m], kind)`` features (used to build repeated rooms).
    """
    a, b, n = (np.asarray(v, dtype=np.float64) for v in (a, b, inward))
    length = float(np.linalg.norm(b - a))
    d = (b - a) / length
    segs, pillars, doorways = [], [], []
    cursor = 0.0
    features = fixed
    if features is None:
        features = []
        s = 1.5
        while s < length - 2.5:
            u = rng.random()
            if u < recess_prob:
                features.append((s, "recess"))
                s += rng.uniform(2.5, 5.0)
            elif u < recess_prob + pillar_prob:
                features.append((s, "pillar"))
                s += rng.uniform(2.0, 4.0)
            else:
                s += rng.uniform(1.0, spacing)
    for pos, kind in features:
        if kind == "recess":
            width = 1.0 + (pos * 7.31 % 1.0) * 0.8 if fixed is None else 1.2
            depth = 0.6 + (pos * 3.17 % 1.0) * 1.2 if fixed is None else 0.8
            p0, p1 = a + d * pos, a + d * (pos + width)
            if pos + width >= length - 0.5:
                continue
            segs += _polyline([a + d * cursor, p0, p0 - n * depth, p1 - n * depth, p1])
            cursor = pos + width
        elif kind == "room":
            width, depth = 3.0, 3.0
            p0, p1 = a + d * pos, a + d * (pos + width)
            door0, door1 = a + d * (pos + 1.0), a + d * (pos + 2.0)
            segs += _polyline([a + d * cursor, door0])
            segs += _polyline([door0, p0, p0 - n * depth, p1 - n * depth, p1, door1])
            doorways.append((*door0, *door1))
            cursor = pos + 2.0
        elif kind == "pillar":
            c = a + d * pos + n * 0.25
            pillars.append((c[0] - 0.2, c[1] - 0.2, c[0] + 0.2, c[1] + 0.2))
    segs += _polyline([a + d * cursor, b])
    return segs, pillars, doorways


def _box_segments(x0, y0, x1, y1):
    return _polyline([(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)])


def _block_walls(x0, y0, x1, y1):
    """Walls of an inner block, each with the normal pointing out of the block (into the hallway)."""
    return [((x0, y0), (x1, y0), (0, -1)), ((x1, y0), (x1, y1), (1, 0)),
            ((x1, y1), (x0, y1), (0, 1)), ((x0, y1), (x0, y0), (-1, 0))]


def _hall_world(name, size, width, rng, blocks, waypoints, fixed_outer=None, fixed_inner=None, description="",
                density: float = 1.0):
    """Hallways between an outer rectangle ``size`` and inner ``blocks``, with wall features."""
    W, H = size
    outer = [((0, 0), (W, 0), (0, 1)), ((W, 0), (W, H), (-1, 0)), ((W, H), (0, H), (0, -1)), ((0, H), (0, 0), (1, 0))]
    segs, pillars, doorways = [], [], []
    for k, (a, b, n) in enumerate(outer):
        s, p, d = _wall_with_features(a, b, n, rng, recess_prob=0.35 * density, pillar_prob=0.25 * density,
                                      fixed=None if fixed_outer is None else fixed_outer(k, a, b))
        segs += s
        pillars += p
        doorways += d
    for blk in blocks:
        for k, (a, b, n) in enumerate(_block_walls(*blk)):
            s, _, d = _wall_with_features(a, b, n, rng, recess_prob=0.3 * density, pillar_prob=0.0,
                                          fixed=None if fixed_inner is None else fixed_inner(k, a, b))
            segs += s
            doorways += d
    boxes = [(x0, y0, 0.0, x1, y1, 2.5) for x0, y0, x1, y1 in pillars]
    return World(name, True, np.asarray(waypoints, dtype=np.float64), (0.0, 0.0, W, H),
                 boxes=np.array(boxes).reshape(-1, 6), segments=np.array(segs), description=description,
                 doorways=np.array(doorways, dtype=np.float64).reshape(-1, 4))


def _ring_world(name, size, width, rng, fixed_outer=None, fixed_inner=None, description="", density=1.0):
    W, H = size
    h = width / 2
    return _hall_world(name, size, width, rng, [(width, width, W - width, H - width)],
                       [(h, h), (W - h, h), (W - h, H - h), (h, H - h)], fixed_outer, fixed_inner, description,
                       density)


def rectangle(seed: int = 0, size: tuple[float, float] = (30.0, 20.0), width: float = 3.0,
              feature_density: float = 1.0, poles: int = 0) -> World:
    """The seed's cyclic example: four hallways meeting in a rectangle, with doors and pillars.

    ``feature_density`` scales how often doors and pillars break the walls (lower: longer
    plain stretches, where scan matching slides along the corridor and odometry drifts).
    ``poles`` free-standing thin poles (r = 0.1 m) stand 0.6 m from the walls: point
    landmarks for the stochastic map running on the same log.
    """
    rng = np.random.default_rng(seed)
    w = _ring_world("rectangle", size, width, rng, description="four hallways forming a rectangle (planar)",
                    density=feature_density)
    if poles:
        W, H = size
        prng = np.random.default_rng(seed + 101)
        cyl = []
        for _ in range(poles):
            side = prng.integers(4)
            t = prng.uniform(0.15, 0.85)
            off = 0.6 if prng.random() < 0.5 else width - 0.6
            x, y = {0: (t * W, off), 1: (W - off, t * H), 2: (t * W, H - off), 3: (off, t * H)}[int(side)]
            cyl.append((x, y, 0.1, 2.0))
        w.cylinders = np.array(cyl)
    return w


def rooms(seed: int = 0, size: tuple[float, float] = (48.0, 12.0), width: float = 3.0) -> World:
    """A rectangle of hallways whose walls repeat one identical room every 6 m: fools place recognition."""
    def outer(k, a, b):
        length = float(np.linalg.norm(np.subtract(b, a)))
        return [(s, "room") for s in np.arange(1.5, length - 4.0, 6.0)]

    def inner(k, a, b):
        return []

    return _ring_world("rooms", size, width, np.random.default_rng(seed), fixed_outer=outer, fixed_inner=inner,
                       description="hallway loop lined with identical rooms (perceptual aliasing)")


def figure8(seed: int = 0, size: tuple[float, float] = (40.0, 16.0), width: float = 3.0) -> World:
    """Two rectangular loops sharing a middle corridor; the path runs both loops in turn."""
    W, H = size
    h, cx = width / 2, W / 2
    blocks = [(width, width, cx - h, H - width), (cx + h, width, W - width, H - width)]
    waypoints = [(cx, H - h), (cx, h), (W - h, h), (W - h, H - h), (cx, H - h), (cx, h), (h, h), (h, H - h)]
    return _hall_world("figure8", size, width, np.random.default_rng(seed), blocks, waypoints,
                       description="two loops sharing a corridor, figure-eight path")


def outdoor(seed: int = 0, blocks: tuple[int, int] = (3, 2), block_size: float = 40.0, street: float = 12.0) -> World:
    """Blocks of buildings with streets between them, poles along the kerbs; loop around all blocks."""
    rng = np.random.default_rng(seed)
    boxes, cyl = [], []
    nx, ny = blocks
    pitch = block_size + street
    for i in range(nx):
        for j in range(ny):
            x0, y0 = i * pitch, j * pitch
            # a block holds 2-4 buildings of varied footprint and height
            cuts = np.sort(rng.uniform(0.25, 0.75, size=rng.integers(1, 3))) * block_size
            edges = np.concatenate([[0.0], cuts, [block_size]])
            for a, b in zip(edges[:-1], edges[1:]):
                if b - a < 4.0:
                    continue
                inset = rng.uniform(0.5, 3.0)
                boxes.append((x0 + a + 0.5, y0 + inset, 0.0, x0 + b - 0.5, y0 + block_size - inset, rng.uniform(6, 25)))
    xmax, ymax = nx * pitch - street, ny * pitch - street
    # poles along the outer ring road, irregular spacing
    for side in range(4):
        s = rng.uniform(2, 8)
        total = (xmax + street) if side % 2 == 0 else (ymax + street)
        while s < total:
            if side == 0:
                p = (-street + 2.0 + s, -street + 1.5)
            elif side == 1:
                p = (xmax + street - 1.5, -street + 2.0 + s)
            elif side == 2:
                p = (xmax + street - 2.0 - s, ymax + street - 1.5)
            else:
                p = (-street + 1.5, ymax + street - 2.0 - s)
            cyl.append((*p, 0.15, rng.uniform(4, 8)))
            s += rng.uniform(8, 20)
    # parked cars and kiosks along both kerbs of the ring road: irregular street furniture
    ring_in = [(-1.5, -1.5), (xmax + 1.5, -1.5), (xmax + 1.5, ymax + 1.5), (-1.5, ymax + 1.5)]
    ring_out = [(-street + 3.0, -street + 3.0), (xmax + street - 3.0, -street + 3.0),
                (xmax + street - 3.0, ymax + street - 3.0), (-street + 3.0, ymax + street - 3.0)]
    for ring in (ring_in, ring_out):
        for k in range(4):
            a, b = np.array(ring[k]), np.array(ring[(k + 1) % 4])
            length = float(np.linalg.norm(b - a))
            d = (b - a) / length
            s_ = rng.uniform(3, 10)
            while s_ < length - 3:
                c = a + d * s_
                half = np.abs(d) * rng.uniform(1.0, 2.4) + np.abs(d[::-1]) * rng.uniform(0.7, 1.0)
                boxes.append((c[0] - half[0], c[1] - half[1], 0.0, c[0] + half[0], c[1] + half[1], rng.uniform(1.2, 2.8)))
                s_ += rng.uniform(6, 18)
    # a wall around the outside of the ring road, broken into pieces
    ring = [(-street - 2, -street - 2), (xmax + street + 2, -street - 2), (xmax + street + 2, ymax + street + 2),
            (-street - 2, ymax + street + 2)]
    for k in range(4):
        a, b = np.array(ring[k]), np.array(ring[(k + 1) % 4])
        for t0 in np.arange(0, 1, 0.2):
            if rng.random() < 0.7:
                p0, p1 = a + (b - a) * t0, a + (b - a) * (t0 + 0.15)
                lo, hi = np.minimum(p0, p1), np.maximum(p0, p1)
                boxes.append((lo[0] - 0.2, lo[1] - 0.2, 0.0, hi[0] + 0.2, hi[1] + 0.2, rng.uniform(2, 4)))
    h = street / 2
    waypoints = np.array([(-h, -h), (xmax + h, -h), (xmax + h, ymax + h), (-h, ymax + h)])
    return World("outdoor", False, waypoints, (-street, -street, xmax + street, ymax + street),
                 boxes=np.array(boxes), cylinders=np.array(cyl), ground=True,
                 description="city blocks, poles and walls with a drivable loop (3D)")


ALIASED_BLOCK_LENGTH = 44.0  # [m] street length of each of the two identical blocks


def aliased(seed: int = 0, shift: float = 18.0) -> World:
    """Two IDENTICAL street blocks ~93 m apart, joined by a street that looks like nothing else;
    the open path drives block A, the connecting street, then block B, and never returns to A,
    so every loop closure between A and B is false (perceptual aliasing, 3D).

    Layout (world frame, x east): block A is the street ``y = 0``, ``0 <= x <= 44``; block B is
    the same block translated by :func:`aliased_offset` (``(91.2, 18.0)`` m for the default
    ``shift``): same buildings, parked cars, poles and trees (the ground's fine roughness differs).
    The connecting street runs 8 m on from A, 30 deg to the left for 36 m (a dog-leg of ``shift``
    metres sideways, so the buildings at its bends hide one block from the other), and 8 m into
    B. The path starts 6 m into A and ends 32 m into B, 122 m in all: at the default 8 m/s and
    10 Hz, 153 scans: 0-47 in block A, 48-112 in the connecting street, 113-152 in block B (3D
    submaps close every 12 m of travel: the first three or four submaps alias the last three).
    Buildings along the connecting street are all different; those of the blocks come from one
    random draw placed twice. The two blocks are ~93 m apart, beyond the loop search's 60 m
    proximity ceiling, so only a place descriptor proposes A-B pairs: a test that the
    correspondence and consistency checks reject them.
    """
    from .motion import open_path
    from .streets import StreetBuilder, StreetStyle

    offset = aliased_offset(shift)
    L = ALIASED_BLOCK_LENGTH
    bend = np.array([L + 8.0, 0.0])
    waypoints = np.array([(6.0, 0.0), tuple(bend), tuple(offset - (8.0, 0.0)), tuple(offset + (32.0, 0.0))])
    corner_radius = 8.0
    path = open_path(waypoints, 0.5, corner_radius)[:, :2]
    # denser than a city street: short buildings, small gaps, many cars and poles
    style = StreetStyle(length=(8.0, 18.0), depth=(8.0, 14.0), building_gap=(1.0, 4.0), park_probability=0.0,
                        car_run_end=0.1, car_run_gap=(4.0, 12.0), kerb_spacing=(6.0, 14.0))
    rng = np.random.default_rng([seed, 8111])
    # the block, built once in its own frame, clear of the path seen from either block's origin
    block = StreetBuilder([path, path - offset], (-20.0, -60.0, L + 20.0, 60.0), rng, style)
    block.street(np.array([(0.0, 0.0), (L, 0.0)]))
    boxes, labels, cyl = block.parts()
    shifted_boxes, shifted_cyl = boxes.copy(), cyl.copy()
    shifted_boxes[:, :2] += offset
    shifted_cyl[:, :2] += offset
    lo = np.minimum(path.min(axis=0), 0.0) - 60.0
    hi = path.max(axis=0) + 60.0
    street = StreetBuilder(path, (lo[0], lo[1], hi[0], hi[1]), rng, style)
    for origin in (np.zeros(2), offset):  # nothing else inside either block
        centre = origin + (L / 2, 0.0)
        street.reserve((centre[0], centre[1], 0.0, L + 8.0, 90.0))
    # the connecting street: the path from the end of A to the start of B (x grows all along)
    start = int(np.argmax(path[:, 0] >= L - 2.0))
    end = int(np.argmax(path[:, 0] >= offset[0] + 2.0))
    street.street(path[start:end + 1])
    sboxes, slabels, scyl = street.parts()
    return World("aliased", False, waypoints, (lo[0] + 20, lo[1] + 20, hi[0] - 20, hi[1] - 20),
                 cylinders=np.vstack([cyl, shifted_cyl, scyl]), ground=True,
                 oriented_boxes=np.vstack([boxes, shifted_boxes, sboxes]),
                 box_labels=np.concatenate([labels, labels, slabels]), closed=False, corner_radius=corner_radius,
                 description="two identical street blocks ~93 m apart joined by a different street; open path A -> B")


def aliased_offset(shift: float = 18.0) -> np.ndarray:
    """Translation ``(2,)`` [m] from block A to block B of :func:`aliased` (B = A + offset)."""
    run = shift / np.tan(np.deg2rad(30.0))
    return np.array([ALIASED_BLOCK_LENGTH + 8.0 + run + 8.0, shift])


WORLDS: dict[str, tuple[Callable[..., World], str, str]] = {
    "rectangle": (rectangle, "laser2d", "four hallways forming a rectangle (the seed's cyclic example)"),
    "rooms": (rooms, "laser2d", "hallway loop of identical rooms, built to fool place recognition"),
    "figure8": (figure8, "laser2d", "two loops sharing a corridor, figure-eight path"),
    "outdoor": (outdoor, "lidar3d", "city blocks, poles and walls, loop of ~200 m (3D LiDAR)"),
    "aliased": (aliased, "lidar3d", "two identical street blocks on an open path A -> B: every A-B closure is false (3D)"),
}
