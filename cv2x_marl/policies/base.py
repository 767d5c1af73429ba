"""One ``Policy`` protocol for every mover: observations in, actions out.

A policy maps the env's per-agent observations (dict of float32 vectors, see
:mod:`cv2x_marl.env.observation`) to per-agent actions in ``[-1, 1]^2`` (times the env's
``max_step_m``). ``reset(seed)`` is called at the start of every episode, so stochastic policies
are reproducible per episode.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

Observations = dict[str, NDArray[np.float32]]
Actions = dict[str, NDArray[np.float32]]


@runtime_checkable
class Policy(Protocol):
    """What every mover implements."""

    name: str

    def reset(self, seed: int | None = None) -> None:
        """Start an episode (seeds any randomness)."""

    def act(self, observations: Observations) -> Actions:
        """Actions for the agents present in ``observations``."""
        ...


class StaticPolicy:
    """Never moves: the baseline every gain is measured against."""

    name = "static"

    def reset(self, seed: int | None = None) -> None:
        return None

    def act(self, observations: Observations) -> Actions:
        return {a: np.zeros(2, dtype=np.float32) for a in observations}


class RandomPolicy:
    """Uniform actions in the box, from its own generator (seeded per episode)."""

    name = "random"

    def __init__(self, seed: int | None = None) -> None:
        self.rng = np.random.default_rng(seed)

    def reset(self, seed: int | None = None) -> None:
        if seed is not None:
            self.rng = np.random.default_rng(np.random.SeedSequence([seed, 0xA11CE]))

    def act(self, observations: Observations) -> Actions:
        acts = self.rng.uniform(-1.0, 1.0, size=(len(observations), 2)).astype(np.float32)
        return dict(zip(observations, acts, strict=True))


class BatchPolicy:
    """Any batch actor as a policy: one call for all agents present, deterministic and stateless.

    For movers trained outside the package (RLlib, TorchRL, your own torch module): evaluate them
    with :func:`cv2x_marl.experiments.evaluate.evaluate` on the same episodes as every baseline.

    Args:
        act_fn: observations [n_agents, obs_dim] (float32, in the order of the observation dict)
            -> actions [n_agents, 2] in [-1, 1].
        name: the name results are reported under.
    """

    def __init__(self, act_fn: Callable[[NDArray[np.float32]], object], name: str = "batch") -> None:
        self.act_fn = act_fn
        self.name = name

    def reset(self, seed: int | None = None) -> None:
        return None

    def act(self, observations: Observations) -> Actions:
        agents = list(observations)
        obs = np.stack([observations[a] for a in agents]).astype(np.float32, copy=False)
        acts = np.asarray(self.act_fn(obs), dtype=np.float32).reshape(len(agents), 2)
        return dict(zip(agents, acts, strict=True))
