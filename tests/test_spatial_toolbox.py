"""The 3D registration toolbox without open3d: its FPFH features, fit scores and information agree
with open3d's on the same clouds, and a 3D loop test never imports open3d (about 100 MiB of a run's
peak)."""

import subprocess
import sys

import numpy as np

from submapslam.geometry import inverse, rotation_angle, se2_to_matrix, transform_points
from submapslam.registration.correspondence import check_correspondence
from submapslam.registration.fpfh import fpfh_features
from submapslam.registration.spatial import SpatialCloud, information_matrix, registration_fit

from .conftest import shared_data
from .test_city_scale import _street_cloud


def _open3d_cloud(points: np.ndarray, normals: np.ndarray | None = None):
    from submapslam._deps import open3d

    o3d = open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(normals)
    return o3d, cloud


def _alpha_wrapped(features: np.ndarray) -> np.ndarray:
    """The alpha histogram's first and last bins merged: both hold angles at +-pi, where the sign of a
    rounding-level zero decides the bin (open3d's and numpy's arithmetic round differently)."""
    out = features.copy()
    out[:, 0] += out[:, 10]
    out[:, 10] = 0.0
    return out


def test_fpfh_features_are_open3d_s_on_the_same_points_and_normals():
    """On open3d's own normals. Where a pair's two angles to the line joining it tie (flat ground),
    rounding decides which end frames the pair: a few pairs land one bin apart."""
    points = SpatialCloud(_street_cloud(np.random.default_rng(0)), 0.4).points
    o3d, pcd = _open3d_cloud(points)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=1.6, max_nn=30))
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=8.0, max_nn=100)
    theirs = np.asarray(o3d.pipelines.registration.compute_fpfh_feature(pcd, search).data).T
    ours = fpfh_features(points, np.asarray(pcd.normals), radius=8.0, max_nn=100)
    assert ours.shape == theirs.shape == (len(points), 33) and len(points) > 1000
    difference = np.abs(_alpha_wrapped(ours) - _alpha_wrapped(theirs)).max(axis=1)
    # a pair adds 100/99 to a bin; a point with such a pair spreads it to its neighbours (weighted)
    assert (difference < 1e-6).mean() > 0.85 and difference.max() < 2.5
    # each of the three histograms sums to 100 for the neighbours plus 100 for the point's own
    np.testing.assert_allclose(ours.reshape(-1, 3, 11).sum(axis=2), 200.0)


def test_prepared_clouds_have_unit_normals_facing_up_or_the_origin():
    cloud = SpatialCloud(_street_cloud(np.random.default_rng(0)), 0.4)
    normals, points = cloud.normals, cloud.points
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    flat = np.abs(normals[:, 2]) >= 0.5
    assert flat.sum() > 500 and (normals[flat, 2] > 0).all()  # the ground's face the sky
    assert (~flat).sum() > 500 and (np.einsum("ij,ij->i", normals[~flat], points[~flat]) <= 0).all()


def test_fit_scores_and_information_are_open3d_s():
    rng = np.random.default_rng(1)
    target = SpatialCloud(_street_cloud(rng), 0.3)
    T = se2_to_matrix(0.4, -0.2, np.deg2rad(3.0))
    source = SpatialCloud(transform_points(inverse(T), target.points) + rng.normal(0, 0.15, target.points.shape),
                          0.3)
    o3d, src = _open3d_cloud(source.points)
    _, tgt = _open3d_cloud(target.points)
    reg = o3d.pipelines.registration
    theirs = reg.evaluate_registration(src, tgt, 0.3, T)
    fitness, rmse = registration_fit(source, target, T, 0.3)
    assert 0.5 < fitness < 1.0
    assert abs(fitness - theirs.fitness) < 1e-9 and abs(rmse - theirs.inlier_rmse) < 1e-9
    np.testing.assert_allclose(information_matrix(source, target, T, 0.3),
                               reg.get_information_matrix_from_point_clouds(src, tgt, 0.3, T), rtol=1e-9)
    assert registration_fit(source, target, se2_to_matrix(500.0, 0.0, 0.0), 0.3) == (0.0, float("inf"))


def test_global_search_recovers_a_real_lidar_pair_without_a_guess():
    """FPFH + RANSAC + GICP on two real scans (small_gicp's sample pair), from no initial guess."""
    from submapslam.io.cloud_folder import read_cloud

    folder = shared_data("lidar3d", "small_gicp_pair")
    src, _ = read_cloud(folder / "source.ply")
    tgt, _ = read_cloud(folder / "target.ply")
    T_ref = np.loadtxt(folder / "T_target_source.txt")
    res = check_correspondence(src, tgt, planar=False, voxel_size=0.25)
    err = inverse(T_ref) @ res.T_target_source
    assert res.accepted, res.reason
    assert np.linalg.norm(err[:3, 3]) < 0.1 and np.rad2deg(rotation_angle(err)) < 1.0


_NO_OPEN3D = """
import sys
import numpy as np
import submapslam.pipeline, submapslam.graph_builder, submapslam.topology.loop_closure, submapslam.localization
from submapslam.geometry import inverse, se2_to_matrix, transform_points
from submapslam.registration.correspondence import check_correspondence
from tests.test_city_scale import _street_cloud
rng = np.random.default_rng(0)
target = _street_cloud(rng)
T = se2_to_matrix(4.0, -2.5, np.deg2rad(35.0))
source = transform_points(inverse(T), target) + rng.normal(0, 0.02, target.shape)
found = check_correspondence(source, target, planar=False, voxel_size=0.4)
refined = check_correspondence(source, target, planar=False, voxel_size=0.4, initial_guess=found.T_target_source,
                               refine_only=True)
assert found.accepted and refined.accepted, (found.reason, refined.reason)
assert np.linalg.norm(refined.T_target_source[:3, 3] - T[:3, 3]) < 0.1, refined.T_target_source
assert refined.information.shape == (6, 6)
assert "open3d" not in sys.modules, "a 3D loop test imported open3d"
print("ok")
"""


def test_a_3d_loop_test_runs_without_importing_open3d():
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", _NO_OPEN3D], capture_output=True, text=True, timeout=300, cwd=repo)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"
