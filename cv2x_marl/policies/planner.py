"""The planner movers: drive straight to the best reachable position under an estimate a vehicle has.

Scripted, not privileged (they read what a vehicle knows or measures): ``planner`` searches the
two-distance model's predicted utility over the reachable set (:func:`~cv2x_marl.env.planning.model_plan`),
``sensing`` the mover's Mode 4 sensing estimate (:func:`~cv2x_marl.env.planning.sensing_plan`). The
reachable set and the searches are the env's (:mod:`cv2x_marl.env.planning`); the privileged
counterpart, the true utility's optimum, is :class:`cv2x_marl.policies.optimum.OptimumPolicy`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env.observation import decode_observations
from cv2x_marl.env.planning import (
    MEASURED_REPLAN_EVERY,
    PlanningEnv,
    measured_plan,
    model_plan,
    reachable_set,
    sensing_plan,
)
from cv2x_marl.policies.base import Actions, Observations

FloatArray = NDArray[np.float64]


class PlannerPolicy:
    """Scripted, not privileged: drive straight to the model's best reachable position.

    The position is computed once per episode from the first observation (one-hop information and
    the two-distance model, like GBMU) by a global search of the model's predicted utility over the
    reachable set (:func:`model_plan`), instead of GBMU's local gradient steps. It shows how much of
    GBMU's gap to the optimum is the algorithm (local steps) and how much the model.

    With ``estimator="sensing"`` (``--policy sensing``) the search runs on the mover's sensing
    estimate instead of the two-distance model (:func:`sensing_plan`): still not privileged (it reads
    only what a vehicle measures), it shows how much of the rest is the model. In an observation
    version 2 env it follows the env's plan, which is the same estimate (and is recomputed with
    ``replan_every``). In an observation version 3 env (no plan in the observation) it plans from the
    measurements the observation carries (:func:`~cv2x_marl.env.planning.measured_plan`: own links from
    the measured RSRP, the others' pairs at median shadowing) and replans every
    :data:`~cv2x_marl.env.planning.MEASURED_REPLAN_EVERY` steps (once per sensing window) from the
    refreshed measurements.

    Args:
        env: the env it acts in (read, never stepped).
        model: the two-distance model (``estimator="model"``).
        estimator: ``model`` or ``sensing``.
    """

    name = "planner"

    def __init__(self, env: PlanningEnv, model: Any, estimator: str = "model") -> None:
        if estimator not in ("model", "sensing"):
            raise ValueError(f"invalid planner estimator {estimator!r}; allowed: model, sensing")
        if estimator == "sensing" and env.mode != "snapshot":
            raise ValueError("the sensing planner needs the env in snapshot mode")
        self.env = env
        self.model = model
        self.estimator = estimator
        if estimator == "sensing":
            self.name = "sensing"
        self.targets_m: dict[str, FloatArray] = {}

    def reset(self, seed: int | None = None) -> None:
        self.targets_m = {}

    def act(self, observations: Observations) -> Actions:
        env = self.env
        agents = list(observations)
        if self.estimator == "sensing" and env.layout.version == 3:
            if not self.targets_m or env.t % MEASURED_REPLAN_EVERY == 0:
                idx = [env.agent_index[a] for a in agents]
                self.targets_m = dict(zip(agents, measured_plan(env, idx), strict=True))
        elif self.estimator == "sensing" and env.layout.version == 2:
            # the env's own plan is this estimate (and follows its replanning, ``replan_every``)
            self.targets_m = {a: env.plan_m[env.agent_index[a]] for a in agents}
        elif not self.targets_m:
            idx = [env.agent_index[a] for a in agents]
            if self.estimator == "sensing":
                plan = sensing_plan(env, idx)
            else:
                v0 = np.stack([observations[a][: env.layout.v0_size] for a in agents])
                pos = np.asarray(env.positions_m)[idx]
                reaches = [reachable_set(env, i) for i in idx]
                plan = model_plan(decode_observations(v0, env.layout), pos, reaches, self.model, env.p_min)
            self.targets_m = dict(zip(agents, plan, strict=True))
        out: Actions = {}
        for a in agents:
            move = (self.targets_m[a] - env.positions_m[env.agent_index[a]]) / env.max_step_m
            out[a] = np.clip(move, -1.0, 1.0).astype(np.float32)
        return out
