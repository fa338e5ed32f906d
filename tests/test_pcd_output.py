"""The fused map as a PCD file (``mapping.write_pcd``), for PCL-based tools."""

import numpy as np

from datasets_synth import generate
from submapslam._deps import open3d
from submapslam.api import run_log
from submapslam.io.pcd import read_pcd_records, write_pcd
from submapslam.io.run_folder import read_ply_points


def test_a_written_pcd_reads_back_as_the_same_points_here_and_in_open3d(tmp_path):
    points = np.random.default_rng(0).uniform(-50.0, 50.0, (1000, 3)).astype(np.float32)
    path = tmp_path / "cloud.pcd"
    write_pcd(path, points)
    records = read_pcd_records(path)
    assert records is not None and records.dtype.names == ("x", "y", "z")
    assert np.array_equal(np.stack([records["x"], records["y"], records["z"]], axis=1), points)
    cloud = open3d().io.read_point_cloud(str(path))
    assert np.array_equal(np.asarray(cloud.points).astype(np.float32), points)


def test_a_run_writes_map_pcd_when_asked_and_it_holds_map_ply_s_points(tmp_path):
    log = generate("rectangle", tmp_path / "log", seed=0, laps=1, size=(20.0, 12.0), max_scans=150)
    _, plain = run_log(log, tmp_path / "plain")
    assert "map.pcd" not in plain and not (tmp_path / "plain" / "map.pcd").exists()
    config = tmp_path / "pcd.yaml"
    config.write_text("mapping:\n  write_pcd: true\n")
    _, paths = run_log(log, tmp_path / "with_pcd", config=config)
    records = read_pcd_records(paths["map.pcd"])
    ply = read_ply_points(paths["map.ply"])
    assert len(records) == len(ply) > 100
    assert np.array_equal(np.stack([records["x"], records["y"], records["z"]], axis=1), ply.astype(np.float32))


def test_a_pcd_that_cannot_be_written_is_one_line_naming_it(tmp_path):
    import pytest

    from submapslam.errors import SubmapSlamError

    target = tmp_path / "no_such_folder" / "map.pcd"
    with pytest.raises(SubmapSlamError, match="no_such_folder/map.pcd: could not write the PCD file"):
        write_pcd(target, np.zeros((3, 3)))
