"""Global maps from the optimised anchors: the occupancy grid (local grids per submap fused; 2D
lasers, and 3D LiDAR through the obstacle slice of each scan) and the fused point cloud."""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from ..child_process import usable_cores
from ..geometry import transform_points
from ..result import SlamResult
from .evidence_grid import EvidenceGrid, GridParams, fuse_submap_grids
from .tiled_grid import TiledLogOdds

if TYPE_CHECKING:
    from .grid_process import GridsBeside

LocalGridJob = tuple[int, np.ndarray, list[np.ndarray], list[np.ndarray]]
# one submap's local grid to make elsewhere: (key, T_anchor_scans (K, 4, 4), scan points [(n_k, 3)],
# per scan the ends of its beams that returned nothing [(m_k, 3)], empty when the log has none)


#: a run's map fusion makes local grids in a child process (``grid_process``) only from
#: this many submaps on: below it the child's start-up (~0.5 s) outweighs what it takes off
MIN_SUBMAPS_BESIDE = 8


def grid_process_wanted(result: SlamResult) -> bool:
    """Whether a run's map fusion makes most of its local grids in a child process
    (``mapping.grid_process``; None: a planar run, when this process may use more than one core).
    A 3D run's fusion is mostly its cloud, not its grid: on terrain 08 (600 scans) the child took
    nothing off the fusion's 3.1-3.4 s and added 15 MiB to this process's peak (the jobs it sent)."""
    wanted = result.config.mapping.grid_process
    return result.planar and usable_cores() > 1 if wanted is None else bool(wanted)


def local_grid_jobs(result: SlamResult, ids: Iterable[int]) -> list[LocalGridJob]:
    """The jobs for the local grids of ``result``'s submaps ``ids`` (keyed by id)."""
    return [(i, result.submap_scan_poses[i], result.submap_scan_points[i], result.no_returns_of(i)) for i in ids]


def job_grid(job: LocalGridJob, params: GridParams) -> EvidenceGrid | None:
    """The local grid of ``job``: what :func:`build_global_grid` makes of that submap."""
    _, poses, points, no_returns = job
    return local_grid(poses, points, params, no_returns)


def local_grid(T_anchor_scans: np.ndarray, scan_points: list[np.ndarray], params: GridParams,
               no_returns: list[np.ndarray] | None = None, extent: np.ndarray | None = None) -> EvidenceGrid | None:
    """Evidence grid of one submap in its anchor frame from its scans (``(n_k, 3)`` sensor frame);
    ``no_returns``: per scan the ends of its beams that returned nothing (free, never hit; they
    do not widen the grid). ``extent``: the scans' :func:`local_extent` when known (not computed
    again)."""
    if extent is None:
        extent = local_extent(T_anchor_scans, scan_points)
    if extent is None:
        return None
    grid = EvidenceGrid.covering(extent, params)
    if no_returns:
        no_returns = list(no_returns)  # spilled (:mod:`.scan_spill`): read once, not a scan at a time
    for n, (T, pts) in enumerate(zip(T_anchor_scans, scan_points)):
        free = no_returns[n] if no_returns and n < len(no_returns) else None
        grid.integrate_scan(T, pts, carve_free=n % params.free_scan_stride == 0, no_returns=free)
    return grid


def grid_params(result: SlamResult) -> GridParams:
    """Grid parameters for a run: the config's evidence model (``mapping.grid``) at the cell size
    for the log's kind; 3D LiDAR carves free space farther."""
    mapping = result.config.mapping
    if result.planar:
        return mapping.grid.model_copy(update={"resolution": mapping.grid_resolution})
    return mapping.grid.model_copy(update={"resolution": mapping.grid_resolution_3d,
                                           "max_free_range": mapping.grid_max_free_range_3d})


def local_extent(T_anchor_scans: np.ndarray, scan_points: list[np.ndarray]) -> np.ndarray | None:
    """``(2, 2)`` min/max corners (anchor frame, x y) of a submap's scans and their poses."""
    lo, hi = T_anchor_scans[:, :2, 3].min(axis=0), T_anchor_scans[:, :2, 3].max(axis=0)
    seen = False
    for T, pts in zip(T_anchor_scans, scan_points):
        if len(pts):
            xy = transform_points(T, pts)[:, :2]
            lo, hi = np.minimum(lo, xy.min(axis=0)), np.maximum(hi, xy.max(axis=0))
            seen = True
    return np.stack([lo, hi]) if seen else None


def build_global_grid(result: SlamResult, params: GridParams | None = None,
                      session_starts: list[int] | None = None,
                      left_between_sessions: list[np.ndarray] | None = None,
                      local_grids: Iterable[EvidenceGrid | None] | None = None,
                      beside: GridsBeside | None = None) -> tuple[EvidenceGrid | TiledLogOdds, int]:
    """Fuse every submap's local grid in time order; return the grid and cells cleared as dynamic.

    The grid is a :class:`~.tiled_grid.TiledLogOdds` (tiles only where the submaps wrote: the
    bounding box of a long drive is mostly cells no scan saw), or with ``left_between_sessions``
    a dense :class:`EvidenceGrid` (the sessions' masks are the whole grid's shape).

    ``session_starts``: the first submap of each session (ascending); with it the empty list
    ``left_between_sessions`` receives the grid-shaped bool mask of the cells a session cleared
    that were occupied when it began (what an earlier session saw and a later one saw gone; not
    what a session saw come and go itself). ``local_grids``: every submap's :func:`local_grid`
    at ``params``, in submap order, made elsewhere (``batch`` on Ray: ahead, on idle cores);
    None: made here, or most of them by ``beside`` (:class:`~.grid_process.GridsBeside`, at
    ``params``) in a child process.

    Two passes over the submaps: the first finds the extent, the second builds each local grid
    and fuses it at once, so memory holds the global grid and one local grid, not all of them
    (on a 3.7 km drive every local grid at once was gigabytes).
    """
    params = params or grid_params(result)
    corners = []
    extents = []  # each submap's local_extent, for its local grid
    for T_world_anchor, poses, points in zip(result.submap_poses, result.submap_scan_poses,
                                             result.submap_scan_points):
        extent = local_extent(poses, points)
        extents.append(extent)
        if extent is None:
            continue
        (x0, y0), (x1, y1) = extent - [[params.resolution] * 2, [-params.resolution] * 2]
        box = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x0, y1, 0.0], [x1, y1, 0.0]])
        corners.append(transform_points(T_world_anchor, box)[:, :2])
    if not corners:
        raise ValueError("no scans to build a grid from")
    starts = set(session_starts or []) - {0}
    track = left_between_sessions is not None
    global_grid = (EvidenceGrid.covering(np.vstack(corners), params, margin=1.5, track_free_runs=False) if track
                   else TiledLogOdds.covering(np.vstack(corners), params, margin=1.5))
    left = np.zeros(global_grid.logodds.shape, dtype=bool) if track else None
    occupied_at_start = None  # while a later session fuses: what was occupied when it began
    cleared = 0
    made = iter(local_grids) if local_grids is not None else None
    for k, (T_world_anchor, poses, points) in enumerate(zip(result.submap_poses, result.submap_scan_poses,
                                                            result.submap_scan_points)):
        if track and k in starts:
            occupied_at_start = global_grid.logodds > params.occupied_threshold
        no_returns = result.no_returns_of(k)
        if made is not None:
            grid = next(made)
        elif beside is not None:
            grid = beside.take(k, partial(local_grid, poses, points, params, no_returns, extents[k]))
        else:
            grid = local_grid(poses, points, params, no_returns, extents[k])
        if grid is not None:
            cleared += fuse_submap_grids(global_grid, grid, T_world_anchor,
                                         left if occupied_at_start is not None else None, occupied_at_start)
    if track:
        left_between_sessions.append(left)
    return global_grid, cleared


def vacated_cells(cleared: np.ndarray, logodds: np.ndarray) -> np.ndarray:
    """Cells where something left: the ``cleared`` cells (e.g. :func:`build_global_grid`'s
    ``left_between_sessions``) and those around them (a thing's edge cells, hit too rarely to
    count as occupied, are not cleared themselves) that the grid's ``logodds`` now hold more free
    than occupied — not a wall beside them, nor a cell occupied again later."""
    from scipy.ndimage import binary_dilation

    return binary_dilation(cleared, structure=np.ones((3, 3), dtype=bool)) & (logodds < 0)


def points_in_vacated_cells(points: np.ndarray, grid: EvidenceGrid, vacated: np.ndarray,
                            min_height: float, max_height: float, chunk_points: int = 200_000) -> np.ndarray:
    """``(N,)`` bool: the world points ``(N, 3)`` standing where the grid saw something leave —
    in a ``vacated`` cell (:func:`vacated_cells`) and between ``min_height`` and
    ``max_height`` [m] above the ground there (the lowest point of the cell and its 8 neighbours:
    a later session sees the ground where a car stood). The grid only knows that band, so
    nothing above it (a roof, a canopy) or on the ground is taken."""
    out = np.zeros(len(points), dtype=bool)
    if not len(points) or not vacated.any():
        return out
    from scipy.ndimage import binary_dilation

    rows, cols = vacated.shape
    # only the points in and around vacated cells, keyed by cell, found a chunk of points at a
    # time: memory as their number, not the grid's (a city grid is 10 M cells) nor the map's
    rows_v, cols_v = np.nonzero(vacated)
    r0, c0 = max(int(rows_v.min()) - 1, 0), max(int(cols_v.min()) - 1, 0)
    r1, c1 = min(int(rows_v.max()) + 2, rows), min(int(cols_v.max()) + 2, cols)
    near_box = binary_dilation(vacated[r0:r1, c0:c1], structure=np.ones((3, 3), dtype=bool))
    found = []
    for lo in range(0, len(points), chunk_points):
        r, c, inside = grid.cells(np.asarray(points[lo:lo + chunk_points, :2], dtype=np.float64))
        inside &= (r >= r0) & (r < r1) & (c >= c0) & (c < c1)
        k = np.flatnonzero(inside)
        k = k[near_box[r[k] - r0, c[k] - c0]]
        found.append((lo + k, r[k], c[k]))
    take, r_take, c_take = (np.concatenate(a) for a in zip(*found))
    is_cand = vacated[r_take, c_take]
    if not is_cand.any():
        return out
    stride = cols + 2  # a key per cell; a neighbour across the grid's edge matches no cell
    key = r_take * stride + c_take + 1
    cells, inverse = np.unique(key, return_inverse=True)
    floor = np.full(len(cells), np.inf)  # the lowest point of each such cell
    np.minimum.at(floor, inverse, points[take, 2])
    cand, cand_key = take[is_cand], key[is_cand]
    ground = np.full(len(cand), np.inf)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            q = cand_key + dr * stride + dc
            pos = np.minimum(np.searchsorted(cells, q), len(cells) - 1)
            ground = np.where(cells[pos] == q, np.minimum(ground, floor[pos]), ground)
    height = points[cand, 2] - ground
    out[cand[(height >= min_height) & (height <= max_height)]] = True
    return out


_KEY_BITS = 21  # per axis: +-2^20 voxels (419 km at 0.4 m, 52 km at 5 cm)


def _voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """One int64 key ``(N,)`` per point: its voxel's integer coordinates packed 21 bits each."""
    cells = np.floor(points / voxel).astype(np.int64) + (1 << (_KEY_BITS - 1))
    return (cells[:, 0] << (2 * _KEY_BITS)) | (cells[:, 1] << _KEY_BITS) | cells[:, 2]


def fuse_clouds(clouds: Iterable[tuple[np.ndarray, np.ndarray]], voxel: float,
                chunk_points: int = 300_000, with_keys: bool = False):
    """Clouds ``(T_world_cloud (4, 4), points (N, 3))`` fused into one float32 ``(M, 3)`` world
    cloud, the first point of each ``voxel`` [m] kept (clouds in the given order). ``with_keys``:
    ``(cloud, keys)``, ``keys`` ``(M,)`` int64 the voxel each point was kept for (computed from
    the float64 world point, so exact where the float32 copy sits on a voxel's face).

    Streaming: the clouds are moved into the world frame about ``chunk_points`` points at a time;
    a chunk's voxels not yet in the map are appended. Memory holds the map (three float32 a
    point, kept in pieces) and its sorted voxel keys, plus one chunk — not every cloud in the
    world frame at once, nor a hash map over all of them (a 3.7 km drive took 300 MB more that
    way).
    """
    keys = np.zeros(0, dtype=np.int64)  # sorted voxel keys of the map
    pieces: list[np.ndarray] = []
    piece_keys: list[np.ndarray] = []
    chunk: list[np.ndarray] = []
    size = 0

    def merge() -> None:
        nonlocal keys
        pts = np.vstack(chunk)
        chunk_keys, first = np.unique(_voxel_keys(pts, voxel), return_index=True)
        pos = np.searchsorted(keys, chunk_keys)
        known = pos < len(keys)
        known[known] = keys[pos[known]] == chunk_keys[known]
        pieces.append(pts[first[~known]].astype(np.float32))
        if with_keys:
            piece_keys.append(chunk_keys[~known])
        keys = np.insert(keys, pos[~known], chunk_keys[~known])

    for T, points in clouds:
        chunk.append(np.asarray(points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3])
        size += len(points)
        if size >= chunk_points:
            merge()
            chunk, size = [], 0
    if chunk:
        merge()
    del keys
    cloud = np.concatenate(pieces) if pieces else np.zeros((0, 3), dtype=np.float32)
    if with_keys:
        return cloud, np.concatenate(piece_keys) if piece_keys else np.zeros(0, dtype=np.int64)
    return cloud


def find_voxels(keys: np.ndarray, sorted_keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(pos, found)``, each ``(N,)``: where each of ``keys`` ``(N,)`` sits in ``sorted_keys``
    (ascending int64) and whether it is there (``pos`` is meaningful only where ``found``)."""
    if not len(sorted_keys):
        return np.zeros(len(keys), dtype=np.int64), np.zeros(len(keys), dtype=bool)
    pos = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return pos, sorted_keys[pos] == keys


def in_voxels(keys: np.ndarray, sorted_keys: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: each of ``keys`` ``(N,)`` is among ``sorted_keys`` (ascending int64)."""
    return find_voxels(keys, sorted_keys)[1]


def cloud_counts(clouds: Iterable[tuple[np.ndarray, np.ndarray]], voxel: float,
                 chunk_keys: int = 300_000) -> tuple[np.ndarray, np.ndarray]:
    """``(keys, counts)``: the sorted int64 keys ``(V,)`` of the ``voxel`` [m] cells that the clouds
    ``(T_world_cloud (4, 4), points (N, 3))`` have a point in, and per cell how many of the clouds
    have one ``(V,)`` int64. Streaming: about ``chunk_keys`` cell keys are held besides the result."""
    keys = np.zeros(0, dtype=np.int64)
    counts = np.zeros(0, dtype=np.int64)
    pending: list[np.ndarray] = []
    size = 0

    def merge() -> None:
        nonlocal keys, counts
        keys, inverse = np.unique(np.concatenate([keys, *pending]), return_inverse=True)
        weights = np.concatenate([counts, np.ones(size, dtype=np.int64)])
        counts = np.zeros(len(keys), dtype=np.int64)
        np.add.at(counts, inverse.reshape(-1), weights)

    for T, points in clouds:
        if len(points):
            pending.append(np.unique(_voxel_keys(transform_points(T, points), voxel)))
            size += len(pending[-1])
            if size >= chunk_keys:
                merge()
                pending, size = [], 0
    if pending:
        merge()
    return keys, counts


def near_own_path(T_anchor_scans: np.ndarray, points: np.ndarray, reach: float) -> np.ndarray:
    """``(N,)`` bool: anchor-frame ``points`` ``(N, 3)`` within ``reach`` [m] of a scan position of
    their submap (``T_anchor_scans`` ``(K, 4, 4)``)."""
    points = np.asarray(points, dtype=np.float64)
    nearest = np.full(len(points), np.inf)
    for position in np.asarray(T_anchor_scans)[:, :3, 3]:
        nearest = np.minimum(nearest, np.einsum("ij,ij->i", points - position, points - position))
    return nearest <= reach * reach


def voxels_left(result: SlamResult, voxel: float, reach: float) -> np.ndarray:
    """Sorted int64 keys of the ``voxel`` [m] cells whose verdict is *moved*: at least as many
    submaps took points out of them as moved, each within ``reach`` [m] of its own path, as kept
    a point there. A submap keeps whatever it has no evidence against, while a split's verdict
    is evidence (beams through the place): a near verdict outweighs one submap's keeping."""
    moved_clouds = ((T, p[near_own_path(result.submap_scan_poses[i], p, reach)])
                    for i, (T, p) in enumerate(zip(result.submap_poses, result.submap_dynamic_points))
                    if p is not None and len(p))
    moved, moved_by = cloud_counts(moved_clouds, voxel)
    kept_by = np.zeros(len(moved), dtype=np.int64)  # per moved cell, the submaps that kept a point there
    if len(moved):
        for T, points in zip(result.submap_poses, result.submap_points):
            if len(points):
                keys = np.unique(_voxel_keys(transform_points(T, points), voxel))  # each cell once a submap
                pos, found = find_voxels(keys, moved)
                kept_by[pos[found]] += 1
    return moved[moved_by >= kept_by]


def _not_held(moved: np.ndarray, moved_keys: np.ndarray, map_keys: np.ndarray) -> tuple[np.ndarray, int]:
    """The ``moved`` points ``(D, 3)`` whose voxels (``moved_keys`` ``(D,)``) the map's
    (``map_keys`` ``(M,)``) do not hold, and how many it held."""
    held = in_voxels(moved_keys, np.sort(map_keys))
    return moved[~held], int(held.sum())


def fused_map(result: SlamResult, voxel: float | None = None) -> np.ndarray:
    """All submap clouds in the world frame, fused at ``voxel`` (default: the run's map voxel)."""
    return fuse_clouds(zip(result.submap_poses, result.submap_points), voxel or result.map_voxel_size)


@dataclass
class MapOutputs:
    """The maps of a run, built from its result (what ``write_results`` writes).

    ``points``: ``(M, 3)`` float32 fused cloud in the world frame; ``grid``: the global grid's
    occupancy (None when the run has no grid): a :class:`~.tiled_grid.TiledLogOdds`, whose
    probabilities a writer takes a band of rows at a time, or the ``(rows, cols)`` float32
    probabilities themselves (a map of several 3D sessions); :attr:`occupancy` is them, dense, with
    the grid's ``origin`` ``(2,)`` [m] and ``resolution`` [m]; ``cleared_cells``: occupied cells later
    submaps saw free (what moved); ``seconds``: wall time spent building them;
    ``dynamic_points``: ``(D, 3)`` float32 world cloud of what the run found moving (3D runs with
    ``mapping.split_movers``), else None; it shares no voxel with ``points``.
    """

    points: np.ndarray
    grid: TiledLogOdds | np.ndarray | None = None
    origin: np.ndarray | None = None
    resolution: float = 0.0
    cleared_cells: int = 0
    seconds: float = 0.0
    dynamic_points: np.ndarray | None = None
    vacated_points: int = 0  # of ``points``, moved to ``dynamic_points`` where the grid saw something leave
    moved_points_in_map: int = 0  # split off a submap where another submap's point keeps the voxel in ``points``
    left_points: int = 0  # of the fused map, voxels more submaps (near their paths) saw move than kept
    #: when a child process made local grids: its peak [MiB], how many it made, and this
    #: process's largest resident set [MiB] while it ran (sampled as each grid was taken); else None
    grid_process: dict | None = None

    @property
    def occupancy(self) -> np.ndarray | None:
        """``(rows, cols)`` float32 occupancy probabilities of the whole grid, row 0 = lowest y
        (dense: a tiled grid's are made on each call), or None without a grid."""
        return self.grid.probabilities() if isinstance(self.grid, TiledLogOdds) else self.grid


def build_map_outputs(result: SlamResult, session_starts: list[int] | None = None,
                      local_grids: Iterable[EvidenceGrid | None] | None = None,
                      grid_process: bool = False) -> MapOutputs:
    """Fuse the map cloud and, when the run keeps grid scans, the occupancy grid.

    ``session_starts`` (a map of several sessions: each one's first submap; 3D, with a grid): the
    cloud's points where the grid saw something leave between sessions
    (:func:`points_in_vacated_cells`) go to the dynamic cloud — a car parked in one session and
    gone in a later one. ``local_grids``: the submaps' local grids made elsewhere
    (:func:`build_global_grid`); ``grid_process``: most of them made in a child process while
    this one makes the cloud and the rest (:class:`~.grid_process.GridsBeside`).

    A map voxel leaves the map (``left_points``) when at least as many submaps took it out as
    moved, near their own paths, as kept it (``mapping.moved_verdict_range``, :func:`voxels_left`).
    The two clouds share no voxel: what a split took out where the map still holds the place
    (more submaps kept a point in that voxel, or the split's verdict came from farther out) is not
    reported as moved (``moved_points_in_map``)."""
    t0 = time.perf_counter()
    grid_scans = result.config.mapping.write_grid and any(len(p) for scans in result.submap_scan_points for p in scans)
    beside = None
    if grid_process and grid_scans and local_grids is None and len(result.submap_poses) >= MIN_SUBMAPS_BESIDE:
        from .grid_process import GridsBeside

        # started first: the child makes its first grids while this process fuses the cloud
        beside = GridsBeside(len(result.submap_poses), lambda k: local_grid_jobs(result, [k])[0], grid_params(result))
    try:
        out = _build_map_outputs(result, session_starts, local_grids, beside, grid_scans)
    finally:
        if beside is not None:
            beside.close()
    if beside is not None:
        out.grid_process = {"peak_mb": round(beside.child_peak_mb, 1), "grids": beside.made_beside,
                            "main_mb_while_child": round(beside.main_mb_while_child, 1)}
    out.seconds = time.perf_counter() - t0
    return out


def _build_map_outputs(result: SlamResult, session_starts: list[int] | None,
                       local_grids: Iterable[EvidenceGrid | None] | None, beside: GridsBeside | None,
                       grid_scans: bool) -> MapOutputs:
    """:func:`build_map_outputs`'s work (``grid_scans``: the run kept scans for a grid)."""
    voxel = result.map_voxel_size
    points, map_keys = fuse_clouds(zip(result.submap_poses, result.submap_points), voxel, with_keys=True)
    out = MapOutputs(points=points)
    del points  # held by ``out`` alone: the filtered clouds below replace it rather than join it
    moved, moved_keys = None, None
    if result.submap_dynamic_points is not None:
        moved, moved_keys = fuse_clouds(((T, p) for T, p in zip(result.submap_poses, result.submap_dynamic_points)
                                         if p is not None), voxel, with_keys=True)
        reach = result.config.mapping.moved_verdict_range
        if reach > 0:
            stays = ~in_voxels(map_keys, voxels_left(result, voxel, reach))
            out.left_points = int((~stays).sum())
            out.points, map_keys = out.points[stays], map_keys[stays]
    vacate = grid_scans and bool(session_starts) and len(session_starts) > 1 and not result.planar
    if not vacate:  # the map's voxels are final: their keys need not stay beside the grid
        if moved is not None:
            moved, out.moved_points_in_map = _not_held(moved, moved_keys, map_keys)
        moved_keys = map_keys = None
    gone = None
    if grid_scans:
        left: list[np.ndarray] = []
        grid, out.cleared_cells = build_global_grid(result, session_starts=session_starts if vacate else None,
                                                    left_between_sessions=left if vacate else None,
                                                    local_grids=local_grids, beside=beside)
        if vacate:
            mapping = result.config.mapping
            vacated = vacated_cells(left[0], grid.logodds)
            in_vacated = points_in_vacated_cells(out.points, grid, vacated, mapping.grid_min_height,
                                                 mapping.grid_max_height)
            if in_vacated.any():
                gone = out.points[in_vacated]
                out.points, map_keys = out.points[~in_vacated], map_keys[~in_vacated]
            out.vacated_points = int(in_vacated.sum())
        out.grid = grid if isinstance(grid, TiledLogOdds) else grid.probabilities(consume=True)
        out.origin, out.resolution = grid.origin, grid.params.resolution
    if moved is not None and vacate:
        moved, out.moved_points_in_map = _not_held(moved, moved_keys, map_keys)
    parts = [c for c in (moved, gone) if c is not None]
    out.dynamic_points = np.vstack(parts) if parts else None
    return out
