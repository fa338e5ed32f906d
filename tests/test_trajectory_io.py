import gzip

import numpy as np
import pytest

from submapslam.errors import InputError
from submapslam.geometry import se2_to_matrix, se3_exp
from submapslam.io.trajectory import (
    Trajectory,
    carmen_reference_trajectory,
    read_carmen_trajectory,
    read_kitti,
    read_relations,
    read_trajectory,
    read_tum,
    read_tum_cov,
    write_kitti,
    write_tum,
    write_tum_cov,
)

from .conftest import shared_data


def random_traj(n=20, seed=0):
    rng = np.random.default_rng(seed)
    poses = np.array([se3_exp(rng.normal(size=6)) for _ in range(n)])
    return Trajectory(1000.0 + np.arange(n) * 0.1, poses)


def test_tum_round_trip(tmp_path):
    t = random_traj()
    write_tum(tmp_path / "a.txt", t)
    back = read_tum(tmp_path / "a.txt")
    np.testing.assert_allclose(back.timestamps, t.timestamps, atol=1e-6)
    np.testing.assert_allclose(back.poses, t.poses, atol=1e-7)


def test_pose_covariance_file_round_trip_and_order(tmp_path):
    """poses_cov.txt: TUM line + 21 upper-triangular entries in the order x y z rx ry rz (GTSAM
    keeps rx ry rz x y z): a variance put on GTSAM's x (index 3) is the file's first entry."""
    t = random_traj(5)
    rng = np.random.default_rng(1)
    A = rng.normal(size=(5, 6, 6))
    covs = A @ A.transpose(0, 2, 1) + np.eye(6)
    covs[0] = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])  # rx ry rz x y z
    covs[0, 3, 4] = covs[0, 4, 3] = 0.5  # x-y
    write_tum_cov(tmp_path / "c.txt", t, covs)
    first = [float(v) for v in (tmp_path / "c.txt").read_text().splitlines()[1].split()]
    assert len(first) == 8 + 21
    assert first[8:14] == [4.0, 0.5, 0.0, 0.0, 0.0, 0.0]  # row x: xx xy xz xrx xry xrz
    assert first[14] == 5.0 and first[-1] == 3.0  # yy ... rzrz
    back, back_covs = read_tum_cov(tmp_path / "c.txt")
    np.testing.assert_allclose(back.poses, t.poses, atol=1e-7)
    np.testing.assert_allclose(back_covs, covs, rtol=1e-8)
    with pytest.raises(ValueError, match="covariances"):
        write_tum_cov(tmp_path / "d.txt", t, covs[:3])


def test_kitti_round_trip_and_sniffing(tmp_path):
    t = random_traj()
    write_kitti(tmp_path / "k.txt", t.poses)
    back = read_kitti(tmp_path / "k.txt")
    np.testing.assert_allclose(back.poses, t.poses, atol=1e-7)
    assert len(read_trajectory(tmp_path / "k.txt")) == 20
    write_tum(tmp_path / "t.txt", t)
    np.testing.assert_allclose(read_trajectory(tmp_path / "t.txt").timestamps, t.timestamps, atol=1e-6)


def test_compressed_tum(tmp_path):
    t = random_traj(5)
    write_tum(tmp_path / "a.txt", t)
    with gzip.open(tmp_path / "a.txt.gz", "wt") as fh:
        fh.write((tmp_path / "a.txt").read_text())
    np.testing.assert_allclose(read_tum(tmp_path / "a.txt.gz").poses, t.poses, atol=1e-7)


def test_garbled_lines_name_the_line(tmp_path):
    p = tmp_path / "bad.txt"
    p.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 zero 0 0 0 1\n")
    with pytest.raises(InputError, match=r"bad\.txt:3: non-numeric"):
        read_tum(p)
    p.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match=r"bad\.txt:2: expected 8 numbers, got 7"):
        read_tum(p)
    p.write_text("1.0 0 0 nan 0 0 0 1\n")
    with pytest.raises(InputError, match="NaN"):
        read_tum(p)
    p.write_text("1 2 3\n")
    with pytest.raises(InputError, match="unknown trajectory format"):
        read_trajectory(p)


def test_relations_file(tmp_path):
    p = tmp_path / "rel.txt"
    p.write_text("10.0 11.0 1.0 0.0 0.0 0.0 0.0 1.5707963\nFLASER 11.0 12.0 0 1 0 0 0 0\n")
    rel = read_relations(p)
    assert len(rel) == 2
    np.testing.assert_allclose(rel.T_a_b[0], se2_to_matrix(1.0, 0.0, np.pi / 2), atol=1e-6)
    p.write_text("10 11 1 2 3\n")
    with pytest.raises(InputError, match="rel.txt:1"):
        read_relations(p)


def test_carmen_trajectory_and_reference_from_real_logs():
    raw = shared_data("carmen", "intel.clf.bz2")
    corrected = shared_data("carmen", "corrected", "intel-corrected.log.gz")
    odo = read_carmen_trajectory(raw)
    assert len(odo) == 13631
    ref = carmen_reference_trajectory(corrected, raw)
    assert len(ref) == 910  # every corrected scan finds its raw line
    assert 976052850 < ref.timestamps[0] < 976053000  # ipc time of the raw log, not logger time
    assert set(np.round(ref.timestamps, 6)) <= set(np.round(odo.timestamps, 6))


def _flaser(ranges: list[float], x: float, y: float, th: float, logger: str) -> str:
    r = " ".join(f"{v:.2f}" for v in ranges)
    return f"FLASER {len(ranges)} {r} {x} {y} {th} {x} {y} {th} {logger} host {logger}\n"


def test_corrected_log_with_imprecise_times_is_matched_by_identical_ranges(tmp_path):
    """MIT CSAIL's corrected log prints its times with 6 digits (1.13486e+09): its scans are
    matched to the raw log's by identical readings, in log order, each taking the raw ipc time."""
    rng = np.random.default_rng(3)
    scans = [list(rng.uniform(0.5, 8.0, 10)) for _ in range(5)]
    scans[3] = list(scans[1])  # the robot stood still: the same readings twice
    raw = tmp_path / "raw.clf"
    raw.write_text("".join(_flaser(s, k, 0.0, 0.0, f"{1134860000.0 + 0.2 * k:.6f}") for k, s in enumerate(scans)))
    corrected = tmp_path / "corrected.log"
    # the printed time 1.13486e+09 is raw scan 0's logger time exactly: time alone would pick scan 0
    corrected.write_text("".join(_flaser(scans[k], 10.0 + k, 1.0, 0.5, "1.13486e+09") for k in (1, 4)))
    ref = carmen_reference_trajectory(corrected, raw)
    np.testing.assert_allclose(ref.timestamps - 1134860000.0, [0.2, 0.8], rtol=0, atol=1e-6)  # scans 1 and 4
    np.testing.assert_allclose(ref.positions[:, 0], [11.0, 14.0])
    # scans 1 and 3 share their readings: the one nearest in logger time
    corrected.write_text(_flaser(scans[3], 0.0, 0.0, 0.0, "1134860000.61"))
    ref = carmen_reference_trajectory(corrected, raw)
    np.testing.assert_allclose(ref.timestamps - 1134860000.0, [0.6], rtol=0, atol=1e-6)
    # no identical readings: by time (within 10 ms), else nothing matches
    corrected.write_text(_flaser([9.0] * 10, 0.0, 0.0, 0.0, "1134860000.405"))
    np.testing.assert_allclose(carmen_reference_trajectory(corrected, raw).timestamps - 1134860000.0, [0.4],
                               rtol=0, atol=1e-6)
    corrected.write_text(_flaser([9.0] * 10, 0.0, 0.0, 0.0, "1.13487e+09"))
    with pytest.raises(InputError, match="identical ranges"):
        carmen_reference_trajectory(corrected, raw)


def test_mit_csail_reference_matches_by_ranges():
    raw = shared_data("carmen", "mit-csail.clf.bz2")
    ref = carmen_reference_trajectory(shared_data("carmen", "corrected", "mit-csail-corrected.log.gz"), raw)
    assert len(ref) == 406  # SOURCE.txt: 406 of its 407 lines match a raw scan exactly
    assert np.all(np.diff(ref.timestamps) > 0)
    assert set(np.round(ref.timestamps, 6)) <= set(np.round(read_carmen_trajectory(raw).timestamps, 6))
