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


def test_localization_ekf_sections_are_strict_and_settable_from_yaml(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("localization:\n  min_fitness: 0.6\n  lost_after: 3\nekf:\n  credibility:\n    b: 5.0\n")
    cfg = load_config(path)
    assert (cfg.localization.min_fitness, cfg.localization.lost_after) == (0.6, 3)
    assert cfg.localization.see_through == 0.5  # the rest keeps its default
    assert (cfg.ekf.credibility.a, cfg.ekf.credibility.b, cfg.ekf.credibility.remove_below) == (1.0, 5.0, 0.0)
    path.write_text("localization:\n  min_fitnes: 0.6\n")
    with pytest.raises(ConfigError, match="unknown config key 'localization.min_fitnes'"):
        load_config(path)
    with pytest.raises(ConfigError, match="localization.min_fitness"):
        config_from_dict({"localization": {"min_fitness": 1.5}})
    with pytest.raises(ConfigError, match=r"^credibility learning rate a must be > 0, got 0$"):
        config_from_dict({"ekf": {"credibility": {"a": 0}}})
    text = dump_config(PipelineConfig())
    assert "\nlocalization:\n  min_range: 0.1\n" in text and "\nekf:\n  credibility:\n    a: 1.0\n" in text


def test_ekf_section_defaults_are_the_ekf_commands_and_credibility_defaults_stay():
    from submapslam.config import CredibilityParams, EkfConfig

    c = EkfConfig().credibility
    assert isinstance(c, CredibilityParams) and (c.a, c.b, c.remove_below, c.min_observations) == (1.0, 1e9, 0.0, 1)
    assert CredibilityParams() == CredibilityParams(a=1.0, b=2.0, remove_below=0.05, min_observations=1)


def test_with_overrides_takes_only_given_values_and_validates():
    from submapslam.config import LocalizationConfig, with_overrides

    base = LocalizationConfig(min_fitness=0.6)
    same = with_overrides(base, "opts", min_fitness=None, lost_after=None)
    assert same == base and same is not base
    assert with_overrides(base, "opts", lost_after=2) == LocalizationConfig(min_fitness=0.6, lost_after=2)
    with pytest.raises(ConfigError, match=r"^opts: config key 'lost_after': "):
        with_overrides(base, "opts", lost_after=0)


def test_grid_params_are_strict_with_the_old_defaults():
    from pydantic import ValidationError

    from submapslam.mapping.evidence_grid import GridParams

    p = GridParams()
    assert (p.resolution, p.l_occ, p.l_free, p.l_min, p.l_max, p.free_confidence, p.occupied_threshold,
            p.clear_margin_cells, p.max_free_range, p.free_scan_stride) == (
        0.05, 0.85, -0.4, -4.0, 4.0, -1.5, 0.6, 2, 12.0, 2)
    with pytest.raises(ValidationError):
        GridParams(resoluton=0.1)
    with pytest.raises(ValidationError):
        GridParams(resolution=0.0)
