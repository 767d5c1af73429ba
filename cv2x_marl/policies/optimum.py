"""The optimum mover: the best reachable position under the env's true utility.

A privileged reference (it reads the env's link model, like the oracle), but global where the
oracle is local: for each mover it searches the whole set of positions the mover can reach in the
episode for the one with the largest eq. 12 utility, evaluated by the same link computation as the
env's reward (:meth:`cv2x_marl.sim.ground_truth.SnapshotLinks.mover_row`, bit-identical to the reward),
then drives there in straight steps.

The reachable set and the search (a grid over the set, two refinements, the start always a candidate)
are the env's: :mod:`cv2x_marl.env.planning` describes them.

Several movers (``cv2x/Mobility-*``): coordinate-wise best response. In ``rounds`` rounds, each mover
in index order moves to its best reachable position given where the others are at that moment
(their targets so far); every mover then drives to its final target. This is a Nash-style
reference for the individual reward, not a bound on the team's utility or PRR: one mover's best
response can lower the others' utility through interference, and the rounds need not converge.

The Cooperative ceiling: when the env rewards the team objective (``reward="team"``: the mean over
vehicles of the eq. 12 utility, per receiver with ``normalise_reward``) and every vehicle moves, the
targets are the best positions found by :func:`cv2x_marl.env.team_search.team_search` (centralised
coordinate ascent of the team objective over every reachable set, from the snapshot and from the
best-response positions, in two vehicle orders): "the best found", never below best response, not a
proof of optimality. :class:`BestResponsePolicy` always plays best response.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env.planning import (
    PlanningEnv,
    best_reachable,
    check_reach_grid,
    reachable_set,
)
from cv2x_marl.env.team_search import team_search
from cv2x_marl.policies.base import Actions, Observations

FloatArray = NDArray[np.float64]


def best_response_targets(
    env: PlanningEnv, movers: list[int], rounds: int = 2, grid_m: float = 2.5, refine: int = 16
) -> FloatArray:
    """[N, 2] target positions: the others stay, each mover's best response after ``rounds`` rounds.

    One mover (``cv2x/SingleMover-*``) needs one round: it is then the exact best reachable position.
    """
    pos = np.array(env.positions_m, dtype=np.float64)
    rounds = 1 if len(movers) == 1 else rounds
    for _ in range(rounds):
        for i in movers:
            row = env.links.mover_row(i, pos)
            pos[i], _ = best_reachable(row, reachable_set(env, i), env.p_min, grid_m, refine)
    return pos


def uses_team_search(env: PlanningEnv) -> bool:
    """Whether :class:`OptimumPolicy` searches the team objective in ``env``: the reward is the team's
    (``reward="team"``, or ``"difference"``: each vehicle's marginal contribution to it) and every vehicle moves."""
    return getattr(env, "reward_kind", "individual") in ("team", "difference") and bool(np.all(env.mover_mask))


class OptimumPolicy:
    """Privileged reference: every mover drives straight to its best reachable position.

    Targets are computed at the first step of each episode, then each action is the remaining
    displacement over ``max_step_m``, clipped to the box. The targets: best response
    (:func:`best_response_targets`), or, when the env rewards the team and every vehicle moves
    (:func:`uses_team_search`), the best positions :func:`~cv2x_marl.env.team_search.team_search` finds
    for the team objective from the snapshot and the best-response positions (the Cooperative ceiling:
    the best found, never below best response). Snapshot mode only (traffic mode has no fixed
    landscape to search).

    Args:
        env: the :class:`~cv2x_marl.env.MobilityEnv` it acts in (read, never stepped by the policy).
        rounds: best-response rounds when several vehicles move.
        grid_m: pitch of the global search grid (m); default 2.5 for one mover, 10 for several.
        refine: grid points refined in each mover's search.
        team: search the team objective where :func:`uses_team_search` (False: best response always).
    """

    name = "optimum"

    def __init__(
        self, env: PlanningEnv, rounds: int = 2, grid_m: float | None = None, refine: int = 16, team: bool = True
    ) -> None:
        if env.mode != "snapshot":
            raise ValueError("the optimum policy needs the env in snapshot mode")
        self.env = env
        self.rounds = rounds
        # one mover: 2.5 m; best-response rounds over many movers: 10 m (then refined to 0.1 m)
        self.grid_m = grid_m if grid_m is not None else (2.5 if int(np.sum(env.mover_mask)) == 1 else 10.0)
        check_reach_grid(env, self.grid_m, "the optimum policy")  # refused here, before an episode runs
        self.refine = refine
        self.targets_m: FloatArray | None = None
        self._episode: int | None = None
        #: whether the targets come from the team search (the Cooperative ceiling)
        self.team = team and uses_team_search(env)

    def reset(self, seed: int | None = None) -> None:
        self.targets_m = None

    def _targets(self) -> FloatArray:
        env = self.env
        movers = [int(i) for i in np.flatnonzero(env.mover_mask)]
        br = best_response_targets(env, movers, self.rounds, self.grid_m, self.refine)
        if not self.team:
            return br
        start = np.array(env.positions_m, dtype=np.float64)
        return team_search(env, [start, br], normalise=bool(getattr(env, "normalise_reward", True))).positions_m

    def act(self, observations: Observations) -> Actions:
        env = self.env
        if self.targets_m is None or (env.t == 0 and self._episode != id(env.links)):
            self.targets_m = self._targets()
            self._episode = id(env.links)
        out: Actions = {}
        for a in observations:
            i = env.agent_index[a]
            move = (self.targets_m[i] - env.positions_m[i]) / env.max_step_m
            out[a] = np.clip(move, -1.0, 1.0).astype(np.float32)
        return out


class BestResponsePolicy(OptimumPolicy):
    """Best response whatever the reward (:func:`best_response_targets`): each mover drives to its best
    reachable position for its own eq. 12 utility, given the others' (``cv2x/Mobility-*``,
    ``Cooperative``)."""

    name = "best-response"

    def __init__(self, env: PlanningEnv, rounds: int = 2, grid_m: float | None = None, refine: int = 16) -> None:
        super().__init__(env, rounds, grid_m, refine, team=False)
