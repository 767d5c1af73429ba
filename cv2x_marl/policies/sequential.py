"""Scripted movers that use the coordination channel of ``decision_order="subframe"`` (``cv2x/Cooperative-v1``).

Each period the vehicles decide in the order of their transmission subframes (:mod:`cv2x_marl.env.turns`); at
its turn a vehicle re-plans its target with every vehicle of an earlier subframe at the position it announced
for this period (its decided move) and the others where they are, then steps straight towards the target
(``max_step_m`` per axis). Between re-plans (``replan_every``) it keeps its target.

    sequential-best-response   every period, the vehicle's best reachable position for its own eq. 12 utility
                               under the true links (privileged, as ``best-response``;
                               :func:`~cv2x_marl.env.planning.best_reachable` on the sensing planner's 20 m grid,
                               4 points refined twice: re-planned every period, a coarser search than
                               ``best-response``'s one-off 10 m grid with 16 points)
    sequential-sensing         every sensing window (10 periods, as ``sensing``), its best reachable position under
                               its measured estimate (``sensing`` on observation version 3:
                               :func:`~cv2x_marl.env.planning.measured_row`, 20 m grid, 4 points refined), the
                               announced moves in place of the old positions
    sequential-team            every period, its best reachable position for the team objective J (privileged, the
                               ceiling's knowledge: :func:`~cv2x_marl.env.team_search.team_move`, one single move of
                               the team search); without the announcements it is the all-at-once team-aware
                               re-planning of ``benchmarks/cooperative_gap.py``

Both act through the parallel API (they read the env and make the turns themselves: :meth:`SequentialPolicy.act`)
or one agent at a time through the AEC API (:meth:`SequentialPolicy.turn_action` with the positions the agent has
heard); the two give the same actions (tested).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env.planning import (
    MEASURED_REPLAN_EVERY,
    PLAN_GRID_M,
    best_reachable,
    check_reach_grid,
    measured_row,
    reachable_set,
)
from cv2x_marl.env.team_search import team_move
from cv2x_marl.env.turns import announced_positions, decide_in_turns, subframes
from cv2x_marl.policies.base import Actions, Observations

if TYPE_CHECKING:
    from cv2x_marl.env.mobility_env import MobilityEnv

FloatArray = NDArray[np.float64]


class SequentialPolicy:
    """The turns of a period and the straight steps towards the targets; :meth:`plan` is the target's search.

    Args:
        env: a snapshot-mode env with ``decision_order="subframe"`` (read, never stepped).
        replan_every: steps between re-plans (1: every period; None: the policy's default, :attr:`replan_default`).
        grid_m, refine: the search's grid pitch (m) and points refined (None: the class's, the sensing planner's).
        hear: False: :meth:`act` ignores the announcements (every vehicle plans with the others where they are:
            the same script with simultaneous decisions, the channel's ablation).
    """

    name = "sequential"
    #: the search grid's pitch (m) and the points refined (the sensing planner's)
    grid_m = PLAN_GRID_M
    refine = 4
    #: the default steps between re-plans
    replan_default = 1

    def __init__(
        self,
        env: Any,
        replan_every: int | None = None,
        grid_m: float | None = None,
        refine: int | None = None,
        hear: bool = True,
    ) -> None:
        replan_every = self.replan_default if replan_every is None else replan_every
        self.hear = hear
        self.grid_m = self.grid_m if grid_m is None else float(grid_m)
        self.refine = self.refine if refine is None else int(refine)
        if getattr(env, "mode", None) != "snapshot" or getattr(env, "decision_order", None) != "subframe":
            raise ValueError(
                f"policy {self.name!r} needs an env in snapshot mode with decision_order='subframe' (the "
                "coordination channel: cv2x/Cooperative-v1); allowed elsewhere: best-response, sensing"
            )
        if not (isinstance(replan_every, int) and replan_every >= 1):
            raise ValueError(f"invalid replan_every={replan_every!r}; allowed: an integer >= 1")
        check_reach_grid(env, self.grid_m, f"the {self.name} policy")
        self.env = env
        self.replan_every = replan_every
        self.targets_m: FloatArray | None = None
        self._episode: int | None = None

    def reset(self, seed: int | None = None) -> None:
        self.targets_m = None

    def plan(self, i: int, heard_m: FloatArray) -> FloatArray:
        """[2] vehicle ``i``'s target with the others at ``heard_m`` [N, 2] (m)."""
        raise NotImplementedError

    def _fresh(self) -> None:
        env = self.env
        if self.targets_m is None or (env.t == 0 and self._episode != id(env.links)):
            self.targets_m = np.array(env.positions_m, dtype=np.float64)
            self._episode = id(env.links)

    def turn_action(self, i: int, heard_m: FloatArray) -> NDArray[np.float32]:
        """[2] vehicle ``i``'s action at its turn, having heard the positions ``heard_m`` [N, 2] (m; the AEC's
        :meth:`~cv2x_marl.env.turns.SubframeAECEnv.heard_positions`)."""
        env = self.env
        self._fresh()
        assert self.targets_m is not None
        if env.mover_mask[i] and env.t % self.replan_every == 0:
            self.targets_m[i] = self.plan(i, np.asarray(heard_m, dtype=np.float64))
        move = (self.targets_m[i] - env.positions_m[i]) / env.max_step_m
        return np.clip(move, -1.0, 1.0).astype(np.float32)

    def act(self, observations: Observations) -> Actions:
        """The period's actions, the vehicles taking their turns in subframe order (each subframe's vehicles
        hear the moves of the earlier subframes, not each other's)."""
        env = self.env
        sub = subframes(env)
        act = np.zeros((env.n, 2))
        decided = np.zeros(env.n, dtype=bool)
        for s in np.unique(sub):
            group = np.flatnonzero(sub == s)
            heard = announced_positions(env, act, decided & self.hear)
            for i in group:
                act[i] = self.turn_action(int(i), heard)
            decided[group] = True
        return {a: act[env.agent_index[a]].astype(np.float32) for a in observations}


class SequentialBestResponsePolicy(SequentialPolicy):
    """``sequential-best-response``: the best reachable position for the own eq. 12 utility under the true links,
    the earlier subframes' vehicles at their announced positions (privileged)."""

    name = "sequential-best-response"

    def plan(self, i: int, heard_m: FloatArray) -> FloatArray:
        env = self.env
        row = env.links.mover_row(i, heard_m)
        return best_reachable(row, reachable_set(env, i), env.p_min, self.grid_m, self.refine)[0]


class SequentialSensingPolicy(SequentialPolicy):
    """``sequential-sensing``: the best reachable position under the vehicle's measured estimate
    (:func:`~cv2x_marl.env.planning.measured_row`: its own links' shadowing from its RSRP reports), the earlier
    subframes' vehicles at their announced positions (not privileged: positions from the CAMs, the rest measured)."""

    name = "sequential-sensing"
    replan_default = MEASURED_REPLAN_EVERY

    def __init__(
        self,
        env: Any,
        replan_every: int | None = None,
        grid_m: float | None = None,
        refine: int | None = None,
        hear: bool = True,
    ) -> None:
        if getattr(getattr(env, "layout", None), "version", None) != 3:
            raise ValueError(f"policy {self.name!r} needs observation version 3 (the RSRP measurements)")
        super().__init__(env, replan_every, grid_m, refine, hear)

    def plan(self, i: int, heard_m: FloatArray) -> FloatArray:
        env = self.env
        row = measured_row(env, i, heard_m)
        return best_reachable(row, reachable_set(env, i), env.p_min, self.grid_m, self.refine)[0]


class SequentialTeamPolicy(SequentialPolicy):
    """``sequential-team``: every period, at its turn, the best reachable position for the team objective J with the
    earlier subframes' vehicles at their announced moves (privileged: :func:`~cv2x_marl.env.team_search.team_move`,
    the team search's single move on the coarse-to-fine grids)."""

    name = "sequential-team"

    def plan(self, i: int, heard_m: FloatArray) -> FloatArray:
        return team_move(self.env, i, heard_m, normalise=bool(self.env.normalise_reward))


class InTurns:
    """A learned policy acting at its turns on a ``decision_order="subframe"`` env (``cv2x/Cooperative-v1``).

    Each period the vehicles of one subframe decide together, on their observations at their turn (the moves
    announced in the earlier subframes, :func:`~cv2x_marl.env.turns.decide_in_turns`); the wrapped policy acts on
    those observations as on any others (one agent's row at a time for a learned policy). :func:`make_policy` wraps
    every ``ppo:PATH`` model loaded for such an env: without the wrapper the parallel API's actions are all taken on
    the period's first observation, and the channel is not used.

    Args:
        policy: the wrapped policy (its ``act`` takes a dict of observations).
        env: the turn-order env it acts in (read, never stepped).
    """

    def __init__(self, policy: Any, env: MobilityEnv) -> None:
        if env.options.decision_order != "subframe":
            raise ValueError(
                f"InTurns needs an env with decision_order='subframe' (cv2x/Cooperative-v1), got "
                f"{env.options.decision_order!r}"
            )
        self.policy = policy
        self.env = env
        self.name = getattr(policy, "name", "learned")

    @classmethod
    def deferred(cls, policy: Any) -> _DeferredTurns:
        """``policy`` in turns in whichever env it is evaluated in: :func:`~cv2x_marl.experiments.evaluate.evaluate`
        calls the returned object's ``bind(env)`` with its env (a training run's evaluations)."""
        return _DeferredTurns(policy)

    def reset(self, seed: int | None = None) -> None:
        self.policy.reset(seed)

    def act(self, observations: Observations) -> Actions:
        env = self.env
        names = env.possible_agents

        def decide(rows: NDArray[np.int64], obs: NDArray[np.float32]) -> NDArray[np.float64]:
            live = [(k, names[r]) for k, r in enumerate(rows) if names[r] in observations]
            out = np.zeros((rows.size, 2))
            if live:
                acts = self.policy.act({a: obs[k] for k, a in live})
                for k, a in live:
                    out[k] = np.asarray(acts[a], dtype=np.float64)
            return out

        actions, _ = decide_in_turns(env, decide)
        return {a: actions[env.agent_index[a]].astype(np.float32) for a in observations}


class _DeferredTurns:
    """A policy to wrap in :class:`InTurns` once its env is known (:meth:`InTurns.deferred`)."""

    def __init__(self, policy: Any) -> None:
        self.policy = policy
        self.name = getattr(policy, "name", "learned")

    def bind(self, env: MobilityEnv) -> InTurns:
        """The policy acting at its turns in ``env``."""
        return InTurns(self.policy, env)

    def reset(self, seed: int | None = None) -> None:  # pragma: no cover - evaluate binds it first
        raise RuntimeError("a deferred InTurns policy acts once bound to its env (InTurns.deferred)")

    def act(self, observations: Observations) -> Actions:  # pragma: no cover - evaluate binds it first
        raise RuntimeError("a deferred InTurns policy acts once bound to its env (InTurns.deferred)")
