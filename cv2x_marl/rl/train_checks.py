"""What `cv2x-marl train` checks of a configuration before anything is trained or written: one env copy built
with the training arguments (:func:`probe_env`), SB3's size rule, and the peak memory estimated per component
(:func:`estimate_training_memory`) against the limit (:func:`check_training_memory`). :mod:`cv2x_marl.rl.train`
runs :func:`check_training_config` before it builds the VecEnv and the model, and re-exports these names.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cv2x_marl.env.mobility_env import check_copies
from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.train_config import _COPY_OVERHEAD_BYTES, TrainConfig
from cv2x_marl.sim import memory
from cv2x_marl.sim.memory import estimate_memory_bytes, format_bytes


def probe_env(cfg: TrainConfig) -> Any:
    """One env copy of ``cfg`` (its arguments checked by the env), and the copies it may run as.

    Raises:
        TrainError: an env argument the env refuses (its message names the argument and the
            allowed values), or copies that cannot share a process.
    """
    try:
        env = make_parallel_env(cfg.env_id, **cfg.env_for_training())
        check_copies(env, cfg.copies)
    except (ValueError, TypeError) as exc:
        raise TrainError(f"train.env of {cfg.env_id}: {exc}") from exc
    return env


def _network_parameters(obs_dim: int, act_dim: int, net_arch: tuple[int, ...]) -> int:
    """Parameters of SB3's MLP actor-critic: separate policy and value networks of ``net_arch``,
    the action head (with its log std) and the value head."""
    layers = 0
    width = obs_dim
    for units in net_arch:
        layers += width * units + units
        width = units
    return 2 * layers + (width * act_dim + 2 * act_dim) + (width + 1)


def estimate_training_memory(cfg: TrainConfig, env: Any) -> dict[str, int]:
    """Peak memory of a training run, per component, in bytes, from one env copy (:func:`probe_env`).

    * ``env_copies``: ``copies`` x what one copy keeps between episodes: its simulator's pair
      index, shadowing, snapshot and sensing arrays (:func:`cv2x_marl.sim.memory.estimate_memory_bytes`;
      measured 0.33 MB per copy on ``paper`` against 0.42 MB estimated, 14.1 MB on ``highway``
      against 15.6 MB), plus the peak of one reset (copies reset one after the other);
    * ``start_cache``: with ``start_pool``, the cached starts (pool + evaluation episodes), one copy's
      arrays each;
    * ``rollout_buffer``: SB3's buffer, ``n_steps`` x sub-envs x (observation + action + 6 float32),
      twice (its arrays are flattened into copies before each update);
    * ``networks``: the policy and value networks' parameters (float32) with their gradients and
      Adam's two moments, plus a mini-batch's activations (forward and backward).
    """
    sim = estimate_memory_bytes(env.config)
    kept = sum(sim.get(k, 0) for k in ("pair_index", "pair_list", "shadowing", "snapshot", "sensing"))
    per_copy = kept + _COPY_OVERHEAD_BYTES
    movers = int(np.count_nonzero(env.mover_mask))
    agent = env.possible_agents[int(np.flatnonzero(env.mover_mask)[0])]
    obs_dim = int(np.prod(env.observation_space(agent).shape))
    act_dim = int(np.prod(env.action_space(agent).shape))
    n_envs = cfg.copies * movers
    buffer_rows = cfg.ppo.n_steps * n_envs
    params = _network_parameters(obs_dim, act_dim, cfg.ppo.net_arch)
    batch = min(cfg.ppo.batch_size, buffer_rows)
    activations = batch * (obs_dim + sum(cfg.ppo.net_arch)) * 4 * 2 * 3
    cached = (cfg.start_pool + cfg.eval_episodes) if cfg.start_pool is not None else 0
    est = {
        "env_copies": cfg.copies * per_copy + int(sim["total"]),
        "start_cache": cached * per_copy,
        "rollout_buffer": 2 * buffer_rows * (obs_dim + act_dim + 6) * 4,
        "networks": params * 4 * 4 + activations,
        "per_copy": per_copy,
        "sub_envs": n_envs,
        "obs_dim": obs_dim,
    }
    est["total"] = est["env_copies"] + est["start_cache"] + est["rollout_buffer"] + est["networks"]
    return est


def check_training_memory(cfg: TrainConfig, env: Any, limit_bytes: int | None = None) -> dict[str, int]:
    """Refuse a training configuration whose estimated memory (:func:`estimate_training_memory`)
    exceeds the limit, before anything is allocated.

    Args:
        cfg: the configuration.
        env: one env copy of it (:func:`probe_env`).
        limit_bytes: the limit; None: ``CV2X_MARL_MEMORY_LIMIT_GB`` (GB) when set, else the memory
            available now (as for the simulator, :func:`cv2x_marl.sim.memory.check_memory`).

    Raises:
        TrainError: the estimate exceeds the limit; the message gives the figures, largest first,
            each with the key that sets it.
    """
    est = estimate_training_memory(cfg, env)
    checked = (limit_bytes, "limit_bytes") if limit_bytes is not None else memory.memory_limit(est["total"])
    if checked is None or est["total"] <= checked[0]:
        return est
    limit_bytes, source = checked
    parts = {
        "env_copies": f"train.copies={cfg.copies} env copies x {_gb(est['per_copy'])} each (plus one reset)",
        "start_cache": f"train.start_pool={cfg.start_pool} + train.eval_episodes={cfg.eval_episodes} cached starts",
        "rollout_buffer": (
            f"rollout buffer: ppo.n_steps={cfg.ppo.n_steps} x {est['sub_envs']:,} sub-envs (train.copies x movers) "
            f"x {est['obs_dim']} observation floats"
        ),
        "networks": f"networks: ppo.net_arch={list(cfg.ppo.net_arch)} (weights, gradients, Adam moments)",
    }
    ranked = sorted((k for k in parts if est[k] > 0), key=lambda k: -est[k])
    detail = "; ".join(f"{parts[k]}: {_gb(est[k])}" for k in ranked)
    raise TrainError(
        f"training needs an estimated {_gb(est['total'])} of memory, more than the {_gb(limit_bytes)} allowed "
        f"({source}): {detail}; reduce the first of these (or set {memory.ENV_LIMIT})"
    )


def _gb(n_bytes: float) -> str:
    return format_bytes(n_bytes)


def check_training_config(cfg: TrainConfig) -> dict[str, int]:
    """Everything about ``cfg`` that can be checked without training: the env arguments (one env
    copy is built), SB3's size rules, and the memory estimate (:func:`check_training_memory`).

    Returns:
        The memory estimate.

    Raises:
        TrainError: naming the key at fault.
    """
    env = probe_env(cfg)
    try:
        est = check_training_memory(cfg, env)
    finally:
        env.close()
    if cfg.ppo.n_steps * est["sub_envs"] < 2:  # SB3: advantages normalised over the rollout
        raise TrainError(
            f"ppo.n_steps x sub-envs (train.copies x movers) must be >= 2, got {cfg.ppo.n_steps} x {est['sub_envs']}"
        )
    return est
