"""The small pieces under the reports: batched TUM poses, ellipses in the world frame, the
top-down render of a 3D map, the PLY reader, and the input's provenance."""

import hashlib
import json

import numpy as np

from submapslam.evaluation.run_figures import anchor_covariances_xy, top_down_image
from submapslam.geometry import pose_from_xyz_quat, poses_from_xyz_quats
from submapslam.io.ply import write_ply
from submapslam.io.provenance import input_provenance, write_provenance
from submapslam.io.run_folder import read_ply_points


def test_batched_poses_equal_one_at_a_time():
    rng = np.random.default_rng(3)
    t, q = rng.normal(size=(20, 3)), rng.normal(size=(20, 4)) * 3.0  # not normalised
    one = np.array([pose_from_xyz_quat(a, b) for a, b in zip(t, q)])
    np.testing.assert_allclose(poses_from_xyz_quats(t, q), one, atol=1e-12)


def test_anchor_ellipse_turns_with_the_anchor():
    # 0.3 m along the anchor's x, 0.1 m along its y; the anchor faces +y in the world
    submaps = {"sigma_x": np.array([0.3, 0.3]), "sigma_y": np.array([0.1, 0.1]), "yaw": np.array([0.0, np.pi / 2]),
               "cov_xy": np.array([0.0, 0.0])}
    C = anchor_covariances_xy(submaps)
    np.testing.assert_allclose(C[0], np.diag([0.09, 0.01]), atol=1e-12)
    np.testing.assert_allclose(C[1], np.diag([0.01, 0.09]), atol=1e-12)


def test_top_down_image_is_the_highest_point_per_cell_top_row_up():
    pts = np.array([[0.05, 0.05, 1.0], [0.06, 0.04, 3.0], [0.95, 0.75, 5.0]])
    img, (x0, x1, y0, y1), cell = top_down_image(pts, max_pixels=10, min_cell=0.1)
    assert cell == 0.1 and np.isclose((x1 - x0) / cell, img.shape[1]) and np.isclose((y1 - y0) / cell, img.shape[0])
    assert img.shape[1] > img.shape[0]  # wider than tall, like the points
    assert img[-1, 0] == 3.0  # the two low points share the bottom-left cell: the higher one
    assert img[0, -1] == 5.0  # the highest-y point is in the top row
    assert np.isfinite(img).sum() == 2
    cropped, extent, _ = top_down_image(pts, max_pixels=10, min_cell=0.1, bounds=(0.0, 0.5, 0.0, 0.5))
    assert np.nanmax(cropped) == 3.0 and extent[1] < 0.5  # the far point is cut away


def test_ply_points_read_back(tmp_path):
    pts = np.random.default_rng(0).normal(size=(50, 3))
    write_ply(tmp_path / "a.ply", pts, colors=np.full((50, 3), 0.5))
    np.testing.assert_allclose(read_ply_points(tmp_path / "a.ply"), pts, atol=1e-6)  # float32 out


def test_provenance_of_a_file_and_a_folder(tmp_path):
    log = tmp_path / "log.clf"
    log.write_bytes(b"FLASER 0 0 0 0 0 0 0 1.0 host 1.0\n")
    doc = input_provenance(log, np.array([10.0, 12.5, 15.0]))
    assert doc["sha256"] == hashlib.sha256(log.read_bytes()).hexdigest() and doc["hash_of"] == "content"
    assert doc["scans"] == 3 and doc["duration_s"] == 5.0 and doc["size_bytes"] == log.stat().st_size
    folder = tmp_path / "scans"
    (folder / "sub").mkdir(parents=True)
    (folder / "sub" / "0.bin").write_bytes(b"1234")
    first = input_provenance(folder, np.array([0.0]))
    (folder / "sub" / "0.bin").write_bytes(b"12345")  # a size change changes the listing hash
    assert input_provenance(folder, np.array([0.0]))["sha256"] != first["sha256"] and first["files"] == 1
    assert json.loads(write_provenance(tmp_path, doc).read_text()) == doc


def test_svg_chart_places_points_on_its_axes():
    import re

    from submapslam.evaluation.html_page import _ticks, svg_line_chart

    assert _ticks(0.0, 10.0) == [0.0, 2.0, 4.0, 6.0, 8.0, 10.0]
    svg = svg_line_chart([0.0, 10.0], [0.0, 100.0], xlabel="t [s]", ylabel="n", width=200, height=160)
    pts = re.search(r'<polyline points="([^"]+)"', svg).group(1).split()
    (ax, ay), (bx, by) = (tuple(map(float, p.split(","))) for p in pts)
    assert ax == 58 and bx == 200 - 12  # first point on the left axis, last on the right edge
    assert ay == 160 - 42 and by < ay  # y grows upwards
    assert "t [s]" in svg and svg.count("<text") >= 6


def test_the_level_priors_decision_in_words():
    """The report's overview says where a 3D run's up came from, what the level test found and
    what became of the ground priors, for each way the test can end."""
    from submapslam.evaluation.html_report import level_priors_in_words

    assert level_priors_in_words({}) is None  # a 2D run, or no level priors
    dropped = level_priors_in_words({"level_ratio": None, "level": None, "kept": False, "level_priors_from": "ground",
                                     "priors": 2, "loops": 0, "loop_chi2_with": None, "loop_chi2_without": None})
    assert "untested" in dropped and "the 2 ground priors left the graph: no closure vouched for them" in dropped
    kept = level_priors_in_words({"level_ratio": None, "level": None, "kept": True, "level_priors_from": "ground",
                                  "priors": 1, "loops": 1, "loop_chi2_with": 0.01, "loop_chi2_without": 0.01})
    assert kept.endswith("stayed: the closures fit them (chi2 0.01 with, 0.01 without)")
    contradicted = level_priors_in_words({"level_ratio": 2.0, "level": False, "kept": False, "priors": 30,
                                          "level_priors_from": "ground", "loops": 3, "loop_chi2_with": 12.73,
                                          "loop_chi2_without": 0.0})
    assert "not level (turn 2.0" in contradicted and "from 0.0 to 12.73" in contradicted
    indifferent = level_priors_in_words({"level_ratio": 52.66, "level": False, "kept": False, "priors": 311,
                                         "level_priors_from": "ground", "loops": 15, "loop_chi2_with": 0.07,
                                         "loop_chi2_without": 0.02, "allowance": 0.0, "odometry_tilt_restored": 155})
    assert indifferent.endswith("from 0.02 to 0.07 (must lower it); the 155 odometry edges' tilt weighed like "
                                "their yaw again")
    near = level_priors_in_words({"level_ratio": 2.5, "level": False, "kept": False, "priors": 30,
                                  "level_priors_from": "ground", "loops": 3, "loop_chi2_with": 9.0,
                                  "loop_chi2_without": 1.0, "allowance": 3.84})
    assert "(at most +3.84 allowed)" in near and "weighed like" not in near
    walls = level_priors_in_words({"level_ratio": 2.866, "level": False, "kept": True, "level_priors_from": "walls",
                                   "priors": 0, "loops": 0})
    assert walls.startswith("up from the walls' vertical") and "no ground prior to test" in walls
    assert "weighed like" not in walls
    walls_restored = level_priors_in_words({"level_ratio": 10.5, "level": False, "kept": True, "priors": 0,
                                            "level_priors_from": "walls", "loops": 0, "odometry_tilt_restored": 74})
    assert "no ground prior to test" in walls_restored
    assert walls_restored.endswith("the 74 odometry edges' tilt weighed like their yaw again")
    assert level_priors_in_words({"level_ratio": 0.43, "level": True, "kept": True,
                                  "level_priors_from": "walls"}).endswith("level (turn 0.43 of the odometry's "
                                                                          "allowance); the ground priors stayed")
