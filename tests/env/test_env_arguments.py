"""Every invalid constructor argument gives a ValueError naming it; numpy integers are integers,
bools are not; state() and render() before reset() say what to do."""

from __future__ import annotations

import numpy as np
import pytest

from cv2x_marl.env import MobilityEnv

FAST = {"overrides": ["sim.warmup_subframes=200"]}


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"max_cycles": True}, "max_cycles"),
        ({"max_cycles": 2.5}, "max_cycles"),
        ({"max_cycles": "10"}, "max_cycles"),
        ({"max_step_m": "5"}, "max_step_m"),
        ({"max_step_m": float("nan")}, "max_step_m"),
        ({"max_step_m": True}, "max_step_m"),
        ({"local_ratio": "half"}, "local_ratio"),
        ({"p_min": None}, "p_min"),
        ({"scale_m": float("inf")}, "scale_m"),
        ({"max_drift_m": "far"}, "max_drift_m"),
        ({"n_neighbours": 2.0}, "n_neighbours"),
        ({"n_neighbours": True}, "n_neighbours"),
        ({"movers": "0"}, "movers"),
        ({"movers": 3}, "movers"),
        ({"movers": [0.5]}, "movers"),
        ({"movers": [True]}, "movers"),
        ({"normalise_reward": 1}, "normalise_reward"),
        ({"roi": "yes"}, "roi"),
    ],
)
def test_bad_arguments_raise_value_error_naming_them(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=f"invalid env argument {name}="):
        MobilityEnv(**kwargs, **FAST)


def test_numpy_integers_are_accepted() -> None:
    env = MobilityEnv(max_cycles=np.int64(3), n_neighbours=np.int32(4), movers=np.array([0, 2]), **FAST)
    obs, _ = env.reset(seed=np.int64(1))
    assert env.max_cycles == 3 and obs["vehicle_0"].shape == (4 * 7 + 5,)
    assert env.mover_mask.sum() == 2


def test_state_and_render_before_reset() -> None:
    env = MobilityEnv(render_mode="rgb_array", **FAST)
    with pytest.raises(RuntimeError, match=r"call reset\(\) first"):
        env.state()
    with pytest.raises(RuntimeError, match=r"call reset\(\) first"):
        env.render()
