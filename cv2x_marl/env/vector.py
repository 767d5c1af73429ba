"""Gymnasium's ``vector_entry_point`` for ``cv2x/SingleMover-v*``: K copies stepped by one compiled call.

    envs = gymnasium.make_vec("cv2x/SingleMover-v2", num_envs=16, vectorization_mode="vector_entry_point")

returns a :class:`SingleMoverVectorEnv` of the id's copies (registered with ``kwargs={"env_id": ...}``). It
follows Gymnasium's vector
API like ``SyncVectorEnv`` over the same single-agent envs, and gives the same results bit for bit
(``tests/env/test_vector.py``):

* seeding: ``reset(seed=s)`` resets copy k with seed ``s + k`` (a list gives one seed per copy,
  None draws fresh ones); a copy's later episodes draw their seeds from its own generator, so the
  same seeded first reset gives the same sequence of episodes in every copy, across autoresets;
* autoreset: ``autoreset_mode`` ``NextStep`` (Gymnasium's default: the step after an episode ended
  resets that copy, ignores its action and returns reward 0), ``SameStep`` (the copy is reset in
  the step that ended it; ``infos["final_obs"]`` and ``infos["final_info"]`` hold what the episode
  ended with) or ``Disabled`` (reset copies yourself with ``options={"reset_mask": mask}``);
* infos: every key of the single env's info (:data:`~cv2x_marl.env.mobility_env.INFO_KEYS`) as an
  array over the copies, with its ``_key`` mask.

With ``start_pool`` the batched vector envs keep (:data:`KEPT_STARTS`, process-wide), per pooled episode
seed, the batch's rows right after that start's reset: a later autoreset (or ``reset()`` without a seed)
drawing the same seed copies them back into the batch (a few array copies) and the copy's env object runs
its own reset only when it is read (``call``, ``get_attr``, ``set_attr``, ``render``); the results are the
same bit for bit (``tests/env/test_v3_fast.py``). Read the copies through those methods, not through
:attr:`envs` directly.

Steps go through :class:`~cv2x_marl.env.mover_batch.MoverBatch` (one numba call for all copies) when the
env options allow it (:func:`~cv2x_marl.env.mover_batch.batch_problem`: no rendering, no
``replan_every``, WINNER+ B1 links); otherwise through each copy's own ``step`` (the same results,
a loop over copies), and :attr:`SingleMoverVectorEnv.batched` says which.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from numpy.typing import NDArray

from cv2x_marl.checks import is_int
from cv2x_marl.env import starts
from cv2x_marl.env.mobility_env import INFO_KEYS, check_copies
from cv2x_marl.env.mover_batch import MoverBatch, batch_problem, batch_signature, refuse_episode_method
from cv2x_marl.env.single import AGENT, SingleMoverEnv

_MODES = ", ".join(m.value for m in AutoresetMode)

#: pooled resets of the batched vector envs (``start_pool``), process-wide like
#: :data:`~cv2x_marl.env.starts.START_CACHE`: (the settings of :func:`~cv2x_marl.env.starts.start_key`, episode
#: seed, horizon) -> the batch's rows (``MoverBatch.row_of``), the observation and the info right after that
#: start's reset; oldest first, bounded like the start cache
KEPT_STARTS: OrderedDict[tuple[Any, ...], tuple[dict[str, Any], NDArray[np.float32], dict[str, Any]]] = OrderedDict()


class SingleMoverVectorEnv(VectorEnv):
    """K copies of a ``cv2x/SingleMover-v*`` id as one Gymnasium ``VectorEnv`` (module docstring).

    Args:
        num_envs: K, the number of copies.
        autoreset_mode: ``NextStep`` (default), ``SameStep`` or ``Disabled`` (or the
            :class:`gymnasium.vector.AutoresetMode`).
        render_mode: passed to every copy (rendering turns the batched step off).
        env_id: the copies' id (:class:`~cv2x_marl.env.single.SingleMoverEnv`).
        **kwargs: env arguments of :class:`~cv2x_marl.env.mobility_env.MobilityEnv`, the same for
            every copy (``max_cycles``, ``overrides``, ...).
    """

    metadata: dict[str, Any] = {  # noqa: RUF012 - Gymnasium declares it so (per instance: the autoreset mode)
        "render_modes": ["rgb_array", "human"],
        "render_fps": 10,
        "autoreset_mode": AutoresetMode.NEXT_STEP,
    }

    def __init__(
        self,
        num_envs: int = 1,
        *,
        autoreset_mode: str | AutoresetMode = AutoresetMode.NEXT_STEP,
        render_mode: str | None = None,
        env_id: str = "cv2x/SingleMover-v0",
        **kwargs: Any,
    ) -> None:
        if not is_int(num_envs) or num_envs < 1:
            raise ValueError(f"invalid num_envs={num_envs!r}; allowed: an integer >= 1")
        try:
            mode = autoreset_mode if isinstance(autoreset_mode, AutoresetMode) else AutoresetMode(autoreset_mode)
        except ValueError:
            raise ValueError(f"invalid autoreset_mode={autoreset_mode!r}; allowed: {_MODES}") from None
        first = SingleMoverEnv(env_id, render_mode=render_mode, **kwargs)
        check_copies(first.par, int(num_envs))
        self.envs = [
            first,
            *(SingleMoverEnv(env_id, render_mode=render_mode, **kwargs) for _ in range(int(num_envs) - 1)),
        ]
        #: the registered id of the copies
        self.env_id = env_id
        self.num_envs = int(num_envs)
        self.autoreset_mode = mode
        self.metadata = {**type(self).metadata, "autoreset_mode": mode}
        self.render_mode = render_mode
        self.single_observation_space = self.envs[0].observation_space
        self.single_action_space = self.envs[0].action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        #: why the copies are stepped one by one (None: they are stepped in one compiled call)
        self.not_batched_because = batch_problem(self.envs[0].par)
        self.batch = MoverBatch([e.par for e in self.envs]) if self.not_batched_because is None else None
        self._obs = np.zeros((self.num_envs, self.envs[0].par.layout.size), dtype=np.float32)
        self._ended = np.zeros(self.num_envs, dtype=bool)
        self._started = np.zeros(self.num_envs, dtype=bool)
        #: what a kept start depends on besides its seed and horizon (:data:`KEPT_STARTS`)
        self._settings = _settings_of(self.envs[0].par)
        #: per copy: the (episode seed, horizon) whose reset its env object has not run yet (None: it has)
        self._pending: list[tuple[int, int] | None] = [None] * self.num_envs
        self._last_info: dict[str, Any] = {}  # the info of the last reset run by _run_reset

    @property
    def batched(self) -> bool:
        """True when steps go through one compiled call for all copies."""
        return self.batch is not None

    # ------------------------------------------------------------------ reset
    def _reset_copy(self, k: int, seed: int | None, options: dict[str, Any] | None) -> dict[str, Any]:
        if seed is None and options is None and self.batch is not None and self.envs[k].par.start_pool:
            return self._pool_reset(k)
        obs, info = self.envs[k].reset(seed=seed, options=options)
        self._pending[k] = None
        if self.batch is not None:
            self.batch.load(k)
        self._obs[k] = obs
        self._ended[k] = False
        self._started[k] = True
        return info

    def _pool_reset(self, k: int) -> dict[str, Any]:
        """``envs[k].reset()`` from the start pool, through the batch: the episode seed drawn as
        :meth:`SingleMoverEnv.reset` draws it; the first time a (seed, horizon) comes, the copy's env is reset
        with it and the batch's rows, observation and info are kept; later, they are copied back into the
        batch and the env object's own reset waits until someone reads the copy (:meth:`_synced`). Bit for bit
        what the env's reset and :meth:`MoverBatch.load` give (tested)."""
        assert self.batch is not None
        env = self.envs[k]
        par = env.par
        horizon = env.horizon_in_force()
        if par._np_random is None:  # as SingleMoverEnv.reset: seeded from the env's generator
            par._np_random = np.random.default_rng(int(env.np_random.integers(0, 2**63 - 1)))
        episode_seed = starts.pool_seed(par, par._np_random)
        key = (episode_seed, horizon)
        kept_key = (self._settings, episode_seed, horizon)
        kept = KEPT_STARTS.get(kept_key) if self.batch.loaded.any() else None
        if kept is None:
            self._run_reset(k, key)
            self.batch.load(k)
            kept = (self.batch.row_of(k), self._obs[k].copy(), self._last_info)
            KEPT_STARTS[kept_key] = kept
            while len(KEPT_STARTS) > starts.cache_size(par):
                KEPT_STARTS.popitem(last=False)
        else:
            KEPT_STARTS.move_to_end(kept_key)
            self.batch.put_row(k, kept[0])
            self._pending[k] = key
            self._obs[k] = kept[1]
        self._ended[k] = False
        self._started[k] = True
        return dict(kept[2])

    def _run_reset(self, k: int, key: tuple[int, int]) -> None:
        """Reset copy ``k``'s env object to episode seed ``key[0]`` with horizon ``key[1]`` as a ``reset()``
        that drew that seed from the pool does (the pool's generator left as it is)."""
        par = self.envs[k].par
        generator = par._np_random
        par.horizon = key[1]
        obs, infos = par.reset(seed=key[0])
        par._np_random = generator
        self._obs[k] = obs[AGENT]
        self._last_info = infos[AGENT]
        self._pending[k] = None

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float32], dict[str, Any]]:
        """Reset every copy (or those of ``options["reset_mask"]``); seeds as ``SyncVectorEnv``."""
        if seed is None:
            seeds: list[int | None] = [None] * self.num_envs
        elif is_int(seed):
            seeds = [int(seed) + k for k in range(self.num_envs)]  # type: ignore[arg-type]
        elif isinstance(seed, list | tuple) and len(seed) == self.num_envs:
            seeds = list(seed)
        else:
            raise ValueError(
                f"invalid reset seed={seed!r}; allowed: None, an integer, or a list of {self.num_envs} seeds"
            )
        options = dict(options) if options else None
        mask = np.ones(self.num_envs, dtype=bool)
        if options is not None and "reset_mask" in options:
            mask = np.asarray(options.pop("reset_mask"))
            if mask.shape != (self.num_envs,) or mask.dtype != np.bool_ or not mask.any():
                raise ValueError(f"options['reset_mask'] must be a bool array of shape ({self.num_envs},) with a True")
            options = options or None
        infos: dict[str, Any] = {}
        for k in np.flatnonzero(mask):
            infos = self._add_info(infos, self._reset_copy(int(k), seeds[k], options), int(k))
        return self._obs.copy(), infos

    # ------------------------------------------------------------------- step
    def step(
        self, actions: Any
    ) -> tuple[NDArray[np.float32], NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_], dict[str, Any]]:
        """Step every copy with ``actions`` [K, 2] (autoreset as :attr:`autoreset_mode`)."""
        try:
            act = np.asarray(actions, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"actions must be numeric with shape ({self.num_envs}, 2), got {actions!r}") from None
        if act.shape != (self.num_envs, 2):
            raise ValueError(f"actions must have shape ({self.num_envs}, 2), got {act.shape}")
        if not self._started.all():
            raise RuntimeError("step() called before reset(): call reset() first")
        k_count = self.num_envs
        reset_now = np.zeros(k_count, dtype=bool)
        if self._ended.any():
            if self.autoreset_mode != AutoresetMode.NEXT_STEP:
                k = int(np.flatnonzero(self._ended)[0])
                raise RuntimeError(
                    f"copy {k} finished its episode: reset it with options={{'reset_mask': mask}} "
                    "(autoreset_mode Disabled)"
                )
            reset_now = self._ended.copy()
        stepping = ~reset_now
        rewards = np.zeros(k_count)
        truncations = np.zeros(k_count, dtype=bool)
        table = np.zeros((k_count, len(INFO_KEYS)))
        if self.batch is not None and not reset_now.any():  # the usual step: every copy moves
            obs, rewards, truncations, table = self.batch.step(act)
            self._obs[:] = obs
        elif self.batch is not None:
            obs, rew, done, info = self.batch.step(act, stepping)
            self._obs[stepping] = obs[stepping]
            rewards[stepping] = rew[stepping]
            truncations[stepping] = done[stepping]
            table[stepping] = info[stepping]
        else:
            for c in np.flatnonzero(stepping):
                ob, r, _term, trunc, inf = self.envs[c].step(act[c])
                self._obs[c], rewards[c], truncations[c] = ob, r, trunc
                table[c] = _info_row(inf)
        extra: dict[str, Any] = {}
        for c in np.flatnonzero(reset_now):  # NextStep: the copies that ended last step start again
            table[c] = _info_row(self._reset_copy(int(c), None, None))
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            for c in np.flatnonzero(truncations):
                final_info = dict(zip(INFO_KEYS, table[c].tolist(), strict=True))
                extra = self._add_info(extra, {"final_obs": self._obs[c].copy(), "final_info": final_info}, int(c))
                table[c] = _info_row(self._reset_copy(int(c), None, None))
        else:
            self._ended = truncations.copy()
        infos: dict[str, Any] = {}
        columns = np.ascontiguousarray(table.T)  # a fresh array: each row below is the caller's own
        masks = np.ones((len(INFO_KEYS), k_count), dtype=bool)
        for col, key in enumerate(INFO_KEYS):
            infos[key] = columns[col]
            infos[f"_{key}"] = masks[col]
        infos.update(extra)
        return self._obs.copy(), rewards, np.zeros(k_count, dtype=bool), truncations, infos

    # ------------------------------------------------------------ the copies
    def _synced(self) -> list[SingleMoverEnv]:
        """The copies with the batch's state written back into them (what their methods then see)."""
        if self.batch is not None:
            for k in np.flatnonzero(self._started):
                key = self._pending[k]
                if key is not None:  # a kept start: the env object's own reset, then the batch's state
                    obs = self._obs[k].copy()
                    self._run_reset(int(k), key)
                    self._obs[k] = obs
                self.batch.sync(int(k))
        return self.envs

    def render(self) -> tuple[Any, ...] | None:
        """Every copy's frame (None each unless ``render_mode`` was given)."""
        return tuple(env.render() for env in self._synced())

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """Call method ``name`` (or read attribute ``name``) of every copy. The copies see the batch's
        current state; ``reset`` / ``step`` of a copy are refused while batched (use the vector env's)."""
        if self.batch is not None:
            refuse_episode_method(name, "call")
        out = []
        for env in self._synced():
            attr = getattr(env, name)
            out.append(attr(*args, **kwargs) if callable(attr) else attr)
        return tuple(out)

    def get_attr(self, name: str) -> tuple[Any, ...]:
        """Attribute ``name`` of every copy."""
        return tuple(getattr(env, name) for env in self._synced())

    def set_attr(self, name: str, values: Any) -> None:
        """Set attribute ``name`` of every copy (one value for all, or a list of K)."""
        if not isinstance(values, list | tuple):
            values = [values] * self.num_envs
        if len(values) != self.num_envs:
            raise ValueError(f"set_attr needs one value or {self.num_envs} values, got {len(values)}")
        self._synced()  # the copies' own state first
        for env, value in zip(self.envs, values, strict=True):
            setattr(env, name, value)
        self._settings = _settings_of(self.envs[0].par)  # kept starts follow the new settings

    def close_extras(self, **kwargs: Any) -> None:
        for env in getattr(self, "envs", []):  # also when __init__ failed
            env.close()


def _settings_of(par: Any) -> tuple[Any, ...]:
    """Everything a copy's state after a reset depends on besides the episode seed and the horizon: the start
    (:func:`~cv2x_marl.env.starts.start_key`) and every option the batch shares (``mover_batch.batch_signature``:
    rewards, observation layout, measurements)."""
    return (*starts.start_key(par, 0)[:-1], *batch_signature(par))


def _info_row(info: dict[str, Any]) -> list[float]:
    """The values of a single env's info in :data:`INFO_KEYS` order."""
    return [info[key] for key in INFO_KEYS]
