"""One value parser (issue 12, defect 4): the YAML 1.2 core schema for --set, config files,
training configs and baseline files; property tests of the parser, the configuration and the
env constructor (random input gives a valid object or a ValueError naming the culprit)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cv2x_marl.config import ConfigError, ScenarioConfig, apply_overrides, load_config_file, preset, to_dict
from cv2x_marl.env import MobilityEnv
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.train import load_train_config
from cv2x_marl.yamlcore import load, parse_scalar


@pytest.mark.parametrize(
    ("text", "value"),
    [
        ("1e3", 1000.0),  # YAML 1.1 (PyYAML): the string '1e3'
        ("3e-4", 0.0003),  # 1.1: a string, crashed SB3
        ("5.9e9", 5.9e9),  # 1.1: a string
        ("-2.5E+2", -250.0),
        (".5", 0.5),
        ("010", 10),  # 1.1: 8 (octal)
        ("0o10", 8),  # the core schema's explicit octal
        ("0x10", 16),  # the core schema's explicit hex
        ("1:40", "1:40"),  # 1.1: 100 (sexagesimal)
        ("2_3", "2_3"),  # 1.1: 23
        ("yes", "yes"),  # 1.1: True
        ("off", "off"),  # 1.1: False
        ("2001-12-14", "2001-12-14"),  # 1.1: a date
        ("True", True),
        ("FALSE", False),
        ("~", None),
        ("null", None),
        ("[1e3, 010]", [1000.0, 10]),
    ],
)
def test_core_schema_scalars(text: str, value: Any) -> None:
    assert parse_scalar(text) == value
    assert type(parse_scalar(text)) is type(value)


def test_infinities_and_nan_are_numbers_that_validation_refuses() -> None:
    assert load(".inf") == math.inf and load("-.Inf") == -math.inf and math.isnan(load(".nan"))
    with pytest.raises(ConfigError, match=r"radio\.tx_power_dbm: expected a finite number"):
        apply_overrides(preset("paper"), ["radio.tx_power_dbm=.inf"])
    with pytest.raises(ConfigError, match=r"vehicles\.n_vehicles: expected an integer"):
        apply_overrides(preset("paper"), ["vehicles.n_vehicles=.inf"])


def test_duplicate_keys_are_an_error() -> None:
    with pytest.raises(yaml.YAMLError, match="duplicate key 'a'"):
        load("a: 1\nb: 2\na: 3\n")


def test_set_config_file_and_training_config_share_the_parser(tmp_path: Path) -> None:
    cfg = apply_overrides(preset("paper"), ["vehicles.n_vehicles=010", "radio.tx_power_dbm=2.3e1"])
    assert cfg.vehicles.n_vehicles == 10 and cfg.radio.tx_power_dbm == 23.0
    with pytest.raises(ConfigError, match=r"vehicles\.n_vehicles: expected an integer.*got '1:40'"):
        apply_overrides(preset("paper"), ["vehicles.n_vehicles=1:40"])
    f = tmp_path / "c.yaml"
    f.write_text("vehicles:\n  n_vehicles: 1e2\nradio:\n  tx_power_dbm: 2e1\n")
    cfg = load_config_file(f, preset("paper"))
    assert cfg.vehicles.n_vehicles == 100 and cfg.radio.tx_power_dbm == 20.0
    f.write_text("vehicles:\n  n_vehicles: 30\nvehicles:\n  n_vehicles: 40\n")
    with pytest.raises(ConfigError, match="duplicate key 'vehicles'"):
        load_config_file(f, preset("paper"))
    t = tmp_path / "t.yaml"
    t.write_text("ppo:\n  learning_rate: 3e-4\n  n_steps: 0x40\ncheckpoint_every: 1e4\n")
    tc = load_train_config(t)
    assert tc.ppo.learning_rate == 3e-4 and tc.ppo.n_steps == 64 and tc.checkpoint_every == 10_000
    t.write_text("ppo:\n  gamma: 5\n")
    with pytest.raises(TrainError, match=r"ppo\.gamma must be a number in \(0, 1\]"):
        load_train_config(t)
    t.write_text("checkpoint_every: 1.5\n")
    with pytest.raises(TrainError, match="checkpoint_every must be an integer >= 1"):
        load_train_config(t)


# -- property tests ----------------------------------------------------------------------------
VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**12), max_value=10**12),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.lists(st.integers(min_value=-3, max_value=30), max_size=3),
)
KEYS = sorted(f"{section}.{key}" for section, keys in to_dict(ScenarioConfig()).items() for key in keys)


@settings(max_examples=150, deadline=None)
@given(text=st.text(max_size=20))
def test_parser_gives_a_value_or_a_yaml_error(text: str) -> None:
    try:
        parse_scalar(text)
    except yaml.YAMLError:
        pass


@settings(max_examples=300, deadline=None)
@given(key=st.sampled_from(KEYS), value=VALUES)
def test_any_config_value_gives_a_config_or_an_error_naming_the_key(key: str, value: Any) -> None:
    section = key.split(".")[0]
    try:
        cfg = apply_overrides(preset("paper"), [f"{key}={yaml.safe_dump(value, default_flow_style=True).strip()}"])
    except ConfigError as exc:
        # the key itself, or (cross-key checks) the section it belongs to, is named
        assert key in str(exc) or f"{section}." in str(exc) or "--set" in str(exc), str(exc)
        return
    assert isinstance(cfg, ScenarioConfig)


ENV_ARGS = [
    "max_cycles",
    "max_step_m",
    "movers",
    "reward",
    "local_ratio",
    "normalise_reward",
    "p_min",
    "n_neighbours",
    "scale_m",
    "max_drift_m",
    "roi",
    "truth_los",
    "render_mode",
    "observation",
    "privileged",
    "reward_form",
    "settle_steps",
    "model",
    "action_mode",
    "replan_every",
    "mode",
]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(name=st.sampled_from(ENV_ARGS), value=VALUES)
def test_any_env_argument_gives_an_env_or_a_value_error_naming_it(name: str, value: Any) -> None:
    try:
        env = MobilityEnv(**{name: value})
    except ValueError as exc:
        assert name in str(exc), str(exc)
        return
    assert isinstance(env, MobilityEnv)


@settings(max_examples=100, deadline=None)
@given(seed=VALUES)
def test_any_reset_seed_gives_an_episode_or_a_value_error(seed: Any) -> None:
    env = MobilityEnv(overrides=["sim.warmup_subframes=100"], max_cycles=2)
    try:
        env.reset(seed=seed)
    except ValueError as exc:
        assert "seed" in str(exc)
        return
    assert seed is None or (isinstance(seed, int) and not isinstance(seed, bool) and seed >= 0)


def test_the_training_config_schema_names_unknown_keys(tmp_path: Path) -> None:
    t = tmp_path / "t.yaml"
    t.write_text("ppo:\n  learnin_rate: 1e-3\n")
    with pytest.raises(TrainError, match=r"unknown ppo key\(s\) \['learnin_rate'\]"):
        load_train_config(t)
    assert dataclasses.is_dataclass(load_train_config(None))
