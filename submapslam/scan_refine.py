"""Scan-level refinement of a planar run after the submap solve (Cartographer's structure).

The submap graph has one node per submap; a scan's pose inside its submap is where odometry
put it. Here every keyframe scan becomes a node of a planar pose graph
(:mod:`submapslam.backend.scan_graph`), with

* odometry between consecutive keyframes (the drift model of :class:`ScanRefineConfig`);
* a prior holding each submap anchor (a keyframe) where the submap solve put it, under a Cauchy
  kernel: the global structure the loops gave stays, unless many matches contradict an anchor;
* scan-to-submap matches: each keyframe against the *other* submaps near it, point-to-line in
  the submap's cloud (:func:`~submapslam.registration.scan_to_submap.match_scans`), from the
  current estimate, gated by fitness, RMSE and the size of the correction, under a robust
  kernel. The factor ties the scan to the matched submap's keyframe nearest to it (where the
  odometry placed that keyframe in the cloud): a cloud is trusted locally.

Matched and solved ``rounds`` times. Scans between keyframes take the correction of the
keyframes around them, blended by scan index. Frames: world = the first scan's frame; poses
``(x, y, yaw)`` [m, rad].
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from .backend.scan_graph import PlanarEdge, solve_planar_graph
from .config import ScanRefineConfig
from .geometry import se2_array_to_matrices, wrap_angle
from .registration.point_to_line import line_normals
from .registration.scan_to_submap import match_scans

log = logging.getLogger(__name__)


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SE(2) ``a ∘ b`` of ``(..., 3)`` poses."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([a[..., 0] + c * b[..., 0] - s * b[..., 1], a[..., 1] + s * b[..., 0] + c * b[..., 1],
                     wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def _between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SE(2) ``a^-1 ∘ b`` of ``(..., 3)`` poses."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[..., 2] - a[..., 2])], axis=-1)


def _inverse(a: np.ndarray) -> np.ndarray:
    return _between(a, np.zeros_like(a))


@dataclass
class RefinedScans:
    """Result of :func:`refine_scans`: ``poses`` ``(N, 4, 4)`` ``T_world_scan`` of every scan,
    ``keyframes`` ``(K,)`` the scan indices that were graph nodes, and figures for the summary."""

    poses: np.ndarray
    keyframes: np.ndarray
    stats: dict = field(default_factory=dict)


def select_keyframes(odom_xyt: np.ndarray, forced: np.ndarray, step_m: float, step_deg: float) -> np.ndarray:
    """Scan indices ``(K,)`` ascending: the first and last scan, every ``forced`` one, and each scan
    ``step_m`` [m] or ``step_deg`` [deg] of odometry away from the keyframe before it."""
    keep = np.zeros(len(odom_xyt), dtype=bool)
    keep[[0, len(odom_xyt) - 1]] = True
    keep[np.asarray(forced, dtype=int)] = True
    step_rad = np.deg2rad(step_deg)
    last = odom_xyt[0]
    for i, p in enumerate(odom_xyt.tolist()):
        if keep[i] or (p[0] - last[0]) ** 2 + (p[1] - last[1]) ** 2 >= step_m**2 \
                or abs(wrap_angle(p[2] - last[2])) >= step_rad:
            keep[i] = True
            last = p
    return np.flatnonzero(keep)


def _odometry_edges(odom_xyt: np.ndarray, keyframes: np.ndarray, cfg: ScanRefineConfig) -> list[PlanarEdge]:
    """Between-factors from the odometry between consecutive keyframes (drift model)."""
    d = _between(odom_xyt[keyframes[:-1]], odom_xyt[keyframes[1:]])
    path = np.hypot(d[:, 0], d[:, 1])
    s_t = cfg.odometry_sigma_m + cfg.odometry_drift * path
    s_r = np.deg2rad(cfg.odometry_sigma_deg) + cfg.odometry_turn_fraction * np.abs(d[:, 2])
    return [PlanarEdge(k, k + 1, d[k], np.diag([1 / s_t[k] ** 2, 1 / s_t[k] ** 2, 1 / s_r[k] ** 2]), False)
            for k in range(len(d))]


def _match_edges(xyt: np.ndarray, odom_xyt: np.ndarray, keyframes: np.ndarray, scans: dict[int, np.ndarray],
                 owners: list[list[int]], anchors: list[int], clouds: list[tuple[np.ndarray, np.ndarray]],
                 members: list[np.ndarray], cfg: ScanRefineConfig) -> tuple[list[PlanarEdge], int]:
    """Scan-to-submap between-factors of every keyframe at the node poses ``xyt`` ``(K, 3)``, and
    the number of matches tried. ``members``: each submap's keyframe nodes.

    A keyframe is matched against a submap's whole cloud, but the factor ties it to that submap's
    keyframe nearest to it (whose place in the cloud the odometry gave): a cloud is trusted
    locally, so a submap the odometry bent inside is not imposed rigidly on its neighbours."""
    pairs: dict[int, list[tuple[int, int]]] = {}  # submap -> (node, the submap's node nearest to it)
    counts = np.array([len(p) for p in members])
    if not counts.sum():
        return [], 0
    all_nodes = np.concatenate([p for p in members if len(p)])
    all_pos = xyt[all_nodes, :2]
    which = np.repeat(np.arange(len(members)), counts)
    tree = cKDTree(all_pos)
    for k, hits in _hits_in_blocks(tree, xyt[:, :2], cfg.match_radius_m):
        if not hits:
            continue
        hits = np.asarray(hits)
        dist = (all_pos[hits, 0] - xyt[k, 0]) ** 2 + (all_pos[hits, 1] - xyt[k, 1]) ** 2
        order = hits[np.argsort(dist, kind="stable")]
        _, first = np.unique(which[order], return_index=True)
        own = owners[keyframes[k]]
        chosen = [int(h) for h in order[np.sort(first)] if which[h] not in own][:cfg.max_submaps_per_scan]
        for h in chosen:  # nearest first
            pairs.setdefault(int(which[h]), []).append((k, int(all_nodes[h])))
    edges: list[PlanarEdge] = []
    tried = 0
    floor = np.diag([cfg.match_sigma_floor_m**2] * 2 + [np.deg2rad(cfg.match_sigma_floor_deg) ** 2])
    for m, items in pairs.items():
        nodes = np.array([k for k, _ in items])
        near = np.array([j for _, j in items])
        a = anchors[m]
        # each scan in submap m's anchor frame, as the current estimate places it
        guesses = _between(xyt[near], xyt[nodes])
        in_cloud = _between(odom_xyt[a][None, :], odom_xyt[keyframes[near]])  # the near keyframes in the cloud
        guesses = _compose(in_cloud, guesses)
        tried += len(nodes)
        reach = cfg.max_correspondence_m
        res = match_scans(clouds[m][0], clouds[m][1], [scans[keyframes[k]] for k in nodes], guesses,
                          reaches=(reach, 0.5 * (reach + 0.1), 0.1, 0.1), cell=cfg.grid_cell_m)
        jump = _between(guesses, res.xyt)
        ok = (res.fitness >= cfg.min_fitness) & (res.inlier_rmse <= cfg.max_inlier_rmse_m) \
            & (np.hypot(jump[:, 0], jump[:, 1]) <= cfg.max_correction_m) \
            & (np.abs(jump[:, 2]) <= np.deg2rad(cfg.max_correction_deg))
        keep = np.flatnonzero(ok)
        info = res.information[keep]
        # the registration's covariance plus a floor (1 cm / 1 deg by default): the odometry holds rotation better
        cov = np.linalg.inv(0.5 * (info + np.swapaxes(info, 1, 2)) + 1e-9 * np.eye(3)) + floor
        measured = _between(in_cloud[keep], res.xyt[keep])  # the scan in the near keyframe's frame
        for q, inf, meas in zip(keep.tolist(), np.linalg.inv(cov), measured):
            edges.append(PlanarEdge(int(near[q]), int(nodes[q]), meas, inf, True))
    return edges, tried


def _hits_in_blocks(tree: cKDTree, xy: np.ndarray, radius: float, block: int = 256
                    ) -> Iterator[tuple[int, list[int]]]:
    """``(k, rows of the tree's points within radius [m] of xy[k])`` for each of ``xy (K, 2)``,
    queried a block at a time: the hit lists of a long log's every keyframe at once (Python ints)
    were tens of MB at the end of a run."""
    for start in range(0, len(xy), block):
        yield from enumerate(tree.query_ball_point(xy[start:start + block], radius), start)


def anchor_sigmas(odom_anchors: np.ndarray, world_anchors: np.ndarray, cfg: ScanRefineConfig
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Sigmas ``(S,)`` [m] and ``(S,)`` [rad] of the priors holding the ``S`` submap anchors
    (``(S, 3)`` poses by odometry and after the submap solve): at least ``anchor_sigma_m`` /
    ``anchor_sigma_deg``, and ``anchor_bend_factor`` times how far the solve bent the odometry
    between the anchor and its neighbours (the larger of its two submap steps). Where the loops
    had to bend the chain, the solve placed the anchor from little evidence, so the scans' matches
    may move it further; elsewhere it is held."""
    sigma_m = np.full(len(odom_anchors), cfg.anchor_sigma_m)
    sigma_rad = np.full(len(odom_anchors), np.deg2rad(cfg.anchor_sigma_deg))
    if len(odom_anchors) < 2 or not cfg.anchor_bend_factor:
        return sigma_m, sigma_rad
    bend = _between(_between(odom_anchors[:-1], odom_anchors[1:]), _between(world_anchors[:-1], world_anchors[1:]))
    step_m, step_rad = np.hypot(bend[:, 0], bend[:, 1]), np.abs(bend[:, 2])
    for sig, step in ((sigma_m, step_m), (sigma_rad, step_rad)):
        sig[:-1] = np.maximum(sig[:-1], cfg.anchor_bend_factor * step)
        sig[1:] = np.maximum(sig[1:], cfg.anchor_bend_factor * step)
    return sigma_m, sigma_rad


def refine_scans(odom_xyt: np.ndarray, world_xyt: np.ndarray, submap_scan_indices: list[list[int]],
                 submap_points: list[np.ndarray], scan_points: list[np.ndarray],
                 cfg: ScanRefineConfig, wall_noise_m: float = 0.0) -> RefinedScans:
    """Refine every scan's world pose after the submap solve.

    ``odom_xyt`` ``(N, 3)``: each scan's odometry pose; ``world_xyt`` ``(N, 3)``: its pose after
    the submap solve (the initial estimate); ``submap_scan_indices``: the scans of each submap
    (the first is its anchor); ``submap_points``: each submap's ``(M, >=2)`` cloud in its anchor
    frame; ``scan_points``: each scan's ``(n, >=2)`` points in its sensor frame; ``wall_noise_m``
    [m]: the laser's scatter across walls the odometry measured (:mod:`.registration.wall_noise`),
    which the submaps' line test allows for.
    """
    t0 = time.perf_counter()
    n = len(odom_xyt)
    anchors = [int(idx[0]) for idx in submap_scan_indices]
    keyframes = select_keyframes(odom_xyt, np.array(anchors, dtype=int), cfg.keyframe_step_m, cfg.keyframe_step_deg)
    node_of = {int(i): k for k, i in enumerate(keyframes)}
    owners: list[list[int]] = [[] for _ in range(n)]
    for m, idx in enumerate(submap_scan_indices):
        for i in idx:
            owners[i].append(m)
    clouds = []
    for p in submap_points:
        xy = np.ascontiguousarray(np.asarray(p)[:, :2], dtype=np.float64)
        clouds.append((xy, line_normals(xy, cKDTree(xy), noise_m=wall_noise_m) if len(xy) >= 7
                       else np.full((len(xy), 2), np.nan)))
    scans: dict[int, np.ndarray] = {}  # keyframes only
    for i in keyframes.tolist():
        xy = np.ascontiguousarray(np.asarray(scan_points[i])[:, :2], dtype=np.float64)
        if len(xy) > cfg.max_scan_points:
            xy = xy[np.linspace(0, len(xy) - 1, cfg.max_scan_points).astype(int)]
        scans[i] = xy
    odo_edges = _odometry_edges(odom_xyt, keyframes, cfg)
    members = [np.array([node_of[i] for i in idx if i in node_of], dtype=int) for idx in submap_scan_indices]
    xyt = np.array(world_xyt[keyframes], dtype=np.float64)
    priors = []
    if cfg.anchor_sigma_m is not None:
        sigma_m, sigma_rad = anchor_sigmas(odom_xyt[anchors], world_xyt[anchors], cfg)
        priors = [(node_of[a], np.diag([sm**-2, sm**-2, sr**-2])) for a, sm, sr in zip(anchors, sigma_m, sigma_rad)]
    n_edges = tried = 0
    for _ in range(cfg.rounds):
        matches, tried = _match_edges(xyt, odom_xyt, keyframes, scans, owners, anchors, clouds, members, cfg)
        n_edges = len(matches)
        xyt = solve_planar_graph(xyt, odo_edges + matches, kernel=cfg.kernel, priors=priors,
                                 prior_kernel=cfg.anchor_kernel)
    # every scan: the correction of the keyframes around it, blended by scan index
    corr = _compose(xyt, _inverse(odom_xyt[keyframes]))  # world <- odometry, per keyframe
    k_next = np.clip(np.searchsorted(keyframes, np.arange(n), side="left"), 0, len(keyframes) - 1)
    k_prev = np.clip(np.where(keyframes[k_next] == np.arange(n), k_next, k_next - 1), 0, len(keyframes) - 1)
    span = np.maximum(keyframes[k_next] - keyframes[k_prev], 1)
    alpha = (np.arange(n) - keyframes[k_prev]) / span
    ca, cb = corr[k_prev], corr[k_next]
    d = _between(ca, cb)
    blended = _compose(ca, d * alpha[:, None])
    out = _compose(blended, odom_xyt)
    stats = {"keyframes": int(len(keyframes)), "matches_tried": int(tried), "matches_kept": int(n_edges),
             "seconds": round(time.perf_counter() - t0, 3)}
    log.info("scan refinement: %s", stats)
    return RefinedScans(poses=se2_array_to_matrices(out), keyframes=keyframes, stats=stats)
