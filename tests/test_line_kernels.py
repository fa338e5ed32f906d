"""The compiled point-to-line kernels against a plain numpy reference (the implementation they replaced)."""

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from submapslam.registration.line_kernels import LineGrid
from submapslam.registration.point_to_line import (
    RecentScanMap,
    line_normals,
    line_offsets,
    point_to_line,
)

from .planar_scenes import wall_points
from .test_planar_refine import CORRIDOR, ROOM


def reference_point_to_line(points_xy, xyt, tree, target, normals, *, max_correspondence=0.3, kernel=0.05,
                            min_eigen_fraction=0.02, prior_xyt=None, iterations=6, converged=(5e-5, 3e-6)):
    """Point-to-line Gauss-Newton in numpy, as before the kernels were compiled."""
    x0, x1, x2 = (float(v) for v in xyt)
    lines = line_offsets(target, normals)
    n_used = 0
    for _ in range(iterations):
        c, s = math.cos(x2), math.sin(x2)
        rotated = points_xy @ np.array([[c, s], [-s, c]])
        d, nn = tree.query(rotated + (x0, x1), distance_upper_bound=max_correspondence)
        ok = d < np.inf
        n_used = int(ok.sum())
        if n_used < 20:
            return np.asarray(xyt, dtype=np.float64), 0
        p, nq = rotated[ok], lines[nn[ok]]
        A = np.empty((n_used, 4))
        A[:, :2] = nq[:, :2]
        A[:, 2] = nq[:, 1] * p[:, 0] - nq[:, 0] * p[:, 1]
        A[:, 3] = nq[:, 0] * (p[:, 0] + x0) + nq[:, 1] * (p[:, 1] + x1) - nq[:, 2]
        w = 1.0 / (1.0 + np.square(A[:, 3]) / kernel**2)
        M = (A * w[:, None]).T @ A
        H, g = M[:3, :3], M[:3, 3]
        S = np.array([1.0, 1.0, 1.0 / max(math.sqrt(float(np.vdot(p, p)) / n_used), 1e-3)])
        evals, evecs = np.linalg.eigh(H * np.outer(S, S))
        keep = evals > min_eigen_fraction * evals.sum()
        Vk = evecs[:, keep]
        step = -(Vk @ ((Vk.T @ (S * g)) / evals[keep]))
        if prior_xyt is not None:
            to_prior = np.asarray(prior_xyt, dtype=np.float64) - (x0, x1, x2)
            to_prior[2] = math.remainder(to_prior[2], 2 * math.pi)
            Vd = evecs[:, ~keep]
            step = step + Vd @ (Vd.T @ (to_prior / S))
        s0, s1, s2 = S * step
        x0, x1, x2 = x0 + s0, x1 + s1, x2 + s2
        if abs(s0) + abs(s1) < converged[0] and abs(s2) < converged[1]:
            break
    return np.array([x0, x1, x2]), n_used


def _target(segments, n_scans=20):
    m = RecentScanMap(window=30, rebuild_every=1)
    for k in range(n_scans):
        pose = np.array([0.1 * k, 0.0, 0.0])
        m.add(wall_points(segments, pose), pose)
    pts = m._grid.points
    return m, pts, m._lines[:, :2]


@pytest.mark.parametrize("segments, prior", [(ROOM, None), (CORRIDOR, np.array([2.03, 0.0, 0.0]))])
def test_compiled_refinement_gives_the_numpy_reference_pose(segments, prior):
    m, target, normals = _target(segments)
    truth = np.array([2.0, 0.0, 0.0])
    scan = wall_points(segments, truth)
    for guess in (truth + [0.08, -0.05, np.deg2rad(1.5)], truth + [-0.2, 0.06, 0.01]):
        want, want_used = reference_point_to_line(scan, guess, cKDTree(target), target, normals, prior_xyt=prior)
        got, got_used = m.refine(scan, guess, prior_xyt=prior)  # whole loop compiled, grid lookup
        assert got_used == want_used
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
        tree_got, tree_used = point_to_line(scan, guess, cKDTree(target), target, normals, prior_xyt=prior)
        assert tree_used == want_used  # compiled steps, k-d tree lookup
        np.testing.assert_allclose(tree_got, want, rtol=0, atol=1e-9)


def test_grid_lookup_is_the_exact_nearest_neighbour_within_the_radius():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-5, 5, size=(2000, 2))
    grid = LineGrid(pts, 0.3)
    query = rng.uniform(-6, 6, size=(5000, 2))
    for radius in (0.3, 0.1):
        d, nn = cKDTree(pts).query(query, distance_upper_bound=radius)
        want = np.where(d < np.inf, nn, -1)
        np.testing.assert_array_equal(grid.nearest(query, radius), want)
    with pytest.raises(ValueError):
        grid.nearest(query, 0.5)


def test_fit_counts_the_points_near_the_line_points():
    m, target, _ = _target(ROOM)
    scan = wall_points(ROOM, np.array([2.0, 0.0, 0.0]))
    for xyt in (np.array([2.0, 0.0, 0.0]), np.array([2.05, 0.02, 0.01])):
        c, s = math.cos(xyt[2]), math.sin(xyt[2])
        d, _ = cKDTree(target).query(scan @ np.array([[c, s], [-s, c]]) + xyt[:2], distance_upper_bound=0.1)
        assert m.fit(scan, xyt, 0.1) == np.count_nonzero(d <= 0.1) / len(scan)


def test_a_huge_extent_gets_coarser_cells_and_stays_exact():
    pts = np.array([[0.0, 0.0], [1e5, 1e5], [0.05, 0.1], [1e5 + 0.2, 1e5]])
    grid = LineGrid(pts, 0.3)
    np.testing.assert_array_equal(grid.nearest(np.array([[0.04, 0.0], [1e5 + 0.15, 1e5], [50.0, 50.0]]), 0.3),
                                  [0, 3, -1])


def test_line_normals_are_unit_and_across_the_wall():
    xy = np.column_stack([np.linspace(0, 5, 50), np.full(50, 1.0)])
    n = line_normals(xy, cKDTree(xy))
    np.testing.assert_allclose(np.abs(n[:, 1]), 1.0, atol=1e-9)
