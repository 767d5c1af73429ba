"""EnvOptions: the env's options as one schema (docs table current, unknown names refused with the
allowed ones, version defaults, ranges and choices named in the messages)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from cv2x_marl.config import TRUTH_LOS
from cv2x_marl.env.options import (
    MAX_CYCLES,
    VERSION_DEFAULTS,
    EnvOptions,
)
from cv2x_marl.env.options_table import options_markdown

DOC = Path(__file__).resolve().parents[2] / "docs" / "env.md"


def test_docs_table_is_current() -> None:
    assert options_markdown() in DOC.read_text(), "regenerate with: python -m cv2x_marl.env.options_table"


def test_unknown_names_are_refused_listing_the_allowed_ones() -> None:
    with pytest.raises(ValueError, match=r"unknown env argument\(s\) max_steps; allowed: preset, overrides"):
        EnvOptions.from_mapping({"max_steps": 3})


def test_version_defaults() -> None:
    assert EnvOptions.from_mapping({}, "v0").observation == 0
    v1 = EnvOptions.from_mapping({}, "v1")
    assert (v1.observation, v1.reward_form, v1.normalise_reward) == (1, "improvement", True)
    assert EnvOptions.from_mapping({"reward_form": "utility"}, "v2").reward_form == "utility"
    assert EnvOptions.from_mapping({}, "v2").observation == 2
    assert set(VERSION_DEFAULTS) == {
        "v0", "v1", "v2", "v3", "cooperative-v0", "cooperative-v1", "traffic-v0", "traffic-v1", "resource-v0",
    }  # fmt: skip
    v3 = EnvOptions.from_mapping({}, "v3")
    assert (v3.observation, v3.shadow_field, v3.reward_form, v3.normalise_reward) == (3, True, "improvement", True)
    coop = EnvOptions.from_mapping({}, "cooperative-v0")
    assert (coop.observation, coop.shadow_field, coop.reward) == (3, True, "team")
    assert coop.decision_order == "simultaneous"
    assert EnvOptions.from_mapping({}, "cooperative-v1") == dataclasses.replace(coop, decision_order="subframe")
    assert (EnvOptions().sensing_window, EnvOptions().rsrp_error_db, EnvOptions().shadow_field) == (10, 3.0, False)
    with pytest.raises(ValueError, match="unknown env version 'v9'"):
        EnvOptions.from_mapping({}, "v9")


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"max_cycles": MAX_CYCLES + 1}, rf"max_cycles=10001; allowed: integer in \[1, {MAX_CYCLES}\]"),
        ({"truth_los": "sometimes"}, r"truth_los='sometimes'; allowed: " + r" \| ".join(TRUTH_LOS)),
        ({"p_min": 1.0}, r"p_min=1.0; allowed: finite number in \(0, 1\)"),
        ({"max_drift_m": 0.0}, r"max_drift_m=0.0; allowed: null or finite number > 0"),
        ({"settle_steps": 100}, r"settle_steps=100; allowed: integer in \[0, max_cycles\)"),
        ({"observation": True}, r"observation=True; allowed: 0 \| 1 \| 2"),
    ],
)
def test_refusals_name_the_argument_and_the_allowed_values(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match="invalid env argument " + message):
        EnvOptions(**kwargs)


def test_python_api_types() -> None:
    opts = EnvOptions(max_cycles=np.int64(3), roi=np.bool_(True), overrides="sim.warmup_subframes=200")
    assert opts.max_cycles == 3 and opts.overrides == ("sim.warmup_subframes=200",)
    with pytest.raises(ValueError, match=r"invalid env argument max_cycles=3\.0"):
        EnvOptions(max_cycles=3.0)


def test_the_roles_say_what_a_start_and_a_saved_policy_depend_on() -> None:
    from cv2x_marl.env.mobility_env import MobilityEnv
    from cv2x_marl.env.mover_batch import batch_signature
    from cv2x_marl.env.options import EPISODE_ROLES, POLICY_ROLES, ROLES, options_with_role
    from cv2x_marl.env.starts import START_OPTIONS, start_key

    assert set(options_with_role(*ROLES)) == {f.name for f in dataclasses.fields(EnvOptions)}
    assert set(options_with_role("run")) == {"render_mode", "reset_cache", "start_pool", "episode_metrics"}
    assert {"observation", "max_step_m", "speed_command"} <= set(options_with_role(*POLICY_ROLES))
    assert not {"reward", "local_ratio", "start_pool"} & set(options_with_role(*POLICY_ROLES))
    assert set(START_OPTIONS) == set(options_with_role(*EPISODE_ROLES)) - {"preset", "overrides", "config"}
    with pytest.raises(ValueError, match="unknown option role"):
        options_with_role("dynamics")
    fast = {"overrides": ["sim.warmup_subframes=200"], "movers": [0]}
    base = MobilityEnv(**fast)
    run_only = MobilityEnv(**fast, episode_metrics=True, reset_cache=3)
    reward = MobilityEnv(**fast, reward_form="improvement")
    # a start does not depend on how the env runs, but on everything an episode is made of
    assert start_key(base, 7) == start_key(run_only, 7)
    assert start_key(base, 7) != start_key(reward, 7)
    # the copies of one batch are one env: every option counts (a kept start's infos depend on episode_metrics)
    assert batch_signature(base) != batch_signature(run_only)
    assert batch_signature(base) == batch_signature(MobilityEnv(**fast))


def test_an_option_is_an_attribute_of_the_env_checked_when_set() -> None:
    from cv2x_marl.env.mobility_env import MobilityEnv

    env = MobilityEnv(overrides=["sim.warmup_subframes=200"], reward="mixed", local_ratio=0.25, max_cycles=3)
    assert (env.reward, env.local_ratio, env.max_cycles, env.reward_kind) == ("mixed", 0.25, 3, "mixed")
    env.reset(seed=0)
    env.local_ratio = 1.0  # the mixed reward is then the own utility alone, from the next step on
    env.reward_form = "utility"
    _, rewards, *_ = env.step({a: [0.0, 0.0] for a in env.agents})
    assert env.options.local_ratio == 1.0
    assert rewards["vehicle_3"] == env.utility[3]
    with pytest.raises(ValueError, match=r"invalid env argument local_ratio=2.0; allowed: finite number in \[0, 1\]"):
        env.local_ratio = 2.0
    with pytest.raises(AttributeError, match="observation shapes the env's spaces and parts, fixed at construction"):
        env.observation = 3
    env.max_cycles = 2  # PettingZoo's API test shortens episodes this way
    _, _, _, truncs, _ = env.step({a: [0.0, 0.0] for a in env.agents})
    assert all(truncs.values()) and env.agents == []
