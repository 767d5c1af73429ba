"""One compiled step for K one-mover env copies: the batched core of the vector envs.

:meth:`MobilityEnv.step_mover` steps one copy in about 150-200 us, almost all of it Python around
small arrays. :class:`MoverBatch` keeps the per-step state of K copies (each in snapshot mode with
one mover and the individual reward, e.g. K ``SingleMover`` envs) in stacked arrays and advances
all of them with one numba call, :func:`_mover_steps`, which for each copy calls the functions
``step_mover`` calls (:mod:`cv2x_marl.env.step`: the action clip, plan residual, settle phase, drift
and region bounds; the eq. 12 utility, PRR and Jain's index; the pair-geometry update; the reward;
the version-1 own state and entries), the mover's links (:func:`cv2x_marl.sim.kernels.mover_row_success`'s
per-link code) and the observation kernel (:func:`cv2x_marl.env.observation.observation_kernel`).
The results are bit-identical to ``step_mover`` by construction (and tested: ``tests/env/test_vector.py``).
Observation version 3 (``cv2x/SingleMover-v3``) steps through :func:`cv2x_marl.env.mover_batch_v3._mover_steps_v3`
instead: the same step plus the shadowing field's row, the mover's column of links and its measurements
(``tests/env/test_v3_fast.py``).

Resets stay with the env objects (a stage-1 run, or the reset cache): after ``envs[k].reset``,
:meth:`MoverBatch.load` copies the copy's start into the stacks; :meth:`MoverBatch.row_of` /
:meth:`MoverBatch.put_row` take those rows out and put them back (the vector env's kept starts of pooled
resets, :data:`cv2x_marl.env.vector.KEPT_STARTS`). While a batch steps a copy, that
copy's env object is not updated (its ``positions_m`` stay at the start): read the state from the
batch (:attr:`MoverBatch.positions_m`) or call :meth:`MoverBatch.sync` first.

Users get it through :class:`cv2x_marl.env.vector.SingleMoverVectorEnv` (Gymnasium's
``vector_entry_point``) and :class:`cv2x_marl.rl.sb3_vec_env.AgentsVecEnv` (SB3).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env.mover_batch_v3 import V3Stacks, mover_steps_v3, widened
from cv2x_marl.env.mover_kernels import (
    CopyStacks,
    LinkConstants,
    ObservationConstants,
    StepConstants,
    StepOutputs,
    mover_steps,
)
from cv2x_marl.env.options import option_names
from cv2x_marl.env.step import BASE_PREV, JAIN, N_SCALARS, PRR, PRR0, U0, U_BEST, U_NOW, U_PREV, U_START, U
from cv2x_marl.sim import kernels

if TYPE_CHECKING:
    from cv2x_marl.env.mobility_env import MobilityEnv

FloatArray = NDArray[np.float64]


def batch_problem(env: MobilityEnv) -> str | None:
    """Why ``env`` cannot be stepped by a :class:`MoverBatch` (None when it can)."""
    if env.fast_mover is None:
        return "it needs snapshot mode, exactly one mover and reward='individual'"
    if env.options.shadow_field and env.layout.version != 3:
        return (
            "the batched step follows the shadowing field only with observation version 3 "
            "(the copies step one by one through MobilityEnv.step_mover)"
        )
    if env.render_mode is not None:
        return "rendering needs the env objects' own state (render_mode is set)"
    if env.replan_every is not None:
        return "replan_every recomputes the sensing plan in Python"
    if env.config.channel.pathloss != "winner_b1" or env.truth_los == "geometry":
        return "the compiled link kernels need channel.pathloss winner_b1 and truth_los snapshot or always"
    return None


class MoverBatch:
    """The per-step state of K one-mover env copies, stepped by one compiled call.

    Args:
        envs: K :class:`MobilityEnv` copies of one configuration (same scenario, options and
            observation layout) that :func:`batch_problem` accepts. Reset a copy through its own
            ``reset`` (seeding, reset cache), then :meth:`load` it.
    """

    def __init__(self, envs: Sequence[MobilityEnv]) -> None:
        if not envs:
            raise ValueError("MoverBatch needs at least one env copy")
        first = envs[0]
        for k, env in enumerate(envs):
            problem = batch_problem(env)
            if problem is not None:
                raise ValueError(f"env copy {k} cannot be stepped in a batch: {problem}")
            if batch_signature(env) != batch_signature(first):
                raise ValueError(f"env copy {k} differs from copy 0 in its scenario or options")
        self.envs = list(envs)
        self.k = len(envs)
        n = first.n
        self.n = n
        self.layout = first.layout
        self.active = np.zeros(self.k, dtype=bool)
        self.mover = np.zeros(self.k, dtype=np.int64)
        self.t = np.zeros(self.k, dtype=np.int64)
        self.positions_m = np.zeros((self.k, n, 2))
        self.start_m = np.zeros((self.k, n, 2))
        self.plan_m = np.zeros((self.k, 2))
        self.best_m = np.zeros((self.k, 2))
        self.disp_m = np.zeros((self.k, 2, n, n))
        self.dist2_m2 = np.zeros((self.k, n, n))
        self.co_table = np.full((self.k, n, 1), -1, dtype=np.int64)
        self.target = np.zeros((self.k, n, n), dtype=bool)
        self.p = np.zeros((self.k, n, n))
        self.los_row = np.zeros((self.k, n), dtype=bool)
        self.gain_row_db = np.zeros((self.k, n))
        self.level_db = np.zeros((self.k, n))
        self.scalars = np.zeros((self.k, N_SCALARS))
        #: copies that hold an episode (loaded since construction)
        self.loaded = np.zeros(self.k, dtype=bool)
        #: the kernel's constants (links, step options, observation), from the first loaded copy
        self._const: tuple[LinkConstants, StepConstants, ObservationConstants] | None = None
        #: observation version 3: the field and the measurements of every copy (:mod:`.mover_batch_v3`)
        self.v3 = V3Stacks(self.envs) if first.layout.version == 3 else None

    def _constants(self, env: MobilityEnv) -> tuple[LinkConstants, StepConstants, ObservationConstants]:
        """The kernel arguments every copy shares (links, options, layout, model), from a reset env."""
        (period, _los, _gain, wb1, range2, _idx, _val, _noise, model, per_sinr, per, thr, sens, _t) = (
            env.links.kernel_args
        )
        links = LinkConstants(period, wb1, float(range2), int(model), per_sinr, per, float(thr), float(sens))
        steps = StepConstants(
            env.max_step_m, int(env.max_cycles), int(env.settle_steps),
            np.inf if env.max_drift_m is None else float(env.max_drift_m), bool(env.roi),
            np.asarray(env.box_m, dtype=np.float64), env.action_mode == "plan_residual", bool(env.normalise_reward),
            env.reward_form == "improvement", float(env.p_min), int(env.layout.version),
        )  # fmt: skip
        layout, fm = env.layout, env.model
        observe = ObservationConstants(
            layout.n_neighbours, layout.scale_m, layout.region_m, layout.interferer_range_m, layout.obs_clip,
            layout.size, layout.model_extra, layout.own_v1_offset,
            np.zeros(1) if fm is None else np.ascontiguousarray(fm.alpha, dtype=np.float64),
            np.zeros(1) if fm is None else np.ascontiguousarray(fm.beta, dtype=np.float64),
            np.zeros(1) if fm is None else np.ascontiguousarray(fm.gamma, dtype=np.float64),
            fm is not None and fm.kind == "logistic", 1e-3 if fm is None else float(fm.p_min),
        )  # fmt: skip
        return links, steps, observe

    def load(self, k: int) -> None:
        """Copy env copy ``k``'s state, just after its ``reset``, into the stacks."""
        env = self.envs[k]
        i = env.fast_mover
        assert i is not None
        if env.t != 0 or env.mover_links is not None:
            raise RuntimeError(f"env copy {k} must be loaded right after its reset")
        if self._const is None:
            self._const = self._constants(env)
        self.mover[k] = i
        self.t[k] = env.t
        self.positions_m[k] = env.positions_m
        self.start_m[k] = env.start_m
        assert env.geometry is not None and env.co_table is not None
        self.disp_m[k] = env.geometry.disp_m
        self.dist2_m2[k] = env.geometry.dist2_m2
        table = env.co_table
        widened(self, "co_table", table.shape[1], -1)
        self.co_table[k] = -1
        self.co_table[k, :, : table.shape[1]] = table
        self.target[k] = env.target
        self.p[k] = env.link_p
        row = env.links.mover_row(i, env.positions_m)
        args = row.args
        self.los_row[k] = args.los_row
        self.gain_row_db[k] = args.gain_row_db
        self.level_db[k] = kernels.levels_db(args.interference_mw, args.noise_mw)
        s = self.scalars[k]
        s[U], s[U0], s[PRR], s[PRR0], s[JAIN] = env.utility[i], env.u0[i], env.prr[i], env.prr0[i], env.jain[i]
        s[BASE_PREV] = env.rewarder.previous[i]
        own = env.own
        if own is not None:
            s[U_NOW], s[U_PREV], s[U_START], s[U_BEST] = own.u_now[i], own.u_prev[i], own.u_start[i], own.u_best[i]
            self.plan_m[k] = env.plan_m[i]
            self.best_m[k] = own.best_m[i]
        if self.v3 is not None:
            self.v3.load(k, env, i)
        self.loaded[k] = True

    #: the per-copy stacks :meth:`load` fills (every entry of a copy's row), and those whose last axis grows
    ROW_ARRAYS = CopyStacks._fields
    WIDE_ARRAYS: dict[str, float] = {"co_table": -1}  # noqa: RUF012 - a constant table

    def row_of(self, k: int) -> dict[str, Any]:
        """A copy of copy ``k``'s rows of every stack (:meth:`put_row` puts them back): what :meth:`load` wrote,
        plus what the steps since then changed."""
        row = {name: np.array(getattr(self, name)[k]) for name in self.ROW_ARRAYS}
        if self.v3 is not None:
            row.update({f"v3.{name}": np.array(getattr(self.v3, name)[k]) for name in self.v3.ROW_ARRAYS})
        return row

    def put_row(self, k: int, row: dict[str, Any]) -> None:
        """Write rows taken by :meth:`row_of` (of this batch) into copy ``k``: the state :meth:`load` gave it
        then, without the env object (a kept start: the same arrays, bit for bit)."""
        if self._const is None:
            raise RuntimeError("put_row needs a batch that has loaded a copy")
        for key, value in row.items():
            owner: Any = self.v3 if key.startswith("v3.") else self
            name = key[3:] if key.startswith("v3.") else key
            fill = owner.WIDE_ARRAYS.get(name)
            if fill is not None:
                stack = widened(owner, name, value.shape[-1], fill)
                stack[k] = fill
                stack[k, ..., : value.shape[-1]] = value
            else:
                getattr(owner, name)[k] = value
        self.loaded[k] = True

    def step(
        self, actions: NDArray[np.floating], active: NDArray[np.bool_] | None = None
    ) -> tuple[NDArray[np.float32], FloatArray, NDArray[np.bool_], FloatArray]:
        """Step the copies (all, or those where ``active``) with ``actions`` [K, 2].

        Returns:
            observations [K, size] float32, rewards [K], truncations [K] (the episode ended) and the
            info table [K, 8] (columns :data:`~cv2x_marl.env.mobility_env.INFO_KEYS`); rows of
            inactive copies are left as they were (zeros in new arrays).
        """
        act = np.ascontiguousarray(actions, dtype=np.float64)
        if act.shape != (self.k, 2):
            raise ValueError(f"actions must have shape ({self.k}, 2), got {act.shape}")
        mask = np.ones(self.k, dtype=bool) if active is None else np.asarray(active, dtype=bool)
        bad = mask & ~np.isfinite(act).all(axis=1)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ValueError(f"action of copy {k} is not finite: {act[k].tolist()}")
        if not self.loaded[mask].all():
            k = int(np.flatnonzero(mask & ~self.loaded)[0])
            raise RuntimeError(f"env copy {k} has no episode: reset and load it first")
        assert self._const is not None  # set by the first load
        done_before = mask & (self.t >= self._const[1].max_cycles)
        if done_before.any():
            raise RuntimeError(f"step() called on a finished episode of copy {int(np.flatnonzero(done_before)[0])}")
        obs = np.zeros((self.k, self.layout.size), dtype=np.float32)
        rewards = np.zeros(self.k)
        dones = np.zeros(self.k, dtype=bool)
        info = np.zeros((self.k, 8))
        stacks = CopyStacks(*(getattr(self, name) for name in CopyStacks._fields))
        out = StepOutputs(obs, rewards, dones, info)
        if self.v3 is not None:
            mover_steps_v3(mask, act, stacks, *self._const, self.v3.kernel_args(), out)
        else:
            mover_steps(mask, act, stacks, *self._const, out)
        return obs, rewards, dones, info

    def sync(self, k: int) -> None:
        """Write copy ``k``'s batched state back into its env object (positions, links, utilities), so
        that the env's own methods (``state()``, ``render()``) see where the batch has moved it."""
        env = self.envs[k]
        i = int(self.mover[k])
        env.positions_m = self.positions_m[k].copy()
        env.t = int(self.t[k])
        env.link_p = self.p[k].copy()
        env.geometry = type(env.geometry)(self.disp_m[k].copy(), self.dist2_m2[k].copy())  # type: ignore[misc]
        s = self.scalars[k]
        env.utility[i], env.prr[i], env.jain[i] = s[U], s[PRR], s[JAIN]
        env.rewarder.previous[i] = s[BASE_PREV]
        own = env.own
        if own is not None:
            own.u_now[i], own.u_prev[i], own.u_best[i] = s[U_NOW], s[U_PREV], s[U_BEST]
            own.best_m[i] = self.best_m[k]
        if self.v3 is not None:
            self.v3.sync(k, env)
        if env.t >= env.max_cycles:
            env.finish()


#: env methods that change a copy's episode: through a batch they would leave its stacks stale
EPISODE_METHODS = ("reset", "step", "step_mover")
#: env options every copy of a batch must share: all of them (the copies of a batch are one env; the batch reads the
#: options once, its kernel constants, and a kept start's infos depend on the run options too)
SHARED_OPTIONS = option_names()
#: env attributes not to be set on a batched copy: the shared options, what is derived from them and what they load
BATCH_ATTRIBUTES = (*SHARED_OPTIONS, "options", "layout", "mover_mask", "box_m", "model", "links")


def refuse_episode_method(name: str, where: str) -> None:
    """Raise if ``name`` would change a batched copy's episode behind the batch's back."""
    if name in EPISODE_METHODS:
        raise RuntimeError(
            f"{where}({name!r}) on a batched copy would desynchronise it from the batch; reset copies through "
            "the vector env (reset(seed=..., options={'reset_mask': mask}) or VecEnv.reset) and step them together"
        )


def batch_signature(env: MobilityEnv) -> tuple[str, ...]:
    """What must agree between the copies of a batch: the scenario and :data:`SHARED_OPTIONS` (by value)."""
    return (repr(env.config), *(repr(getattr(env.options, name)) for name in SHARED_OPTIONS))
