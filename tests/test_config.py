"""Tracker configuration: the default file equals the defaults, and every kind of mistake raises a
ConfigError that names the key, the allowed values and the file."""
from __future__ import annotations

import pytest
import yaml

from app.config import DEFAULT_CONFIG_PATH, KEYS, TrackerConfig, config_from_dict, config_to_dict, load_config
from app.errors import ConfigError


def write(tmp_path, text):
    path = tmp_path / "tracker.yaml"
    path.write_text(text)
    return path


def test_default_file_equals_the_dataclass_defaults():
    assert load_config(DEFAULT_CONFIG_PATH) == TrackerConfig()
    assert load_config(None) == TrackerConfig()


def test_default_file_documents_every_key():
    data = yaml.safe_load(DEFAULT_CONFIG_PATH.read_text())
    listed = {f"{s}.{k}" for s, keys in data.items() for k in keys}
    assert listed == set(KEYS)
    text = DEFAULT_CONFIG_PATH.read_text()
    for key in KEYS:
        line = next(line for line in text.splitlines() if line.strip().startswith(key.split(".")[1] + ":"))
        assert "#" in line, f"{key} has no comment"


def test_values_are_read_into_the_nested_settings(tmp_path):
    path = write(tmp_path, """
filter: {particles: 600, sampling: blockwise}
motion: {lambda_v: 0.95}
likelihood: {occlusion: smooth_exponential, classification: true}
render: {resolution: [160, 120]}
status: {min_covered_pixels: 50}
""")
    c = load_config(path)
    assert c.particles == 600 and c.sampling == "blockwise"
    assert c.motion.lambda_v == 0.95 and c.motion.sigma_a == 2.0  # a key left out keeps its default
    assert c.likelihood.occlusion == "smooth_exponential" and c.likelihood.classification
    assert c.resolution == (160, 120) and c.status.min_covered_pixels == 50


def test_to_dict_round_trips():
    c = load_config(None)
    assert config_from_dict(config_to_dict(c)) == c


def test_unknown_key_suggests_the_close_one(tmp_path):
    path = write(tmp_path, "filter:\n  particle: 300\n")
    with pytest.raises(ConfigError, match=r"filter\.particle'.*did you mean 'filter\.particles'") as info:
        load_config(path)
    assert info.value.key == "filter.particle"
    assert str(path) in str(info.value)


def test_a_key_in_the_wrong_section_names_the_right_one():
    with pytest.raises(ConfigError, match=r"did you mean 'motion\.sigma_a'"):
        config_from_dict({"filter": {"sigma_a": 4.0}})


def test_unknown_section_is_rejected_with_the_valid_ones():
    with pytest.raises(ConfigError, match=r"unknown section \(did you mean 'motion'\?\).*filter, init"):
        config_from_dict({"motoin": {"sigma_a": 4.0}})


@pytest.mark.parametrize("data,key,pattern", [
    ({"filter": {"particles": 0}}, "filter.particles", r"outside the allowed range \[1, 100000\]"),
    ({"filter": {"particles": 2.5}}, "filter.particles", "expected an integer"),
    ({"filter": {"particles": True}}, "filter.particles", "expected an integer"),
    ({"filter": {"resample_threshold": 1.5}}, "filter.resample_threshold", r"\[0, 1\]"),
    ({"filter": {"sampling": "blockwis"}}, "filter.sampling", r"joint, blockwise \(did you mean 'blockwise'"),
    ({"filter": {"resampling": "residual"}}, "filter.resampling", "multinomial, stratified, systematic"),
    ({"motion": {"sigma_a": "5"}}, "motion.sigma_a", "expected a finite number"),
    ({"motion": {"lambda_v": float("nan")}}, "motion.lambda_v", "expected a finite number"),
    ({"likelihood": {"sigma_base": 0.0}}, "likelihood.sigma_base", r"\(0, 0.1\]"),
    ({"likelihood": {"classification": "yes"}}, "likelihood.classification", "true or false"),
    ({"likelihood": {"occlusion": "smooth"}}, "likelihood.occlusion", "exponential, smooth_exponential"),
    ({"likelihood": {"w_u": 0, "w_e": 0, "w_n": 0}}, "likelihood.w_n", "must be positive"),
    ({"render": {"resolution": [80]}}, "render.resolution", r"\[width, height\]"),
    ({"render": {"resolution": "80x60"}}, "render.resolution", r"\[width, height\]"),
    ({"render": {"near": 1.0, "far": 0.5}}, "render.far", "must exceed near"),
    ({"render": {"backend": "numba"}}, "render.backend", r"'numba' is not one of: auto, gl, cpu"),
    ({"status": {"uncertain_position_spread": 0.02}}, "status.uncertain_position_spread", "refine.feedback_spread"),
    ({"refine": {"prior_forget_ratio": 0.5}}, "refine.prior_forget_ratio", "above 1"),
    ({"refine": {"prior_forget_ratio": -1.0}}, "refine.prior_forget_ratio", "outside the allowed range"),
    ({"refine": {"outline_ring": "no"}}, "refine.outline_ring", "true or false"),
    ({"refine": {"tissue_border": 1}}, "refine.tissue_border", "true or false"),
    ({"refine": {"nearby_hold": -1}}, "refine.nearby_hold", r"outside the allowed range"),
    ({"refine": {"nearby_hold": 1.5}}, "refine.nearby_hold", "expected an integer"),
    ({"refine": {"nearby_margin": 2.0}}, "refine.nearby_margin", "outside the allowed range"),
    ({"refine": {"nearby_hold": 0}}, "refine.nearby_hold", "outside the allowed range"),
    ({"refine": {"nearby_sigma_p": 0.0}}, "refine.nearby_sigma_p", "outside the allowed range"),
    ({"filter": [1, 2]}, "filter", "expected a mapping"),
])
def test_invalid_values_name_their_key(data, key, pattern):
    with pytest.raises(ConfigError, match=pattern) as info:
        config_from_dict(data, source="x.yaml")
    assert info.value.key == key
    assert f"config key '{key}'" in str(info.value) and str(info.value).startswith("x.yaml: ")


def test_empty_sections_and_files_give_defaults(tmp_path):
    assert load_config(write(tmp_path, "")) == TrackerConfig()
    assert load_config(write(tmp_path, "filter:\n")) == TrackerConfig()


def test_missing_file_and_bad_yaml_are_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="no such configuration file"):
        load_config(tmp_path / "absent.yaml")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(write(tmp_path, "filter: [unclosed\n"))
    with pytest.raises(ConfigError, match="expected a mapping of sections"):
        load_config(write(tmp_path, "- 1\n- 2\n"))


def test_the_shipped_default_yaml_states_exactly_the_built_in_defaults():
    from app.config import DEFAULT_CONFIG_PATH, config_to_dict, load_config

    assert config_to_dict(load_config(DEFAULT_CONFIG_PATH)) == config_to_dict(load_config(None))
