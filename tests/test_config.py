import pytest

from submapslam.config import PipelineConfig, config_from_dict, dump_config, load_config
from submapslam.errors import ConfigError


def test_defaults_round_trip_through_yaml(tmp_path):
    text = dump_config(PipelineConfig())
    path = tmp_path / "c.yaml"
    path.write_text(text)
    assert load_config(path) == PipelineConfig()


def test_misspelled_key_is_an_error_naming_the_key(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("submaps:\n  max_distanse: 5\n")
    with pytest.raises(ConfigError, match="unknown config key 'submaps.max_distanse'"):
        load_config(path)


def test_wrong_type_and_range_errors():
    with pytest.raises(ConfigError, match="odometry.max_range"):
        config_from_dict({"odometry": {"max_range": -1}})
    with pytest.raises(ConfigError, match="loops.min_fitness"):
        config_from_dict({"loops": {"min_fitness": "high"}})


def test_not_a_mapping_and_bad_yaml(tmp_path):
    p = tmp_path / "a.yaml"
    p.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(p)
    p.write_text("a: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(p)
    with pytest.raises(ConfigError, match="no such config file"):
        load_config(tmp_path / "missing.yaml")


def test_values_are_applied():
    cfg = config_from_dict({"submaps": {"max_distance": 4.5}, "backend": {"robust_kernel": "huber"}})
    assert cfg.submaps.max_distance == 4.5 and cfg.backend.robust_kernel == "huber"


def test_a_directory_or_binary_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path)
    p = tmp_path / "bin.yaml"
    p.write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(ConfigError):
        load_config(p)
