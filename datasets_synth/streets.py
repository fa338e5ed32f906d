"""Streets: buildings, parked cars, poles and trees along both sides of a driven centreline.

A :class:`StreetBuilder` keeps a road corridor free of every obstacle (nothing within
``road_half_width`` of any point of the driven path, wherever the path goes next or went
before) and an occupancy raster of what it has placed, so a street the path revisits, or a
crossing street, does not pile a second row of objects into the first.

Buildings stand at the kerb with gaps between them, their fronts parallel to the street; with a
catalogue of templates (:func:`building_templates`) the same few footprints and heights repeat
street after street, as in a real city, where places alias. Parks leave long stretches open.
Everything is deterministic from the generator passed in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .worlds import box_footprint, densify


@dataclass(frozen=True)
class StreetStyle:
    """Cross-section of a street, lateral offsets from the centreline of the driven path [m]."""

    road_half_width: float = 7.0  # corridor kept free of any obstacle
    car_offset: float = 8.4  # parked cars' centres (1.7-1.9 m wide: inner side >= 7.45 m)
    kerb_offset: float = 9.6  # poles and tree trunks
    facade_offset: float = 11.0  # building fronts, plus a setback of up to ``setback``
    setback: float = 1.5
    building_gap: tuple[float, float] = (1.5, 9.0)
    length: tuple[float, float] = (10.0, 30.0)  # building extent along the street
    depth: tuple[float, float] = (9.0, 18.0)
    height: tuple[float, float] = (6.0, 24.0)
    park_probability: float = 0.05  # per building slot: an open stretch instead
    park_length: tuple[float, float] = (30.0, 70.0)
    park_depth: float = 30.0
    car_run_end: float = 0.2  # probability a row of parked cars ends after a car
    car_run_gap: tuple[float, float] = (8.0, 45.0)
    kerb_spacing: tuple[float, float] = (10.0, 32.0)
    tree_fraction: float = 0.5


def building_templates(rng: np.random.Generator, n: int = 5, style: StreetStyle = StreetStyle()) -> np.ndarray:
    """``(n, 3)`` building templates ``(length along the street, depth, height)`` [m], 0.1 m steps."""
    lo = np.array([style.length[0], style.depth[0], style.height[0]])
    hi = np.array([style.length[1], style.depth[1], style.height[1]])
    return np.round(rng.uniform(lo, hi, size=(n, 3)), 1)


class StreetBuilder:
    """Places street objects around a driven path and collects them as world parts.

    Args:
        corridor: ``(M, 2)`` the whole driven path, or a list of such polylines (any spacing;
            densified to 0.5 m). No obstacle comes within ``style.road_half_width`` of it.
        extent: ``(xmin, ymin, xmax, ymax)`` of the occupancy raster (objects outside it are not
            checked against each other).
        rng: the generator every random choice comes from.
        cell: occupancy raster cell [m].
    """

    def __init__(self, corridor: np.ndarray | list[np.ndarray], extent: tuple[float, float, float, float], rng: np.random.Generator,
                 style: StreetStyle = StreetStyle(), cell: float = 0.5) -> None:
        from scipy.spatial import cKDTree

        self.style = style
        self.rng = rng
        pieces = corridor if isinstance(corridor, list) else [corridor]
        self.tree = cKDTree(np.vstack([densify(p, 0.5) for p in pieces]))
        self.cell = cell
        self.origin = np.array(extent[:2], dtype=np.float64)
        shape = np.ceil((np.array(extent[2:]) - self.origin) / cell).astype(int) + 1
        self.occupied = np.zeros(tuple(shape), dtype=bool)
        self.boxes: list[tuple[float, ...]] = []
        self.labels: list[str] = []
        self.cylinders: list[tuple[float, float, float, float]] = []

    # ----------------------------------------------------------------- checks and bookkeeping

    def clearance(self, xy: np.ndarray) -> float:
        """Smallest distance [m] from the points ``(N, 2)`` to the driven path."""
        return float(self.tree.query(np.asarray(xy).reshape(-1, 2))[0].min())

    def _cells(self, box: tuple[float, ...]) -> np.ndarray:
        cx, cy, yaw, length, width = box[:5]
        step = 0.8 * self.cell
        u = np.arange(-length / 2, length / 2 + 1e-9, step)
        v = np.arange(-width / 2, width / 2 + 1e-9, step)
        U, V = (a.ravel() for a in np.meshgrid(u, v, indexing="ij"))
        c, s = np.cos(yaw), np.sin(yaw)
        xy = np.stack([cx + c * U - s * V, cy + s * U + c * V], axis=1)
        ij = np.floor((xy - self.origin) / self.cell).astype(int)
        inside = np.all((ij >= 0) & (ij < self.occupied.shape), axis=1)
        return np.unique(np.ravel_multi_index(ij[inside].T, self.occupied.shape))

    def _outline(self, box: tuple[float, ...], spacing: float = 0.5) -> np.ndarray:
        corners = box_footprint(np.asarray(box, dtype=np.float64))
        return densify(np.vstack([corners, corners[:1]]), spacing)

    def reserve(self, box: tuple[float, ...]) -> None:
        """Mark the footprint of ``(cx, cy, yaw, length, width)`` occupied (nothing else goes there)."""
        self.occupied.flat[self._cells(box)] = True

    def add_box(self, box: tuple[float, ...], label: str, *, clear: float, max_overlap: float = 0.0,
                reserve: bool = True) -> bool:
        """Add oriented box ``(cx, cy, yaw, length, width, zmin, zmax)`` if its footprint keeps
        ``clear`` metres from the path and at most ``max_overlap`` of it is occupied already."""
        if self.clearance(self._outline(box)) < clear:
            return False
        cells = self._cells(box)
        if len(cells) and self.occupied.flat[cells].mean() > max_overlap:
            return False
        if reserve:
            self.occupied.flat[cells] = True
        self.boxes.append(tuple(float(v) for v in box))
        self.labels.append(label)
        return True

    def add_cylinder(self, x: float, y: float, radius: float, height: float, *, clear: float) -> bool:
        """Add a vertical cylinder standing on the ground if it keeps ``clear`` metres from the
        path and its square footprint is free."""
        box = (x, y, 0.0, 2 * radius, 2 * radius)
        if self.clearance(np.array([[x, y]])) - radius < clear:
            return False
        cells = self._cells(box)
        if len(cells) and self.occupied.flat[cells].any():
            return False
        self.occupied.flat[cells] = True
        self.cylinders.append((float(x), float(y), float(radius), float(height)))
        return True

    def parts(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``oriented_boxes (B, 7)``, ``box_labels (B,)``, ``cylinders (C, 4)`` placed so far."""
        return (np.array(self.boxes, dtype=np.float64).reshape(-1, 7), np.array(self.labels, dtype=str),
                np.array(self.cylinders, dtype=np.float64).reshape(-1, 4))

    # ----------------------------------------------------------------- streets

    def street(self, centreline: np.ndarray, templates: np.ndarray | None = None, *, buildings: bool = True,
               cars: bool = True, kerb: bool = True) -> None:
        """Line both sides of ``centreline`` ``(K, 2)`` (a stretch of the driven path).

        ``templates``: ``(T, 3)`` building catalogue (length, depth, height) to draw from; None:
        every building has its own random size. Buildings go first, then parked cars, then poles
        and trees, each side in turn.
        """
        line = _Line(densify(centreline, 0.5))
        if line.length < 5.0:
            return
        for side in (1.0, -1.0):
            if buildings:
                self._buildings(line, side, templates)
        for side in (1.0, -1.0):
            if cars:
                self._cars(line, side)
            if kerb:
                self._kerb(line, side)

    def _building_size(self, templates: np.ndarray | None) -> np.ndarray:
        if templates is not None:
            return templates[self.rng.integers(len(templates))]
        return building_templates(self.rng, 1, self.style)[0]

    def _buildings(self, line: _Line, side: float, templates: np.ndarray | None) -> None:
        st, rng = self.style, self.rng
        s = rng.uniform(0.0, 8.0)
        while s < line.length - st.length[0]:
            if rng.random() < st.park_probability:
                s += self._park(line, side, s) + rng.uniform(*st.building_gap)
                continue
            length, depth, height = self._building_size(templates)
            if s + length > line.length:
                break
            p, t = line.at(s + length / 2), line.chord(s, s + length)
            n = side * np.array([-t[1], t[0]])
            offset = st.facade_offset + rng.uniform(0.0, st.setback) + depth / 2
            cx, cy = p + n * offset
            box = (cx, cy, float(np.arctan2(t[1], t[0])), length, depth, 0.0, height)
            if self.add_box(box, "building", clear=st.facade_offset - 1.0, max_overlap=0.05):
                s += length + rng.uniform(*st.building_gap)
            else:
                s += 2.0

    def _park(self, line: _Line, side: float, s: float) -> float:
        """An open stretch with a few trees; returns its length along the street."""
        st, rng = self.style, self.rng
        length = min(rng.uniform(*st.park_length), max(line.length - s, 0.0))
        if length < 5.0:
            return length
        p, t = line.at(s + length / 2), line.chord(s, s + length)
        n = side * np.array([-t[1], t[0]])
        for _ in range(int(length * st.park_depth / 150.0)):
            u, v = rng.uniform(-length / 2, length / 2), rng.uniform(st.facade_offset, st.facade_offset + st.park_depth)
            x, y = p + t * u + n * v
            self._tree(x, y)
        cx, cy = p + n * (st.facade_offset + st.park_depth / 2)
        self.reserve((cx, cy, float(np.arctan2(t[1], t[0])), length, st.park_depth))
        return length

    def _tree(self, x: float, y: float) -> bool:
        st, rng = self.style, self.rng
        if not self.add_cylinder(x, y, rng.uniform(0.18, 0.3), rng.uniform(3.0, 4.0), clear=st.road_half_width + 1.0):
            return False
        size = rng.uniform(2.4, 3.4)
        canopy = (x, y, rng.uniform(0, np.pi / 2), size, size, rng.uniform(2.4, 3.0), rng.uniform(5.5, 8.0))
        if not self.add_box(canopy, "canopy", clear=st.road_half_width, max_overlap=1.0, reserve=False):
            self.cylinders.pop()  # a trunk without its canopy would be a pole: drop the tree
            return False
        return True

    def _cars(self, line: _Line, side: float) -> None:
        st, rng = self.style, self.rng
        s = rng.uniform(0.0, 15.0)
        while s < line.length - 5.0:
            length, width = rng.uniform(4.0, 4.9), rng.uniform(1.7, 1.9)
            p, t = line.at(s + length / 2), line.chord(s, s + length)
            n = side * np.array([-t[1], t[0]])
            cx, cy = p + n * (st.car_offset + rng.uniform(-0.15, 0.15))
            yaw = float(np.arctan2(t[1], t[0])) + rng.normal(0.0, 0.03)
            placed = self.add_box((cx, cy, yaw, length, width, 0.25, rng.uniform(1.4, 1.75)), "car",
                                  clear=st.road_half_width)
            s += length + rng.uniform(0.8, 3.0)
            if not placed or rng.random() < st.car_run_end:
                s += rng.uniform(*st.car_run_gap)

    def _kerb(self, line: _Line, side: float) -> None:
        st, rng = self.style, self.rng
        s = rng.uniform(0.0, st.kerb_spacing[1])
        while s < line.length:
            p, t = line.at(s), line.chord(s - 1.0, s + 1.0)
            x, y = p + side * np.array([-t[1], t[0]]) * (st.kerb_offset + rng.uniform(-0.2, 0.2))
            if rng.random() < st.tree_fraction:
                self._tree(x, y)
            else:
                self.add_cylinder(x, y, rng.uniform(0.1, 0.18), rng.uniform(4.5, 9.0), clear=st.road_half_width + 1.0)
            s += rng.uniform(*st.kerb_spacing)


class _Line:
    """A polyline parametrised by arc length."""

    def __init__(self, points: np.ndarray) -> None:
        step = np.linalg.norm(np.diff(points, axis=0), axis=1)
        keep = np.concatenate([[True], step > 1e-6])
        self.points = points[keep]
        self.s = np.concatenate([[0.0], np.cumsum(step[step > 1e-6])])
        self.length = float(self.s[-1])

    def at(self, s: float) -> np.ndarray:
        s = float(np.clip(s, 0.0, self.length))
        return np.array([np.interp(s, self.s, self.points[:, 0]), np.interp(s, self.s, self.points[:, 1])])

    def chord(self, s0: float, s1: float) -> np.ndarray:
        """Unit direction from the point at ``s0`` to the point at ``s1`` (the local street direction)."""
        d = self.at(s1) - self.at(s0)
        norm = float(np.linalg.norm(d))
        if norm < 1e-9:
            return np.array([1.0, 0.0])
        return d / norm
