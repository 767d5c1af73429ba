"""A stable-baselines3 PPO model as a policy (``--policy ppo:PATH``)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cv2x_marl.extras import require
from cv2x_marl.policies.base import BatchPolicy
from cv2x_marl.runs import check_file

if TYPE_CHECKING:
    from cv2x_marl.env.mobility_env import MobilityEnv


class PpoPolicy(BatchPolicy):
    """A stable-baselines3 PPO model (shared across agents) acting deterministically.

    Args:
        path: the ``.zip`` written by ``cv2x-marl train`` (or any SB3 PPO save).
        env: the env it will act in; its observation and action spaces must match the model's.
    """

    def __init__(self, path: Path | Any, env: MobilityEnv | None = None) -> None:
        super().__init__(self._predict, "ppo")
        if not isinstance(path, str | Path):  # an already loaded model
            self.model = path
        else:
            path = Path(path)
            if not path.exists():
                raise ValueError(f"PPO model file {path} does not exist")
            check_file(path)  # against the checksum in the run folder's run.json, when it has one
            PPO = require("stable_baselines3", f"loading the PPO model {path}").PPO

            try:
                self.model = PPO.load(str(path), device="cpu")
            except Exception as exc:  # any load failure is reported with the file name
                raise ValueError(f"cannot load PPO model {path}: {type(exc).__name__}: {exc}") from exc
        if env is not None:
            want = env.observation_space(env.possible_agents[0]).shape
            got = self.model.observation_space.shape
            if want != got:
                raise ValueError(
                    f"PPO model {path} expects observations of shape {got}, the env gives {want} "
                    "(another vehicle count or n_neighbours?)"
                )

    def _predict(self, obs: np.ndarray) -> np.ndarray:
        act, _ = self.model.predict(obs, deterministic=True)
        return np.asarray(act)
