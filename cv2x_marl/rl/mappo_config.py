"""The configuration of a MAPPO run (``cv2x-marl train --config FILE`` with ``algo: mappo``); no torch import.

A MAPPO file is a training config (docs/rl.md) whose top-level ``algo`` is ``mappo``:

.. code-block:: yaml

    algo: mappo
    env_id: cv2x/Cooperative-v0
    copies: 8                 # env copies K: K episodes per iteration, each of max_cycles steps
    env: {max_cycles: 100, max_step_m: 5.0, start_pool: 256}
    mappo: {learning_rate: 3e-4, n_epochs: 5, minibatch_steps: 200, ...}   # MappoSettings
    eval_every: 10            # iterations between learning-curve rows (eval.csv)
    checkpoint_every: 10      # iterations between checkpoints (--resume continues from the newest)
    eval_episodes: 8
    eval_seed: 10000

:func:`config_algo` tells the CLI which trainer a file (or ``--algo``) asks for; :func:`load_mappo_config`
reads and checks a MAPPO file, rejecting unknown keys by name with the allowed ones.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cv2x_marl.checks import is_int
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.train_config import (
    MAX_COPIES,
    PPO_REALS,
    check_pooled_env,
    check_reals,
    read_sections,
    with_cli_values,
)
from cv2x_marl.yamlcore import load_mapping

#: the TensorDict group of the agents (MAPPO's collection and update, :mod:`cv2x_marl.rl.mappo`)
GROUP = "agents"

#: the trainers ``cv2x-marl train`` dispatches to (``--algo`` or the config's ``algo``)
ALGOS = ("ppo", "mappo", "utility-map", "imitation")
#: the env ids MAPPO trains on: on ``cv2x/Cooperative-v0`` every vehicle moves and the reward is the team's, so one
#: critic value per env step (on ``state()``) serves every agent (``cv2x/Cooperative-v1``: the same, the vehicles
#: sampling their moves at their turns, :meth:`cv2x_marl.rl.mappo.Mappo.collect`); on ``cv2x/Resource-v0`` every
#: vehicle that reselects picks an entry of its candidate list (masked ``Discrete`` actions), each rewarded with its
#: own utility (or the team's)
MAPPO_ENV_IDS = ("cv2x/Cooperative-v0", "cv2x/Cooperative-v1", "cv2x/Resource-v0")
#: the env ids of masked discrete actions (:class:`cv2x_marl.policies.mappo_nets.MaskedActor`)
MASKED_ENV_IDS = ("cv2x/Resource-v0",)
#: ``mappo.encoder``: what the shared actor reads (:mod:`cv2x_marl.policies.encoders`; ``mlp``: the flat observation;
#: ``candidates``: the masked actor's scorer shared over the candidate list)
ENCODERS = ("mlp", "deepsets", "attention", "candidates", "candidates-attention")
#: the encoders of each action kind: the Gaussian actor (Cooperative-v0) and the masked one (Resource-v0)
GAUSSIAN_ENCODERS = ("mlp", "deepsets", "attention")
MASKED_ENCODERS = ("mlp", "candidates", "candidates-attention")
#: ``mappo.critic``: ``state`` (MAPPO: ``state()``, with individual rewards followed by the agent's observation) or
#: ``observation`` (independent PPO with parameter sharing: each agent's value from its own observation)
CRITICS = ("state", "observation")
#: the rewards a masked run may train on (``env.reward``; the env's default is ``individual``)
MASKED_REWARDS = ("individual", "team", "mixed")
#: the widest hidden layer of ``actor_net`` / ``critic_net`` / ``encoder_units``
MAX_UNITS = 65_536


def count_at_least(name: str, value: Any, low: int = 1) -> int:
    """``value`` as an int >= ``low`` (a whole float such as YAML's ``1e4`` counts; bools do not)."""
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if not is_int(value) or value < low:
        raise TrainError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


def hidden_layers(name: str, value: Any, max_units: int = MAX_UNITS) -> tuple[int, ...]:
    """``value`` as units per hidden layer: a non-empty list of integers in [1, ``max_units``]."""
    rule = f"a non-empty list of integers in [1, {max_units:,}] (units per hidden layer)"
    if not isinstance(value, tuple | list) or not value:
        raise TrainError(f"{name} must be {rule}, got {value!r}")
    try:
        units = tuple(count_at_least(name, v) for v in value)
    except TrainError:
        raise TrainError(f"{name} must be {rule}, got {list(value)!r}") from None
    if max(units) > max_units:
        raise TrainError(f"{name} must be {rule}, got {list(value)!r}")
    return units


@dataclass(frozen=True)
class MappoSettings:
    """MAPPO hyperparameters (the ``mappo:`` mapping; Yu et al., *The Surprising Effectiveness of PPO in
    Cooperative Multi-Agent Games*, NeurIPS 2022)."""

    learning_rate: float = 3e-4
    #: passes over one iteration's samples
    n_epochs: int = 5
    #: env steps (each with all its agents) per mini-batch
    minibatch_steps: int = 200
    gamma: float = 0.95
    gae_lambda: float = 0.95
    clip_range: float = 0.2
    #: weight of the (Monte Carlo) entropy of the squashed Gaussian; 0 switches the term off
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    #: initial log standard deviation of the Gaussian before the tanh squashing
    log_std_init: float = -0.5
    #: hidden layers of the shared actor's MLP (after the encoder)
    actor_net: tuple[int, ...] = (128, 128)
    #: hidden layers of the centralised critic's MLP on ``state()``
    critic_net: tuple[int, ...] = (256, 256)
    encoder: str = "deepsets"
    #: d of :class:`~cv2x_marl.policies.encoders.NeighbourEncoder` (features 3 d)
    encoder_units: int = 64
    #: what the critic reads (:data:`CRITICS`); ``observation`` only with masked actions (cv2x/Resource-v0)
    critic: str = "state"
    #: masked actions: the weight of the observation-seeded Gumbel noise in the deterministic choice (0: the plain
    #: argmax over the valid entries; :class:`~cv2x_marl.policies.mappo_nets.MaskedActor`)
    dither: float = 0.0

    def __post_init__(self) -> None:
        check_reals(
            self,
            "mappo",
            {
                **PPO_REALS,
                "log_std_init": (lambda v: -20 <= v <= 2, "a number in [-20, 2]"),
                "dither": (lambda v: 0 <= v <= 10, "a number in [0, 10]"),
            },
        )
        for name in ("n_epochs", "minibatch_steps", "encoder_units"):
            object.__setattr__(self, name, count_at_least(f"mappo.{name}", getattr(self, name)))
        if self.encoder_units > MAX_UNITS:
            raise TrainError(f"mappo.encoder_units must be an integer in [1, {MAX_UNITS:,}], got {self.encoder_units}")
        for name in ("actor_net", "critic_net"):
            object.__setattr__(self, name, hidden_layers(f"mappo.{name}", getattr(self, name)))
        if not isinstance(self.encoder, str) or self.encoder not in ENCODERS:
            raise TrainError(f"mappo.encoder must be one of {', '.join(ENCODERS)}, got {self.encoder!r}")
        if not isinstance(self.critic, str) or self.critic not in CRITICS:
            raise TrainError(f"mappo.critic must be one of {', '.join(CRITICS)}, got {self.critic!r}")


@dataclass(frozen=True)
class MappoConfig:
    """Everything a MAPPO run needs besides timesteps and seed."""

    env_id: str = "cv2x/Cooperative-v0"
    #: env copies K: each iteration collects one episode (``env.max_cycles`` steps) of each copy
    copies: int = 8
    #: env keyword arguments; ``start_pool`` P (required, >= 1): episodes start from the protocol's first P
    #: training seeds (:func:`cv2x_marl.env.seeds.training_pool`), never from a held-out one
    env: dict[str, Any] = field(default_factory=lambda: {"max_cycles": 100, "max_step_m": 5.0, "start_pool": 256})
    mappo: MappoSettings = field(default_factory=MappoSettings)
    #: iterations between two learning-curve rows (``eval.csv``)
    eval_every: int = 10
    #: iterations between two checkpoints (``checkpoints/mappo_<iteration>.pt``; also at the end and at an interrupt)
    checkpoint_every: int = 10
    eval_episodes: int = 8
    eval_seed: int = 10_000
    algo: str = "mappo"

    def __post_init__(self) -> None:
        if self.algo != "mappo":
            raise TrainError(f"algo must be 'mappo' in a MAPPO config, got {self.algo!r}")
        if self.env_id not in MAPPO_ENV_IDS:
            raise TrainError(
                f"env_id {self.env_id!r}: MAPPO trains on {', '.join(MAPPO_ENV_IDS)} (every vehicle moves for the "
                "team reward); other ids train with algo: ppo"
            )
        for name in ("copies", "eval_every", "checkpoint_every", "eval_episodes"):
            object.__setattr__(self, name, count_at_least(f"train.{name}", getattr(self, name)))
        if self.copies > MAX_COPIES:
            raise TrainError(f"train.copies must be an integer in [1, {MAX_COPIES:,}], got {self.copies}")
        object.__setattr__(self, "eval_seed", count_at_least("train.eval_seed", self.eval_seed, low=0))
        check_pooled_env(self.env_id, self.env, "MAPPO")
        masked = self.env_id in MASKED_ENV_IDS
        # the critic's one value per step needs the team reward and every mover (Cooperative-v0); a masked run
        # (Resource-v0) has per-agent values and may take the team reward instead of the individual one
        for key in ("movers",) if masked else ("reward", "movers"):
            if key in self.env:
                raise TrainError(f"train.env.{key}: MAPPO keeps {self.env_id}'s own {key} (leave the key out)")
        if masked and self.env.get("reward", "individual") not in MASKED_REWARDS:
            raise TrainError(
                f"train.env.reward must be one of {', '.join(MASKED_REWARDS)} on {self.env_id}, "
                f"got {self.env['reward']!r}"
            )
        allowed = MASKED_ENCODERS if masked else GAUSSIAN_ENCODERS
        if self.mappo.encoder not in allowed:
            raise TrainError(
                f"mappo.encoder {self.mappo.encoder!r} does not act on {self.env_id}; "
                f"encoders there: {', '.join(allowed)}"
            )
        if not masked and self.mappo.dither != 0:
            raise TrainError(f"mappo.dither is for the masked choices of {', '.join(MASKED_ENV_IDS)} (leave it out)")
        if not masked and self.mappo.critic != "state":
            raise TrainError(
                f"mappo.critic {self.mappo.critic!r}: {self.env_id} trains with the critic on state() (the team "
                f"reward); critic: observation is for {', '.join(MASKED_ENV_IDS)}"
            )

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["mappo"]["actor_net"] = list(self.mappo.actor_net)
        d["mappo"]["critic_net"] = list(self.mappo.critic_net)
        # the defaults of the masked path's keys are left out: run folders written before them still --resume
        if self.mappo.critic == "state":
            del d["mappo"]["critic"]
        if self.mappo.dither == 0:
            del d["mappo"]["dither"]
        return {"algo": d.pop("algo"), **d}


def config_algo(path: Path | None, cli_algo: str | None) -> str:
    """The trainer ``cv2x-marl train`` runs: ``--algo`` (``cli_algo``), else the config file's ``algo``, else ``ppo``.

    Raises:
        TrainError: an algorithm not in :data:`ALGOS`, or ``--algo`` and the file naming different ones.
    """
    file_algo = None if path is None else load_mapping(path, "training config", TrainError).get("algo")
    for where, algo in (("--algo", cli_algo), (f"{path}: algo", file_algo)):
        if algo is not None and algo not in ALGOS:
            raise TrainError(f"{where} {algo!r} is not available; algorithms: {', '.join(ALGOS)}")
    if cli_algo is not None and file_algo is not None and cli_algo != file_algo:
        raise TrainError(f"--algo {cli_algo} and the config's algo: {file_algo} differ (give one)")
    return str(cli_algo or file_algo or "ppo")


def load_mappo_config(path: Path | None, env_id: str | None = None, copies: int | None = None) -> MappoConfig:
    """Read a MAPPO file (module docstring); a run folder's ``train_config.json`` is one (its ``seed`` and
    ``timesteps`` are skipped: :func:`cv2x_marl.rl.train.run_settings` reads them). CLI values override the file.

    Raises:
        TrainError: unknown keys (named, with the allowed ones) or values out of range.
    """
    data, raw, env = read_sections(
        path, ("seed", "timesteps"), MappoConfig, "MAPPO config", "mappo", MappoSettings, "MAPPO"
    )
    target = env_id if env_id is not None else data.get("env_id", MappoConfig.env_id)
    # the env arguments' defaults: Cooperative-v0's moves (max_step_m) mean nothing to a resource choice
    defaults = {"max_cycles": 100, "start_pool": 256} if target in MASKED_ENV_IDS else MappoConfig().env
    if env_id is not None:
        data["env_id"] = env_id
    cfg = MappoConfig(**{**data, "env": {**defaults, **env}, "mappo": MappoSettings(**raw)})
    return with_cli_values(cfg, None, copies)
