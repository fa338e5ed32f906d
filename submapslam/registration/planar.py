"""Planar (2D laser) submap matching: FFT correlative search, then point-to-point ICP in SE(2).

Planar clouds (z = 0) make the 3D point-to-plane / GICP systems singular, so planar submaps are
matched entirely in SE(2):

1. coarse: the target is rasterised into a likelihood grid (Gaussian of the distance to the
   nearest target point); for every candidate yaw the rotated source is rasterised and
   cross-correlated with it by FFT, which scores every translation at once (Olson's correlative
   matching, exhaustive over the window). The best and the best well-separated second peak
   are kept: their ratio measures ambiguity.
2. fine: point-to-point ICP with a shrinking correspondence distance (scipy cKDTree).
3. information: Gauss-Newton Hessian of the ICP residuals at the solution, ``(3, 3)`` over
   ``(x, y, yaw)`` of the source pose perturbed in its own frame, scaled by the inlier residual
   variance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy import fft as sfft
from scipy.fft import next_fast_len
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree

from ..geometry import matrix_to_se2, se2_to_matrix
from .kdtree2d import KdTree2D
from .point_to_line import first_point_per_cell, line_normals, point_to_line


@dataclass
class PlanarMatch:
    """Result of :func:`match_planar`; ``xyt`` is the source->target pose ``(x, y, yaw)``."""

    xyt: np.ndarray
    score: float            # mean likelihood of the source points at the coarse optimum, [0, 1]
    ambiguity: float        # second distinct peak / best peak, [0, 1]; near 1 = ambiguous
    fitness: float
    inlier_rmse: float
    information: np.ndarray  # (3, 3) over (x, y, yaw), the source pose perturbed in its own frame

    @property
    def T(self) -> np.ndarray:
        return se2_to_matrix(*self.xyt)


def _rotate(xy: np.ndarray, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return xy @ np.array([[c, s], [-s, c]])


def _subsample(xy: np.ndarray, cell: float, max_points: int, rng: np.random.Generator) -> np.ndarray:
    xy = xy[first_point_per_cell(xy, cell)]
    if len(xy) > max_points:
        xy = xy[rng.choice(len(xy), max_points, replace=False)]
    return xy


def _likelihood_grid(target: np.ndarray, resolution: float, sigma: float, pad_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian-of-distance likelihood of ``(M, 2)`` target points on a padded grid; returns grid, origin."""
    lo = target.min(axis=0) - 1.0 - pad_m
    hi = target.max(axis=0) + 1.0 + pad_m
    shape = [next_fast_len(int(v)) for v in np.ceil((hi - lo) / resolution).astype(int) + 1]
    ij = np.floor((target - lo) / resolution).astype(int)
    # More than 7.5 sigma from every target point the likelihood is below 1e-12: those cells
    # stay 0, and the distance transform runs only on the box around the points (the padding
    # for the search window is mostly that far away).
    reach = int(np.ceil(7.5 * sigma / resolution)) + 1
    a0, b0 = np.maximum(ij.min(axis=0) - reach, 0)
    a1, b1 = np.minimum(ij.max(axis=0) + reach + 1, shape)
    occ = np.zeros((a1 - a0, b1 - b0), dtype=bool)
    occ[ij[:, 0] - a0, ij[:, 1] - b0] = True
    dist = distance_transform_edt(~occ) * resolution
    like = np.zeros(shape)
    like[a0:a1, b0:b1] = np.exp(-0.5 * (dist / sigma) ** 2)
    return like, lo


def _best_peaks(peaks: list[tuple[float, float, float, float]]) -> tuple[np.ndarray, float, float, np.ndarray | None]:
    """Best ``(x, y, yaw)``, its score, the ambiguity ratio of the best well-separated other peak
    and that peak's ``(x, y, yaw)`` (None when there is none)."""
    best = max(peaks, key=lambda p: p[0])
    second, second_xyt = 0.0, None
    for peak in peaks:
        if peak[0] > second and _far(peak[1:], best[1:]):
            second, second_xyt = peak[0], np.array(peak[1:])
    return np.array(best[1:]), best[0], (second / best[0] if best[0] > 0 else 1.0), second_xyt


def _far(a, b) -> bool:
    """Two ``(x, y, yaw)`` peaks (any sequences of three) are distinct: more than 1.5 m or 10
    degrees apart."""
    return bool(np.hypot(a[0] - b[0], a[1] - b[1]) > 1.5 or abs(np.angle(np.exp(1j * (a[2] - b[2])))) > np.deg2rad(10))


def coarse_search(source: np.ndarray, target: np.ndarray, **kwargs) -> tuple[np.ndarray, float, float]:
    """:func:`coarse_peaks` without the second peak's pose: ``(x, y, yaw)``, score, ambiguity."""
    return coarse_peaks(source, target, **kwargs)[:3]


def coarse_peaks(
    source: np.ndarray,
    target: np.ndarray,
    *,
    resolution: float = 0.15,
    sigma: float = 0.2,
    center: np.ndarray | None = None,
    window: float = 15.0,
    yaws: np.ndarray | None = None,
    max_source_points: int = 1000,
) -> tuple[np.ndarray, float, float, np.ndarray | None]:
    """Exhaustive correlative search; ``source``/``target`` are ``(N, 2)`` in their own frames.

    ``center`` is the expected source->target ``(x, y)`` (default 0) and ``window`` the half
    width [m] of the translation search around it. ``yaws`` are the candidate yaws [rad]
    (default: every 1.5 degrees). Small windows are scored directly, large ones by FFT
    cross-correlation. Returns ``(x, y, yaw)``, the score in [0, 1], the ambiguity ratio and the
    best well-separated other peak's ``(x, y, yaw)`` (or None).
    """
    rng = np.random.default_rng(0)
    center = np.zeros(2) if center is None else np.asarray(center, dtype=np.float64)
    if yaws is None:
        yaws = np.deg2rad(np.arange(-180.0, 180.0, 1.5))
    sub = _subsample(source, resolution, max_source_points, rng)
    if len(sub) == 0 or len(target) == 0:
        return np.zeros(3), 0.0, 1.0, None
    c_src = sub.mean(axis=0)
    src = sub - c_src  # rotate about the source centroid: the translation window stays compact
    r_src = float(np.abs(src).max())
    cells = int(np.ceil(window / resolution))
    peaks: list[tuple[float, float, float, float]] = []
    if cells <= 8:
        like, lo = _likelihood_grid(target, resolution, sigma, window + r_src + 2 * resolution)
        offs = np.arange(-cells, cells + 1)
        # every (2 cells + 1)^2 block of the grid as a view: one gather per source point
        blocks = sliding_window_view(like, (len(offs), len(offs)))
        for yaw in yaws:
            R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
            centroid = R @ c_src + center  # expected centroid in the target frame
            base = np.floor((src @ R.T + centroid - lo) / resolution).astype(int)
            corner = base - cells
            if corner.min() >= 0 and (corner[:, 0].max() < blocks.shape[0]) and (corner[:, 1].max() < blocks.shape[1]):
                scores = blocks[corner[:, 0], corner[:, 1]].sum(axis=0)
            else:
                # indices beyond the padded grid clip to its border, where the likelihood is ~0
                ia = np.clip(base[:, 0][:, None] + offs[None, :], 0, like.shape[0] - 1)
                ib = np.clip(base[:, 1][:, None] + offs[None, :], 0, like.shape[1] - 1)
                scores = like[ia[:, :, None], ib[:, None, :]].sum(axis=0)
            a, b = np.unravel_index(int(np.argmax(scores)), scores.shape)
            t = centroid + np.array([offs[a], offs[b]]) * resolution - R @ c_src
            peaks.append((float(scores[a, b]) / len(src), t[0], t[1], float(yaw)))
        return _best_peaks(peaks)
    # Circular correlation is exact where the source, placed anywhere on the grid, cannot wrap
    # onto the target: a margin of the source's radius beyond the likelihood's reach suffices
    # (placements farther out score 0; the window may reach beyond the grid). float32: the
    # scores are sums of at most max_source_points values in [0, 1].
    reach = 7.5 * sigma + resolution
    like, lo = _likelihood_grid(target, resolution, sigma, r_src + min(window, reach) + 2 * resolution)
    like = like.astype(np.float32)
    H, W = like.shape
    F_like = sfft.rfft2(like, workers=-1)
    cx = lo[0] + np.arange(H) * resolution
    cy = lo[1] + np.arange(W) * resolution
    for chunk in np.array_split(yaws, max(1, int(np.ceil(len(yaws) / 8)))):
        kern = np.zeros((len(chunk), H, W), dtype=np.float32)
        Rs = []
        for n, yaw in enumerate(chunk):
            R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
            Rs.append(R)
            k = np.round(src @ R.T / resolution).astype(int)
            kern[n] = np.bincount((k[:, 0] % H) * W + k[:, 1] % W, minlength=H * W).reshape(H, W)
        # corr[a, b] = sum over source points of like[a + k0, b + k1]: source centroid at cell (a, b)
        corr = sfft.irfft2(F_like[None] * np.conj(sfft.rfft2(kern, axes=(1, 2), workers=-1)),
                           s=(H, W), axes=(1, 2), workers=-1)
        for n, yaw in enumerate(chunk):
            R = Rs[n]
            expected = R @ c_src + center
            ia = np.nonzero(np.abs(cx - expected[0]) <= window)[0]
            ib = np.nonzero(np.abs(cy - expected[1]) <= window)[0]
            if len(ia) == 0 or len(ib) == 0:
                continue
            subc = corr[n][np.ix_(ia, ib)]
            a, b = np.unravel_index(int(np.argmax(subc)), subc.shape)
            t = np.array([cx[ia[a]], cy[ib[b]]]) - R @ c_src
            peaks.append((float(subc[a, b]) / len(src), t[0], t[1], float(yaw)))
    if not peaks:
        return np.zeros(3), 0.0, 1.0, None
    return _best_peaks(peaks)


def icp_2d(source: np.ndarray, target: np.ndarray, xyt: np.ndarray, *, max_distance: float = 1.0,
           min_distance: float = 0.2, iterations: int = 30, tree: cKDTree | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point-to-point ICP in SE(2). Returns ``xyt``, source inlier indices and their targets."""
    tree = tree or cKDTree(target)
    x, y, yaw = (float(v) for v in xyt)
    source = np.ascontiguousarray(source, dtype=np.float64)
    dmax = max_distance
    inl = np.zeros(0, dtype=int)
    nn = np.zeros(0, dtype=int)
    for _ in range(iterations):
        c, s = math.cos(yaw), math.sin(yaw)
        moved = source @ np.array([[c, s], [-s, c]]) + np.array([x, y])
        d, nn_all = tree.query(moved, distance_upper_bound=dmax)
        inl = np.flatnonzero(d < np.inf)
        k = len(inl)
        if k < 10:
            break
        nn = nn_all[inl]
        P, Q = moved[inl], target[nn]
        # cross-covariance of the centred pairs: sum(P^T Q) - k mp mq^T
        (sp0, sp1), (sq0, sq1) = P.sum(axis=0).tolist(), Q.sum(axis=0).tolist()
        (h00, h01), (h10, h11) = (P.T @ Q).tolist()
        mp0, mp1, mq0, mq1 = sp0 / k, sp1 / k, sq0 / k, sq1 / k
        h00 -= sp0 * mq0
        h01 -= sp0 * mq1
        h10 -= sp1 * mq0
        h11 -= sp1 * mq1
        dyaw = math.atan2(h01 - h10, h00 + h11)
        cd, sd = math.cos(dyaw), math.sin(dyaw)
        dt0 = mq0 - (cd * mp0 - sd * mp1)
        dt1 = mq1 - (sd * mp0 + cd * mp1)
        x, y = cd * x - sd * y + dt0, sd * x + cd * y + dt1
        yaw = math.atan2(sd * c + cd * s, cd * c - sd * s)
        dmax = max(min_distance, dmax * 0.7)
        if abs(dyaw) < 1e-5 and math.hypot(dt0, dt1) < 1e-4 and dmax == min_distance:
            break
    return np.array([x, y, yaw]), inl, nn


def target_normals(target: np.ndarray, tree: cKDTree) -> np.ndarray:
    """Unit normals ``(M, 2)`` of every target point (8-neighbour PCA, corners included)."""
    return line_normals(target, tree, k=8, max_flatness=np.inf)


def registration_information(source: np.ndarray, target: np.ndarray, xyt: np.ndarray,
                             inlier_distance: float, tree: cKDTree | None = None,
                             effective_points: int = 100,
                             normals: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
    """Point-to-line information ``(3, 3)`` over ``(x, y, yaw)``, fitness and inlier RMSE at ``xyt``.

    The information is about a perturbation of the source pose in the *source's* frame
    (``T_target_source · Exp(dx, dy, dyaw)``: the tangent a GTSAM between-factor's noise is in).
    Each inlier contributes ``J^T J`` with ``J = [n^T R, n^T dR p]`` (``n`` the target normal,
    ``R`` the source's rotation), so a corridor gives little information along its axis, as the
    source sees it: degenerate matches stay uncertain where they are degenerate. Neighbouring
    points are not independent, so the sum is scaled to ``effective_points`` observations at the
    inlier residual variance. ``normals`` ``(M, 2)`` of the target (from :func:`target_normals`)
    can be passed to share them between calls.
    """
    tree = tree or cKDTree(target)
    c, s = np.cos(xyt[2]), np.sin(xyt[2])
    moved = source @ np.array([[c, s], [-s, c]]) + xyt[:2]
    d, nn = tree.query(moved, distance_upper_bound=inlier_distance)
    inl = np.isfinite(d)
    fitness = float(inl.mean()) if len(d) else 0.0
    if inl.sum() < 3:
        return np.eye(3) * 1e-6, fitness, float("inf")
    rmse = float(np.sqrt(np.mean(d[inl] ** 2)))
    normals = (target_normals(target, tree) if normals is None else normals)[nn[inl]]
    P = moved[inl] - xyt[:2]  # rotated source points (lever arms about the source origin)
    along = normals @ np.array([[c, -s], [s, c]])  # R^T n: the normals in the source's axes
    J = np.stack([along[:, 0], along[:, 1], normals[:, 1] * P[:, 0] - normals[:, 0] * P[:, 1]], axis=1)
    sigma2 = max(rmse, 0.02) ** 2
    scale = min(1.0, effective_points / len(J))
    return scale * (J.T @ J) / sigma2, fitness, rmse


class PlanarCloud:
    """A planar cloud's k-d tree, normals and line-like points, built once when first needed.

    :func:`planar_cloud` keeps these for the last few clouds passed in, so a submap tested
    against several others (loop hypotheses, adjacent-submap checks, the reverse fitness) is
    indexed once.
    """

    def __init__(self, points: np.ndarray) -> None:
        self.source = points
        self.xy = np.ascontiguousarray(points[:, :2], dtype=np.float64)
        self._tree: KdTree2D | None = None
        self._normals: np.ndarray | None = None
        self._lines: tuple[KdTree2D, np.ndarray, np.ndarray] | None = None

    @property
    def tree(self) -> KdTree2D:
        """A k-d tree over the points (cKDTree's queries, :class:`.kdtree2d.KdTree2D`)."""
        if self._tree is None:
            self._tree = KdTree2D(self.xy)
        return self._tree

    @property
    def normals(self) -> np.ndarray:
        """Normals of every point (:func:`target_normals`)."""
        if self._normals is None:
            self._normals = target_normals(self.xy, self.tree)
        return self._normals

    @property
    def lines(self) -> tuple[KdTree2D, np.ndarray, np.ndarray] | None:
        """``(tree, points, normals)`` of the line-like points, or None when fewer than 10."""
        if self._lines is None:
            normals = line_normals(self.xy, self.tree)
            line = np.isfinite(normals[:, 0])
            pts = self.xy[line]
            self._lines = (KdTree2D(pts), pts, normals[line]) if line.sum() >= 10 else (None, pts, normals[line])
        return None if self._lines[0] is None else self._lines


_CLOUDS: dict[int, PlanarCloud] = {}
_CLOUDS_KEPT = 16


def planar_cloud(points: np.ndarray) -> PlanarCloud:
    """The :class:`PlanarCloud` of ``points`` ``(N, >=2)``, reused while the same array is passed.

    Arrays are recognised by identity (the cache holds them, so an id cannot be reused); they
    must not be modified in place afterwards (submap clouds are fixed once the submap closes).
    """
    entry = _CLOUDS.get(id(points))
    if entry is not None and entry.source is points and entry.xy.shape[0] == len(points):
        _CLOUDS[id(points)] = _CLOUDS.pop(id(points))  # most recently used last
        return entry
    entry = PlanarCloud(points)
    _CLOUDS[id(points)] = entry
    while len(_CLOUDS) > _CLOUDS_KEPT:
        del _CLOUDS[next(iter(_CLOUDS))]
    return entry


def match_planar(source: np.ndarray, target: np.ndarray, *, initial_guess: np.ndarray | None = None,
                 yaw_hint: float | None = None, window: float = 15.0, yaw_window: float = np.pi,
                 resolution: float = 0.1, inlier_distance: float = 0.2, refine_only: bool = False,
                 resolve_ambiguity_above: float | None = None) -> PlanarMatch:
    """Match planar clouds ``(N, 3)`` / ``(M, 3)`` (z ignored); no initial guess needed.

    ``initial_guess`` (4x4 source->target) centres the translation window (half width
    ``window`` m) and the yaw window (half width ``yaw_window`` rad); ``yaw_hint`` centres the
    yaw window only; with neither, the search is global. The search runs coarse-to-fine: a
    coarse grid (0.3 m or more, 2 degree steps) over the whole window, then ``resolution`` over
    +-0.6 m and +-3 degrees around the best cell, then ICP. ``refine_only`` skips the search
    (ICP from ``initial_guess``).

    The coarse grid's scores are blurred (a corridor slid by a door's width scores nearly as well):
    when the best distinct second peak scores above ``resolve_ambiguity_above`` of the best, it is
    refined the same way, and the ambiguity becomes the ratio of the two refined fitnesses (0 when
    both end at one pose); the better of the two is the match.
    """
    src = source[:, :2]
    cloud = planar_cloud(target)
    tgt, tree = cloud.xy, cloud.tree
    normals = cloud.normals  # shared by every information evaluation below
    second = None
    if refine_only:
        if initial_guess is None:
            raise ValueError("refine_only needs an initial_guess")
        xyt0, score, amb = matrix_to_se2(initial_guess), float("nan"), 0.0
    else:
        center_yaw = 0.0
        if initial_guess is not None:
            x, y, center_yaw = matrix_to_se2(initial_guess)
        elif yaw_hint is not None:
            center_yaw = float(yaw_hint)
        half = min(float(yaw_window), np.pi)
        coarse_res = max(0.3, resolution)
        coarse_step = np.deg2rad(2.0)
        yaws = center_yaw + np.arange(-half, half + 1e-9, coarse_step)
        if initial_guess is None:
            # the source centroid may land anywhere on the target (plus a margin)
            extent = float(np.abs(tgt - tgt.mean(axis=0)).max()) + 2.0
            xyt_c, score, amb, second = _search_about_centroid(src, tgt, yaws, coarse_res, extent)
        else:
            xyt_c, score, amb, second = coarse_peaks(src, tgt, resolution=coarse_res, sigma=max(0.3, 1.5 * coarse_res),
                                                     center=np.array([x, y]), window=window, yaws=yaws)
        xyt0, score = _fine_search(src, tgt, xyt_c, resolution)
    xyt, info, fitness, rmse = _icp(src, cloud, xyt0, resolution, inlier_distance)
    if initial_guess is not None and not refine_only:
        # The correlative score can prefer a slightly slid pose along self-similar corridors;
        # ICP straight from the guess competes, and the better fit wins.
        xyt_g, _, _ = icp_2d(src, tgt, matrix_to_se2(initial_guess), max_distance=1.0,
                             min_distance=inlier_distance, tree=tree)
        info_g, fitness_g, rmse_g = registration_information(src, tgt, xyt_g, inlier_distance, tree, normals=normals)
        if fitness_g >= fitness:
            xyt, info, fitness, rmse = xyt_g, info_g, fitness_g, rmse_g
    # point-to-point ICP follows where walls end and samples differ between submaps; a
    # point-to-line pass removes that bias (degenerate directions keep the ICP result)
    xyt, info, fitness, rmse = _line_pass(src, cloud, xyt, info, fitness, rmse, inlier_distance)
    if resolve_ambiguity_above is not None and second is not None and amb > resolve_ambiguity_above:
        start = _fine_search(src, tgt, second, resolution)[0]
        xyt2, info2, fitness2, rmse2 = _line_pass(src, cloud, *_icp(src, cloud, start, resolution, inlier_distance),
                                                  inlier_distance)
        if not _far(xyt2, xyt):
            amb = 0.0  # both peaks lead to one alignment
        elif fitness2 > fitness:
            amb = fitness / fitness2
            xyt, info, fitness, rmse = xyt2, info2, fitness2, rmse2
        else:
            amb = fitness2 / fitness if fitness > 0 else 1.0
    return PlanarMatch(xyt=xyt, score=score, ambiguity=amb, fitness=fitness, inlier_rmse=rmse, information=info)


def _fine_search(src: np.ndarray, tgt: np.ndarray, xyt_c: np.ndarray, resolution: float) -> tuple[np.ndarray, float]:
    """The ``resolution`` grid over +-0.6 m and +-3 degrees around a coarse peak ``(x, y, yaw)``:
    its best ``(x, y, yaw)`` and score."""
    fine_yaws = xyt_c[2] + np.deg2rad(np.arange(-3.0, 3.01, 0.5))
    xyt0, score, _ = coarse_search(src, tgt, resolution=resolution, center=xyt_c[:2], window=0.6, yaws=fine_yaws)
    return xyt0, score


def _icp(src: np.ndarray, cloud: PlanarCloud, xyt0: np.ndarray, resolution: float,
         inlier_distance: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Point-to-point ICP from ``xyt0``: ``(x, y, yaw)``, information ``(3, 3)``, fitness, RMSE [m]."""
    xyt, _, _ = icp_2d(src, cloud.xy, xyt0, max_distance=3 * resolution + inlier_distance,
                       min_distance=inlier_distance, tree=cloud.tree)
    info, fitness, rmse = registration_information(src, cloud.xy, xyt, inlier_distance, cloud.tree, normals=cloud.normals)
    return xyt, info, fitness, rmse


def _line_pass(src: np.ndarray, cloud: PlanarCloud, xyt: np.ndarray, info: np.ndarray, fitness: float, rmse: float,
               inlier_distance: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The point-to-line pass from ``xyt`` (with its ICP ``info``, ``fitness``, ``rmse``): the refined
    ``(x, y, yaw)``, information, fitness and RMSE, unless it loses more than 0.02 of fitness."""
    refined = _point_to_line_pass(src, cloud, xyt, inlier_distance)
    if refined is not None:
        info_r, fitness_r, rmse_r = registration_information(src, cloud.xy, refined, inlier_distance, cloud.tree,
                                                             normals=cloud.normals)
        if fitness_r >= fitness - 0.02:
            return refined, info_r, fitness_r, rmse_r
    return xyt, info, fitness, rmse


def _point_to_line_pass(src: np.ndarray, cloud: PlanarCloud, xyt: np.ndarray,
                        inlier_distance: float) -> np.ndarray | None:
    """Point-to-line Gauss-Newton from ``xyt`` against the target's line-like points, or None."""
    lines = cloud.lines
    if lines is None:
        return None
    xyt_r, used = point_to_line(src, xyt, *lines, max_correspondence=inlier_distance, iterations=10)
    return xyt_r if used else None


def _search_about_centroid(src, tgt, yaws, resolution, window):
    """Global search: translation window centred so the source centroid can land anywhere on the target."""
    best = None
    # per yaw, the translation that puts the source centroid on the target centroid
    c_s, c_t = src.mean(axis=0), tgt.mean(axis=0)
    results = []
    for chunk in np.array_split(yaws, max(1, len(yaws) // 30)):
        mid = float(np.median(chunk))
        R = np.array([[np.cos(mid), -np.sin(mid)], [np.sin(mid), np.cos(mid)]])
        center = c_t - R @ c_s
        res = coarse_peaks(src, tgt, resolution=resolution, center=center, window=window, yaws=chunk)
        results.append(res)
        if best is None or res[1] > best[1]:
            best = res
    # ambiguity across chunks too
    others = [r for r in results if r is not best and _far(r[0], best[0])]
    other = max(others, key=lambda r: r[1], default=None)
    if other is not None and best[1] > 0 and other[1] / best[1] > best[2]:
        return best[0], best[1], other[1] / best[1], other[0]
    return best
