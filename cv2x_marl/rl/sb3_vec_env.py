"""An SB3 ``VecEnv`` that exposes every moving agent of K env copies as one sub-env.

With parameter sharing, one policy acts for every vehicle: sub-env ``k * M + m`` is mover ``m``
of copy ``k`` (M movers per copy). What SuperSuit's ``pettingzoo_env_to_vec_env_v1`` gets wrong
for SB3, this adapter does explicitly:

* seeding: ``VecEnv.seed(s)`` (called by ``PPO(..., seed=s)``) gives copy k the seed
  ``s + k * M``; its episodes then draw their seeds from a generator seeded with it, so two runs
  with one seed see identical episodes (and PPO ends with identical parameters);
* truncation: when the episode of a copy ends by ``max_cycles``, every agent's info carries
  ``TimeLimit.truncated = True`` (and ``terminal_observation``), so SB3 bootstraps the value of
  the last state instead of treating the time limit as a terminal state;
* auto-reset: the copy is reset at once and the first observation of the next episode is returned;
* one mover per copy (``SingleMover``): all copies step in one compiled call
  (:class:`cv2x_marl.env.mover_batch.MoverBatch`, the core of the ``vector_entry_point`` env too),
  bit-identical to :meth:`MobilityEnv.step_mover` and to the full step (tested) and about 15x
  faster than stepping the copies one by one; where the batch does not apply
  (:func:`~cv2x_marl.env.mover_batch.batch_problem`, e.g. ``replan_every``), through ``step_mover``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

try:
    from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn
except ImportError as _exc:  # the train extra is not installed
    from cv2x_marl.extras import missing_extra

    raise missing_extra("stable_baselines3", "the SB3 adapter (cv2x_marl.rl)", _exc) from _exc

from cv2x_marl.env.mobility_env import INFO_KEYS, MobilityEnv, check_copies
from cv2x_marl.env.mover_batch import BATCH_ATTRIBUTES, MoverBatch, batch_problem, refuse_episode_method
from cv2x_marl.env.seeds import training_pool
from cv2x_marl.rng import derive_seeds


class AgentsVecEnv(VecEnv):
    """K copies of a :class:`MobilityEnv`, each mover of each copy a sub-env.

    Args:
        env_fn: builds one env copy.
        n_copies: K.
        start_pool: when set, every episode of every copy starts from one of ``start_pool`` episode
            seeds (derived from the seed of copy 0, so from PPO's seed) instead of a fresh seed: with
            the envs' ``reset_cache`` their starts are computed once and reused (a training speed-up
            that trades the variety of starts; held-out evaluation is unaffected). With the env option
            ``start_pool=P`` instead (the envs built with it), the episodes start from the protocol's first
            P training seeds (:func:`cv2x_marl.env.seeds.training_pool`, disjoint from every held-out list),
            drawn per copy from the copy's generator (seeded from PPO's seed); the two exclude each other.
        batched: step one-mover copies in one compiled call when the env allows it (False: one
            ``step_mover`` call per copy; the same results, for checks).
    """

    def __init__(
        self,
        env_fn: Callable[[], MobilityEnv],
        n_copies: int,
        start_pool: int | None = None,
        batched: bool = True,
    ) -> None:
        if n_copies < 1:
            raise ValueError(f"n_copies must be >= 1, got {n_copies}")
        if start_pool is not None and (
            isinstance(start_pool, bool) or not isinstance(start_pool, int) or start_pool < 1
        ):
            raise ValueError(f"start_pool must be None or an integer >= 1, got {start_pool!r}")
        self.start_pool = start_pool
        self._pool: list[int] | None = None
        first = env_fn()
        check_copies(first, n_copies)
        if start_pool is not None and first.start_pool:
            raise ValueError(
                f"start_pool={start_pool} (seeds derived from PPO's seed) and the env option "
                f"start_pool={first.start_pool} (the protocol's training seeds) exclude each other: set one"
            )
        self.envs = [first, *(env_fn() for _ in range(n_copies - 1))]
        self.movers = [a for a in first.possible_agents if first.mover_mask[first.agent_index[a]]]
        self.m = len(self.movers)
        self.k = n_copies
        self._zero = np.zeros(2, dtype=np.float32)
        self._episode_rngs: list[np.random.Generator | None] = [None] * n_copies
        self._actions: np.ndarray | None = None
        self.render_mode = first.render_mode
        self._obs_shape: tuple[int, ...] = tuple(first.observation_space(self.movers[0]).shape)
        #: every copy steps through ``step_mover`` (one mover, snapshot mode, individual reward)
        self.fast = first.fast_mover is not None and first.render_mode is None
        #: all copies in one compiled call (None: copy by copy)
        self.batch = MoverBatch(self.envs) if batched and self.fast and batch_problem(first) is None else None
        super().__init__(self.k * self.m, first.observation_space(self.movers[0]), first.action_space(self.movers[0]))

    # ------------------------------------------------------------------ reset
    def _episode_seed(self, k: int) -> int:
        rng = self._episode_rngs[k]
        if rng is None:
            rng = self._episode_rngs[k] = np.random.default_rng(np.random.SeedSequence())
        if self._pool is not None:
            return self._pool[int(rng.integers(len(self._pool)))]
        return int(rng.integers(0, 2**31 - 1))

    def _reset_copy(self, k: int, seed: int | None) -> dict[str, np.ndarray]:
        if seed is not None:
            self._episode_rngs[k] = np.random.default_rng(seed)
        obs, infos = self.envs[k].reset(seed=self._episode_seed(k))
        if self.batch is not None:
            self.batch.load(k)
        for m, a in enumerate(self.movers):
            self.reset_infos[k * self.m + m] = infos[a]
        return obs

    def reset(self) -> VecEnvObs:
        if self.envs[0].start_pool and self._pool is None:  # the env option: the protocol's training seeds
            self._pool = [int(s) for s in training_pool(self.envs[0].start_pool)]
        elif self.start_pool is not None and (self._pool is None or self._seeds[0] is not None):
            base = self._seeds[0]
            if base is None:
                base = int(np.random.SeedSequence().generate_state(1)[0])
            self._pool = derive_seeds(base, self.start_pool)
        out = np.empty((self.num_envs, *self._obs_shape), dtype=np.float32)
        for k in range(self.k):
            obs = self._reset_copy(k, self._seeds[k * self.m])
            out[k * self.m : (k + 1) * self.m] = [obs[a] for a in self.movers]
        self._reset_seeds()
        self._reset_options()
        return out

    # ------------------------------------------------------------------- step
    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions, dtype=np.float32).reshape(self.num_envs, -1)

    def step_wait(self) -> VecEnvStepReturn:
        assert self._actions is not None, "step_async must come first"
        obs_out = np.empty((self.num_envs, *self._obs_shape), dtype=np.float32)
        rewards = np.empty(self.num_envs, dtype=np.float32)
        dones = np.zeros(self.num_envs, dtype=bool)
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        if self.fast:
            return self._step_fast(obs_out, rewards, dones, infos)
        for k, env in enumerate(self.envs):
            acts = {a: self._zero for a in env.agents}
            for m, a in enumerate(self.movers):
                acts[a] = self._actions[k * self.m + m]
            obs, rew, term, trunc, info = env.step(acts)
            for m, a in enumerate(self.movers):
                i = k * self.m + m
                rewards[i] = rew[a]
                infos[i] = dict(info[a])
                obs_out[i] = obs[a]
                done = term[a] or trunc[a]
                dones[i] = done
                if done:
                    infos[i]["TimeLimit.truncated"] = bool(trunc[a] and not term[a])
                    infos[i]["terminal_observation"] = obs[a]
            if dones[k * self.m]:
                new = self._reset_copy(k, None)
                obs_out[k * self.m : (k + 1) * self.m] = [new[a] for a in self.movers]
        return obs_out, rewards, dones, infos

    def _step_fast(
        self, obs_out: np.ndarray, rewards: np.ndarray, dones: np.ndarray, infos: list[dict[str, Any]]
    ) -> VecEnvStepReturn:
        assert self._actions is not None
        if self.batch is not None:
            batch_obs, batch_rewards, batch_done, table = self.batch.step(self._actions)
            obs_out[:] = batch_obs
            rewards[:] = batch_rewards
            dones[:] = batch_done
            for k, row in enumerate(table.tolist()):
                infos[k] = dict(zip(INFO_KEYS, row, strict=True))
                if batch_done[k]:
                    infos[k]["TimeLimit.truncated"] = True
                    infos[k]["terminal_observation"] = batch_obs[k].copy()
                    obs_out[k] = self._reset_copy(k, None)[self.movers[0]]
            return obs_out, rewards, dones, infos
        for k, env in enumerate(self.envs):
            ob, reward, done, info = env.step_mover(self._actions[k])
            rewards[k], obs_out[k], infos[k], dones[k] = reward, ob, dict(info), done
            if done:
                infos[k]["TimeLimit.truncated"] = True
                infos[k]["terminal_observation"] = ob
                obs_out[k] = self._reset_copy(k, None)[self.movers[0]]
        return obs_out, rewards, dones, infos

    def close(self) -> None:
        for env in self.envs:
            env.close()

    # ------------------------------------------------------------- attributes
    def _copies(self, indices: VecEnvIndices) -> list[int]:
        return [i // self.m for i in self._get_indices(indices)]

    def _synced(self, indices: VecEnvIndices) -> list[int]:
        """The copies of ``indices``, with the batch's state written back into their env objects."""
        copies = self._copies(indices)
        if self.batch is not None:
            for k in set(copies):
                if self.batch.loaded[k]:
                    self.batch.sync(k)
        return copies

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [getattr(self.envs[k], attr_name) for k in self._synced(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        if self.batch is not None and attr_name in BATCH_ATTRIBUTES:
            raise RuntimeError(
                f"set_attr({attr_name!r}) on batched copies: the batch read it once; build the VecEnv with "
                "the new value instead"
            )
        for k in set(self._copies(indices)):
            setattr(self.envs[k], attr_name, value)

    def env_method(self, method_name: str, *args: Any, indices: VecEnvIndices = None, **kwargs: Any) -> list[Any]:
        if self.batch is not None:
            refuse_episode_method(method_name, "env_method")
        return [getattr(self.envs[k], method_name)(*args, **kwargs) for k in self._synced(indices)]

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [self.envs[k].render() for k in self._synced(None)]
