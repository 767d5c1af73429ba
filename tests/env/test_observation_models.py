"""An observation version added from one file: a toy model registered here, used by the env as the built-in ones."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from numpy.typing import NDArray

from cv2x_marl.env import MobilityEnv
from cv2x_marl.env.observation import FEATURES, OWN, VERSION_BLOCKS
from cv2x_marl.env.observation_models import OBSERVATIONS, ObservationModel, register_observation

FAST = {"overrides": ["sim.warmup_subframes=200"]}


class DriftObservation(ObservationModel):
    """Toy version 90: the v0 block, then the own drift from the start (in ``scale_m``) and the steps taken."""

    version = 90
    own = 3

    def fill(self, env: MobilityEnv, obs: NDArray[np.float32], rows: NDArray[np.int64]) -> None:
        k = env.layout.own_v1_offset
        obs[:, k : k + 2] = (env.positions_m - env.start_m)[rows] / env.layout.scale_m
        obs[:, k + 2] = env.t


@pytest.fixture
def toy() -> Iterator[type[ObservationModel]]:
    register_observation(DriftObservation)
    yield DriftObservation
    del OBSERVATIONS[90], VERSION_BLOCKS[90]


def test_a_registered_version_is_an_option_with_its_layout_and_its_entries(toy: type[ObservationModel]) -> None:
    env = MobilityEnv(observation=90, max_cycles=3, max_step_m=5.0, movers=[0], **FAST)
    k = env.n - 1
    assert env.observation_space("vehicle_0").shape == (k * FEATURES + OWN + 3,)
    obs, _ = env.reset(seed=3)
    assert obs["vehicle_0"][-3:].tolist() == [0.0, 0.0, 0.0]
    zero = np.zeros(2, dtype=np.float32)
    actions = {a: zero for a in env.agents} | {"vehicle_0": np.array([1.0, -0.5], dtype=np.float32)}
    obs, *_ = env.step(actions)
    # vehicle 0 moved by (5, -2.5) m (inside the paper grid's box at seed 3, no drift bound): / scale_m 100
    np.testing.assert_allclose(obs["vehicle_0"][-3:], [0.05, -0.025, 1.0], rtol=1e-6)
    assert obs["vehicle_1"][-3:].tolist() == [0.0, 0.0, 1.0]  # a vehicle that stays put
    # the v0 block is the built-in one: equal to version 0's on the same episode
    ref = MobilityEnv(observation=0, max_cycles=3, max_step_m=5.0, movers=[0], **FAST)
    ref.reset(seed=3)
    ref_obs, *_ = ref.step(actions)
    np.testing.assert_array_equal(obs["vehicle_0"][:-3], ref_obs["vehicle_0"])


def test_unregistered_versions_are_refused_naming_the_registered_ones(toy: type[ObservationModel]) -> None:
    with pytest.raises(ValueError, match=r"observation=91; allowed: 0 \| 1 \| 2 \| 3 \| 4 \| 5 \| 90"):
        MobilityEnv(observation=91, **FAST)


def test_a_taken_version_is_refused() -> None:
    class Clash(ObservationModel):
        version = 3

    with pytest.raises(ValueError, match="observation version 3 is taken by MeasuredObservation"):
        register_observation(Clash)
    assert OBSERVATIONS[3].__name__ == "MeasuredObservation"
