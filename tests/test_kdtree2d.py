"""KdTree2D answers cKDTree's queries: the same neighbours and distances, the same misses."""

import numpy as np
from scipy.spatial import cKDTree

from submapslam.registration.kdtree2d import KdTree2D


def test_nearest_within_a_bound_is_cKDTree_s():
    rng = np.random.default_rng(4)
    pts = rng.uniform(-10, 10, size=(500, 2))
    query = rng.uniform(-11, 11, size=(2000, 2))
    ours, ref = KdTree2D(pts), cKDTree(pts)
    for bound in (0.3, 0.1, np.inf):
        d, i = ours.query(query, distance_upper_bound=bound)
        d_ref, i_ref = ref.query(query, distance_upper_bound=bound)
        np.testing.assert_array_equal(i, i_ref)
        np.testing.assert_array_equal(d, d_ref)


def test_k_nearest_are_cKDTree_s_in_order():
    rng = np.random.default_rng(5)
    pts = rng.uniform(-10, 10, size=(300, 2))
    d, i = KdTree2D(pts).query(pts, k=7)
    d_ref, i_ref = cKDTree(pts).query(pts, k=7)
    np.testing.assert_array_equal(i, i_ref)
    np.testing.assert_allclose(d, d_ref, rtol=0, atol=1e-12)


def test_the_bound_is_strict_as_in_cKDTree():
    pts = np.array([[0.0, 0.0], [5.0, 5.0]])
    q = np.array([[0.3, 0.0], [np.nextafter(0.3, 0.0), 0.0]])
    d, i = KdTree2D(pts).query(q, distance_upper_bound=0.3)
    d_ref, i_ref = cKDTree(pts).query(q, distance_upper_bound=0.3)
    np.testing.assert_array_equal(i, i_ref)
    np.testing.assert_array_equal(d, d_ref)
    assert i.tolist() == [2, 0]


def test_fewer_points_than_asked_or_none_are_misses_as_in_cKDTree():
    pts = np.array([[0.0, 0.0], [1.0, 0.0]])
    q = np.array([[0.1, 0.0]])
    d, i = KdTree2D(pts).query(q, k=3)
    d_ref, i_ref = cKDTree(pts).query(q, k=3)
    np.testing.assert_array_equal(i, i_ref)
    np.testing.assert_allclose(d, d_ref)
    d, i = KdTree2D(np.zeros((0, 2))).query(q, distance_upper_bound=0.3)
    d_ref, i_ref = cKDTree(np.zeros((0, 2))).query(q, distance_upper_bound=0.3)
    np.testing.assert_array_equal(i, i_ref)
    np.testing.assert_array_equal(d, d_ref)
