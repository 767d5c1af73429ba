"""The coordination channel of ``decision_order="subframe"`` (``cv2x/Cooperative-v1``): who decides when in a
period, and what each agent sees of the moves decided before it.

In C-V2X Mode 4 every vehicle transmits its CAM once per 100 ms period, in the subframe of its SPS resource
(subframe ``= resource // n_subchannels``, 0 .. RRI - 1). A vehicle that decides its move when its own subframe
comes has received the CAMs of the vehicles transmitting earlier in the period, and those carry the moves they
have decided (their new positions); the vehicles later in the period have not yet announced anything. So the
agents decide in the order of their subframes (:func:`decision_order`; ties, vehicles sharing a subframe on other
sub-channels, the lower vehicle index first), and agent ``i``'s observation at its turn is the env's observation
with every vehicle of an earlier subframe at its announced position (:func:`turn_view`, :func:`turn_observation`).
Vehicles sharing ``i``'s subframe transmit with it (half duplex: neither hears the other), so ``i`` sees their old
positions even when the tie rule lets them decide first. Every announcement is heard (the observation's
positions are every vehicle's, as in the simultaneous versions); the other entries (measurements, own state) are
the period's, unchanged by the moves.

:class:`SubframeAECEnv` is the PettingZoo AEC API of such an env (``make_aec_env`` builds it): ``agent_iter``
yields the agents in the period's order, ``observe`` is the view at the agent's turn, the period's step runs once
the last agent has decided (the moves are per vehicle, so the period's positions equal the moves made one after
the other) and its rewards are the env's (``cv2x/Cooperative-v1``: the team objective, as v0). The parallel API of
the same env takes the period's actions at once, on the period's first observation (PettingZoo's AEC-to-parallel
meaning); a policy on the parallel env makes the turns itself with :func:`decide_in_turns` (one call per subframe,
the observations at the turn: a learner's batched actor) or :func:`announced_positions` (the scripts of
:mod:`cv2x_marl.policies.sequential`).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from pettingzoo.utils.agent_selector import AgentSelector
from pettingzoo.utils.conversions import parallel_to_aec_wrapper

from cv2x_marl.env import step as step_core

if TYPE_CHECKING:
    from cv2x_marl.env.mobility_env import MobilityEnv

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def subframes(env: MobilityEnv) -> IntArray:
    """[N] each vehicle's transmission subframe in the period (``resource // n_subchannels``, 0 .. RRI - 1)."""
    return np.asarray(env.resource, dtype=np.int64) // int(env.config.sps.n_subchannels)


def decision_order(subframe: IntArray) -> IntArray:
    """[N] vehicle indices in the order they decide: by subframe, ties by the lower index (a stable sort).

    Args:
        subframe: [N] each vehicle's transmission subframe (:func:`subframes`).
    """
    return np.argsort(np.asarray(subframe, dtype=np.int64), kind="stable").astype(np.int64)


def visible_mask(subframe: IntArray, decided: NDArray[np.bool_], i: int) -> NDArray[np.bool_]:
    """[N] the vehicles whose decided move vehicle ``i`` has heard: decided and in an earlier subframe than ``i``'s.

    Args:
        subframe: [N] transmission subframes. decided: [N] who has decided this period. i: the vehicle.
    """
    return np.asarray(decided, dtype=bool) & (np.asarray(subframe) < subframe[i])


def announced_positions(env: MobilityEnv, actions: FloatArray, announced: NDArray[np.bool_]) -> FloatArray:
    """[N, 2] positions (m) with the vehicles of ``announced`` where their actions move them this period (the env's
    move rule: :func:`~cv2x_marl.env.step.move_vehicles`, clip, drift and region bounds, settle phase) and every
    other vehicle where it is now.

    Args:
        env: a snapshot-mode env between two steps.
        actions: [N, 2] the period's actions (rows outside ``announced`` are not read).
        announced: [N] the vehicles whose moves are announced.
    """
    mask = np.asarray(announced, dtype=bool)
    now = np.asarray(env.positions_m, dtype=np.float64)
    if not mask.any():
        return now.copy()
    act = np.where(mask[:, None], np.asarray(actions, dtype=np.float64), 0.0)
    plan = env.plan_m if env.dynamics.residual else now
    settle = env.t >= env.max_cycles - env.settle_steps
    new, _, _ = step_core.move_vehicles(
        act, now, env.start_m, np.asarray(plan, dtype=np.float64), env.step_scale_m, env.max_step_m,
        env.dynamics.residual, settle, env.drift_m, env.roi, env.box_m,
    )  # fmt: skip
    return np.where(mask[:, None], new, now)


def turn_observations(env: MobilityEnv, rows: IntArray, positions_m: FloatArray) -> NDArray[np.float32]:
    """[len(rows), size] the observations of agents ``rows`` with the vehicles at ``positions_m``
    (:func:`announced_positions`): the env's observation (:meth:`~cv2x_marl.env.mobility_env.MobilityEnv.build`,
    the version's entries) with the positions and the pair geometry at ``positions_m``, everything else the
    period's. Equal bit for bit to the parallel observations when no vehicle has moved (``positions_m`` the env's).

    Args:
        env: a snapshot-mode env between two steps.
        rows: [A] the agents' vehicle indices.
        positions_m: [N, 2] the positions they have heard (m).
    """
    pos = np.asarray(positions_m, dtype=np.float64)
    rows = np.asarray(rows, dtype=np.int64)
    now, geometry = env.positions_m, env.geometry
    moved = not np.array_equal(pos, now)
    try:
        if moved:
            env.positions_m = pos
            env.geometry = env.links.geometry(pos)
        obs = env.build(rows)
        if rows.size == env.n:
            env.observer.fill(env, obs, rows)
        else:  # the versions with a plan fill every vehicle at once or one at a time
            for r, i in enumerate(rows):
                one = obs[r : r + 1]
                env.observer.fill_mover(env, one, int(i))
    finally:
        env.positions_m, env.geometry = now, geometry
    return obs


def turn_observation(env: MobilityEnv, i: int, positions_m: FloatArray) -> NDArray[np.float32]:
    """[size] agent ``i``'s observation with the vehicles at ``positions_m`` (:func:`turn_observations`)."""
    return turn_observations(env, np.array([i], dtype=np.int64), positions_m)[0]


def decide_in_turns(
    env: MobilityEnv, decide: Callable[[IntArray, NDArray[np.float32]], Any]
) -> tuple[FloatArray, NDArray[np.float32]]:
    """The period's actions, the vehicles deciding subframe by subframe (what the AEC API does, for a policy that
    acts on a batch: a learner's actor, a script).

    Every vehicle of one subframe hears the same moves (those of the earlier subframes), so one call of ``decide``
    per subframe gets them all: ``decide(rows, obs)`` receives the vehicles of the subframe and their observations
    at their turn and returns their actions [len(rows), 2].

    Args:
        env: a snapshot-mode env between two steps.
        decide: the policy of one subframe's vehicles.

    Returns:
        ``(actions [N, 2], observations [N, size])``: the period's actions (pass them to ``env.step``) and each
        vehicle's observation at its turn.
    """
    sub = subframes(env)
    act = np.zeros((env.n, 2))
    obs = np.zeros((env.n, env.layout.size), dtype=np.float32)
    decided = np.zeros(env.n, dtype=bool)
    for s in np.unique(sub):
        rows = np.flatnonzero(sub == s)
        obs[rows] = turn_observations(env, rows, announced_positions(env, act, decided))
        act[rows] = np.asarray(decide(rows, obs[rows]), dtype=np.float64).reshape(rows.size, 2)
        decided[rows] = True
    return act, obs


class SubframeAECEnv(parallel_to_aec_wrapper):
    """The AEC API of a ``decision_order="subframe"`` env (module docstring): the agents decide in the order of their
    transmission subframes, each observing the moves announced in the earlier subframes of the period.

    Attributes:
        order: the live agents in this period's order of decisions.
        actions_m: [N, 2] the actions decided so far this period (undecided rows 0).
        decided: [N] who has decided this period.
    """

    terminations: dict[str, bool]
    truncations: dict[str, bool]

    def __init__(self, parallel_env: MobilityEnv) -> None:
        if parallel_env.options.decision_order != "subframe":
            raise ValueError(
                f"SubframeAECEnv needs decision_order='subframe', got {parallel_env.options.decision_order!r} "
                "(make_aec_env builds PettingZoo's AEC conversion for simultaneous decisions)"
            )
        super().__init__(parallel_env)
        self.order: list[str] = []
        self.actions_m = np.zeros((parallel_env.n, 2))
        self.decided = np.zeros(parallel_env.n, dtype=bool)
        self._subframe = np.zeros(parallel_env.n, dtype=np.int64)

    @property
    def par(self) -> MobilityEnv:
        """The parallel env whose periods this API steps."""
        return self.env

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> None:
        super().reset(seed=seed, options=options)
        self._start_period()

    def _start_period(self) -> None:
        """A new period: nobody has decided; the order of the live agents by subframe."""
        par = self.par
        self._subframe = subframes(par)
        live = set(par.agents)
        self.order = [par.possible_agents[i] for i in decision_order(self._subframe) if par.possible_agents[i] in live]
        self._agent_selector = AgentSelector(self.order)
        self.agent_selection = self._agent_selector.reset()
        self.actions_m = np.zeros((par.n, 2))
        self.decided = np.zeros(par.n, dtype=bool)
        self._actions = dict.fromkeys(self.order)

    def heard_positions(self, agent: str) -> FloatArray:
        """[N, 2] the positions ``agent`` has heard now: the moves announced in the earlier subframes, the rest
        where they are (:func:`announced_positions`, :func:`visible_mask`)."""
        i = self.par.agent_index[agent]
        return announced_positions(self.par, self.actions_m, visible_mask(self._subframe, self.decided, i))

    def observe(self, agent: str) -> NDArray[np.float32]:
        """``agent``'s observation now (at its turn: with the moves announced before it); after the episode's last
        period, its final observation."""
        if not self.par.agents:
            return self._observations[agent]
        return turn_observation(self.par, self.par.agent_index[agent], self.heard_positions(agent))

    def step(self, action: Any) -> None:
        agent = self.agent_selection
        if self.terminations[agent] or self.truncations[agent]:
            self._actions.pop(agent, None)
            self._was_dead_step(action)
            return
        par = self.par
        i = par.agent_index[agent]
        # checked at the turn (shape (2,), finite: the env's messages), before later agents hear the move
        self.actions_m[i] = step_core.decode_actions({agent: action}, {agent}, [agent], par.possible_agents,
                                                     par.agent_index)[i]  # fmt: skip
        self._actions[agent] = action
        self.decided[i] = True
        if not self._agent_selector.is_last():
            if self._agent_selector.is_first():
                self._clear_rewards()
            self.agent_selection = self._agent_selector.next()
            return
        obss, rews, terms, truncs, infos = self.par.step(self._actions)
        self._observations = copy.copy(obss)
        self.terminations, self.truncations = copy.copy(terms), copy.copy(truncs)
        self.infos, self.rewards = copy.copy(infos), copy.copy(rews)
        self._cumulative_rewards = copy.copy(rews)
        self.agents = self.par.agents + [a for a in sorted(obss) if a not in set(self.par.agents)]
        if self.par.agents:
            self._start_period()
        self._deads_step_first()


def subframe_aec(parallel_env: MobilityEnv) -> Any:
    """:class:`SubframeAECEnv` with PettingZoo's order-enforcing wrapper (what ``make_aec_env`` returns)."""
    from pettingzoo.utils.wrappers import OrderEnforcingWrapper

    return OrderEnforcingWrapper(SubframeAECEnv(parallel_env))
