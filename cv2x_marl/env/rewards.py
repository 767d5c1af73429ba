"""The reward model: each agent's reward from the eq. 12 utilities of a step.

Five options say it, read here only: ``reward`` (``individual``: the own utility; ``team``: the mean over the
vehicles of ``team_objective``, their utility or their PRR; ``mixed``: ``local_ratio`` own plus
``1 - local_ratio`` team; ``difference``: the team objective minus its value with the agent back at its start),
``normalise_reward`` (utilities per target receiver, applied where they are computed), ``reward_form``
(``utility``: the reward is the value after the step; ``improvement``: its change over the step, a potential-based
shaping whose episode sum is final minus start) and ``p_min`` (the clip inside eq. 12's log).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env import step as step_core
from cv2x_marl.env.team_search import difference_rewards

if TYPE_CHECKING:
    from cv2x_marl.env.episode import EpisodeEnv

FloatArray = NDArray[np.float64]


class RewardModel:
    """The rewards of one env (its options read from the env at each step).

    Attributes:
        previous: [N] each agent's reward base after the last step (the improvement form's reference).
    """

    def __init__(self) -> None:
        self.previous: FloatArray = np.zeros(0)

    def base(self, env: EpisodeEnv, u: FloatArray) -> FloatArray:
        """[N] the reward's base of utilities ``u`` [N] (what the ``utility`` form returns); the options are read
        from the env at each call (a live env's reward options can be set)."""
        o = env.options
        if o.reward == "individual":
            return u
        if o.reward == "difference":
            return difference_rewards(
                env.links, env.positions_m, env.start_m, env.mover_mask, env.p_min, env.normalise_reward
            )
        team = np.full_like(u, (u if o.team_objective == "utility" else env.prr).mean())
        if o.reward == "team":
            return team
        return o.local_ratio * u + (1.0 - o.local_ratio) * team

    def reset(self, env: EpisodeEnv) -> None:
        """At the episode's start: the reference of the first step's improvement."""
        self.previous = self.base(env, env.utility).copy()

    def step(self, env: EpisodeEnv) -> FloatArray:
        """[N] the rewards of the step just taken (:func:`~cv2x_marl.env.step.step_rewards`)."""
        improvement = env.options.reward_form == "improvement"
        return step_core.step_rewards(self.base(env, env.utility), self.previous, improvement)

    def step_mover(self, env: EpisodeEnv, i: int, u: float) -> float:
        """The reward of agent ``i`` (individual reward) after a step of it alone with utility ``u``."""
        improvement = env.options.reward_form == "improvement"
        reward, self.previous[i] = step_core.step_reward(u, self.previous[i], improvement)
        return float(reward)
