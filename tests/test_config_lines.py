"""A bad YAML config names the line of the problem."""

import pytest

from submapslam.config import load_config
from submapslam.errors import ConfigError


@pytest.mark.parametrize("text,message", [
    ("odometry:\n  voxel_size: 0.5\nsubmaps:\n  max_scanz: 3\n", "c.yaml:4: unknown config key 'submaps.max_scanz'"),
    ("odometry:\n  voxel_size: [1\nsubmaps: 2\n", "c.yaml:3: not valid YAML (expected ',' or ']'"),
    ("# tuned\nodometry:\n\n  voxel_size: abc\n", "c.yaml:4: config key 'odometry.voxel_size': Input should be a valid number"),
    ("loops:\n  enabled: true\nsubmaps: 5\n", "c.yaml:3: config key 'submaps'"),
    ("odometry:\n\tvoxel_size: 1\n", "c.yaml:2: not valid YAML"),
])
def test_config_errors_name_the_line(tmp_path, text, message):
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert str(err.value).startswith(f"{tmp_path}/{message}"), str(err.value)
