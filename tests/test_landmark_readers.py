"""Landmark-log readers: MR.CLAM folders (plain and .xz), Victoria Park, bad input."""

import lzma
import re

import numpy as np
import pytest

from submapslam.errors import InputError
from submapslam.io.landmark_logs import read_mrclam, read_victoria_park

HEADER = "# a\n# b\n# c\n# d\n"


def _mrclam(folder, measurement_rows="100.5 11 2.0 0.1\n100.5 22 1.5 -0.2\n", xz=False):
    folder.mkdir(parents=True, exist_ok=True)
    files = {
        "Robot1_Odometry.dat": "100.0 0.5 0.0\n100.2 0.5 0.0\n101.0 0.0 0.0\n",
        "Robot1_Measurement.dat": measurement_rows,
        "Robot1_Groundtruth.dat": "99.9 1.0 2.0 0.0\n100.0 1.0 2.0 0.0\n101.0 1.5 2.0 0.0\n",
        "Barcodes.dat": "1 11\n2 12\n6 22\n",
        "Landmark_Groundtruth.dat": "6 3.0 1.7 0.001 0.001\n",
    }
    for name, body in files.items():
        if xz and name.startswith("Robot1_"):
            with lzma.open(folder / (name + ".xz"), "wt") as fh:
                fh.write(HEADER + body)
        else:
            (folder / name).write_text(HEADER + body)
    return folder


@pytest.mark.parametrize("xz", [False, True])
def test_mrclam_reader_ignores_robots_and_starts_at_ground_truth(tmp_path, xz):
    log = read_mrclam(_mrclam(tmp_path / "d", xz=xz), 1)
    np.testing.assert_allclose(log.initial_pose, [1.0, 2.0, 0.0])  # gt pose at the first odometry time
    ids = [i for s in log.steps for i in s.ids]
    assert ids == [6]                        # barcode 11 is robot 1: ignored; 22 -> subject 6
    np.testing.assert_allclose(log.steps[0].ranges_bearings, [[1.5, -0.2]])
    assert log.steps[0].motion[0] == pytest.approx(0.25)  # 0.5 s at 0.5 m/s
    assert set(log.truth_landmarks) == {6}


def test_mrclam_garbled_line_names_file_and_line(tmp_path):
    folder = _mrclam(tmp_path / "d", measurement_rows="100.5 22 1.5 -0.2\n100.6 22 abc 0.1\n")
    with pytest.raises(InputError, match=r"Robot1_Measurement\.dat.*6"):
        read_mrclam(folder, 1)
    folder = _mrclam(tmp_path / "e", measurement_rows="100.5 22 1.5\n")
    with pytest.raises(InputError, match=r"Robot1_Measurement\.dat"):
        read_mrclam(folder, 1)


def test_truncated_xz_is_an_input_error(tmp_path):
    folder = _mrclam(tmp_path / "d", xz=True)
    p = folder / "Robot1_Odometry.dat.xz"
    p.write_bytes(p.read_bytes()[:-20])
    with pytest.raises(InputError, match="Robot1_Odometry"):
        read_mrclam(folder, 1)
    vp = tmp_path / "vp.txt.xz"
    with lzma.open(vp, "wt") as fh:
        fh.write("ODOMETRY 0 1 0.1 0 0 0.01 0 0 0.01 0 0.01\n" * 200)
    vp.write_bytes(vp.read_bytes()[:-20])
    with pytest.raises(InputError, match="vp.txt.xz"):
        read_victoria_park(vp)


def test_victoria_park_converts_landmarks_to_range_bearing(tmp_path):
    p = tmp_path / "vp.txt"
    p.write_text("ODOMETRY 0 1 1.0 0 0 0.01 0 0 0.01 0 0.001\nLANDMARK 1 7 3.0 4.0 0.4 0 0.4\n")
    log = read_victoria_park(p)
    assert len(log.steps) == 1 and log.steps[0].ids == [7]
    np.testing.assert_allclose(log.steps[0].ranges_bearings, [[5.0, np.arctan2(4.0, 3.0)]])
    np.testing.assert_allclose(np.diag(log.measurement_cov), [0.4, 0.04])


def test_mrclam_camera_model_covers_the_measurements():
    """The sensor model for unobserved predictions (60 deg, 6.5 m) holds nearly every real
    measurement, so a landmark only counts as missed where the camera could have seen it."""
    from .conftest import shared_data

    log = read_mrclam(shared_data("landmarks", "utias_mrclam7"), 1)
    rb = np.vstack([s.ranges_bearings for s in log.steps if len(s.ranges_bearings)])
    inside = (rb[:, 0] <= log.max_range) & (np.abs(rb[:, 1]) <= log.fov / 2)
    assert len(rb) > 2000 and inside.mean() > 0.95
    # and it stays inside the camera's reach: at the very edge a miss says nothing
    assert log.max_range < rb[:, 0].max() and log.fov / 2 < np.abs(rb[:, 1]).max()


def test_landmark_log_format_is_sniffed_or_checked(tmp_path):
    from submapslam.io.landmark_logs import read_landmark_log

    p = tmp_path / "vp.txt"
    p.write_text("ODOMETRY 0 1 1.0 0 0 0.01 0 0 0.01 0 0.001\nLANDMARK 1 7 3.0 4.0 0.4 0 0.4\n")
    assert read_landmark_log(p).steps[0].ids == [7]                  # a file: victoria_park format
    assert read_landmark_log(p, "synth").steps[0].ids == [7]
    folder = _mrclam(tmp_path / "d")
    assert read_landmark_log(folder).name == "MR.CLAM robot 1"       # a folder without scans/
    with pytest.raises(InputError) as err:
        read_landmark_log(p, "Victoria")
    assert str(err.value) == f"{p}: unknown landmark log format 'Victoria'; use mrclam, victoria, synth or cloud"


def test_pole_steps_come_from_scans_in_memory():
    """The EKF's pole log is built from scans and odometry handed over by a reader: no files."""
    from types import SimpleNamespace

    from submapslam.ekf.features import PLANAR_POLE_RANGE, landmark_log_from_scans
    from submapslam.geometry import se2_to_matrix
    from submapslam.trajectory import Trajectory

    # a pole 4 m ahead: 5 returns 0.1 m wide, a wall 10 m behind on both sides
    a = np.linspace(-0.0125, 0.0125, 5)
    wall = np.linspace(-0.5, 0.5, 41)
    wall = wall[np.abs(wall) > 0.05]
    pts = np.r_[np.c_[4 * np.cos(a), 4 * np.sin(a)], np.c_[14 * np.cos(wall), 14 * np.sin(wall)]]
    pts = pts[np.argsort(np.arctan2(pts[:, 1], pts[:, 0]))]
    pts = np.c_[pts, np.zeros(len(pts))]
    odo = [se2_to_matrix(0.0, 0.0, 0.0), se2_to_matrix(1.0, 0.0, 0.1)]
    scans = [SimpleNamespace(timestamp=float(k), points=pts, planar=True, odometry=odo[k]) for k in range(2)]
    truth = Trajectory([0.0, 1.0], [se2_to_matrix(5.0, 2.0, 0.3), se2_to_matrix(6.0, 2.0, 0.4)])
    log = landmark_log_from_scans(scans, "mem", fov_deg=180.0, truth=truth, truth_landmarks={3: np.array([1.0, 2.0])})
    assert log.name == "mem" and len(log.steps) == 2 and not log.known_association
    np.testing.assert_allclose(log.steps[1].motion, [1.0, 0.0, 0.1], atol=1e-12)
    (r, b), = log.steps[0].ranges_bearings
    assert r == pytest.approx(4.1, abs=0.01) and b == pytest.approx(0.0, abs=1e-9)  # centre behind the surface
    np.testing.assert_allclose(log.initial_pose, [5.0, 2.0, 0.3])
    assert log.fov == pytest.approx(np.pi) and log.max_range == PLANAR_POLE_RANGE and set(log.truth_landmarks) == {3}


def test_pole_log_reader_checks_the_field_of_view(tmp_path):
    from datasets_synth import generate
    from submapslam.io.landmark_logs import read_cloud_pole_log

    log = generate("rectangle", tmp_path / "log", seed=0, laps=1, poles=5, max_scans=10)
    meta = (log / "meta.yaml").read_text()
    assert "  fov_deg: " in meta
    (log / "meta.yaml").write_text(re.sub(r"fov_deg: .*", "fov_deg: wide", meta))
    with pytest.raises(InputError) as err:
        read_cloud_pole_log(log)
    assert str(err.value) == f"{log / 'meta.yaml'}: sensor.fov_deg must be a number of degrees, got 'wide'"
