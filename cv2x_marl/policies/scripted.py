"""GBMU, greedy and oracle movers behind the :class:`~cv2x_marl.policies.base.Policy` protocol.

GBMU and greedy read everything they use from the observation (positions of the receivers and of
their main interferers relative to the mover, the target flag, NSV): one-hop information only.
The oracle is privileged: it reads the env's link model to climb the true utility.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cv2x_marl.env.observation import ObservationLayout, decode_observations
from cv2x_marl.policies.base import Actions, Observations
from cv2x_marl.policies.gbmu import SteeringUtility, StepSchedule, armijo_move, gbmu_direction
from cv2x_marl.regression.model import TwoDistanceModel
from cv2x_marl.sim.kernels import link_summaries


class GbmuPolicy:
    """GBMU (or greedy, ``fairness=False``) acting through observations.

    One env step is one GBMU iteration: the move ``delta * mean_j(t_j G_ij)`` (metres) becomes the
    action ``move / max_step_m``, clipped to the box. ``delta = 1`` is the paper's step; a larger
    ``delta`` covers in an env episode of ~100 steps the distance the paper's 10,000 in-node
    iterations cover.

    Args:
        model: the steering two-distance model (eq. 15, or its logistic version).
        layout: the env's observation layout.
        max_step_m: the env's offset of a full action (m).
        delta: step size of step 3 (per env step).
        fairness: eq. 12 (GBMU) or eq. 9 (greedy).
        schedule: step-size schedule (:class:`~cv2x_marl.policies.gbmu.StepSchedule`); None: the
            paper's constant ``delta``. ``decay`` counts env steps since :meth:`reset`;
            ``backtracking`` runs Armijo's rule on the model's predicted utility along the move
            projected onto the action box (so the move it accepts is the move the env makes, up to
            the env's own bounds).
    """

    def __init__(
        self,
        model: TwoDistanceModel,
        layout: ObservationLayout,
        max_step_m: float,
        delta: float = 100.0,
        fairness: bool = True,
        schedule: StepSchedule | None = None,
    ) -> None:
        self.model = model
        self.layout = layout
        self.max_step_m = max_step_m
        self.delta = delta
        self.fairness = fairness
        self.schedule = schedule
        self.name = "gbmu" if fairness else "greedy"
        self._k = 0  # GBMU iterations (env steps) since reset, for the decaying step

    def reset(self, seed: int | None = None) -> None:
        self._k = 0

    def act(self, observations: Observations) -> Actions:
        agents = list(observations)
        obs = np.stack([observations[a] for a in agents])
        inputs = decode_observations(obs, self.layout)
        origin = np.zeros((len(agents), 2))
        direction = gbmu_direction(inputs, self.model, self.fairness)(origin)
        kind = "constant" if self.schedule is None else self.schedule.kind
        if kind == "constant":
            move = self.delta * direction
        elif kind == "decay":
            assert self.schedule is not None
            move = float(self.schedule.step_size(self.delta, self._k)) * direction
        else:
            assert self.schedule is not None
            lim = self.max_step_m
            utility = SteeringUtility(inputs, self.model, self.fairness)
            box = lambda m: np.clip(m, -lim, lim)  # noqa: E731 - the action box, in metres
            move, _ = armijo_move(origin, direction, self.delta, utility, self.schedule, box)
        self._k += 1
        act = np.clip(move / self.max_step_m, -1.0, 1.0).astype(np.float32)
        return dict(zip(agents, act, strict=True))


class OraclePolicy:
    """Privileged reference: climbs each agent's true eq. 12 utility (snapshot mode).

    The gradient of agent i's utility with respect to its own position comes from central
    differences of the env's link model (secant +-h_m), the others held where they are; the move
    is ``delta * grad / |R_i|`` as for GBMU.
    """

    name = "oracle"

    def __init__(self, env: Any, delta: float = 100.0, h_m: float = 5.0) -> None:
        self.env = env
        self.delta = delta
        self.h_m = h_m

    def reset(self, seed: int | None = None) -> None:
        return None

    def act(self, observations: Observations) -> Actions:
        env = self.env
        if env.mode != "snapshot":
            raise ValueError("the oracle policy needs the env in snapshot mode")
        out: Actions = {}
        base = env.positions_m
        for a in observations:
            i = env.agent_index[a]
            grad = np.zeros(2)
            for c in range(2):
                us = []
                for sign in (1.0, -1.0):
                    pos = base.copy()
                    pos[i, c] += sign * self.h_m
                    # eq. 12 itself, whatever the env's normalise_reward (the step rule divides by |R_i|)
                    us.append(link_summaries(env.links.success(pos), env.target, env.p_min)[0, i])
                grad[c] = (us[0] - us[1]) / (2 * self.h_m)
            n_rx = max(int(env.target[i].sum()), 1)
            move = self.delta * grad / n_rx
            out[a] = np.clip(move / env.max_step_m, -1.0, 1.0).astype(np.float32)
        return out
