"""A stable-baselines3 PPO model as a policy (``--policy ppo:PATH``)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cv2x_marl.extras import require
from cv2x_marl.policies.base import Actions, BatchPolicy, Observations, one_torch_thread
from cv2x_marl.runs import check_file

if TYPE_CHECKING:
    from cv2x_marl.env.mobility_env import MobilityEnv


def _is_recurrent_save(path: Path) -> bool:
    """Whether an SB3 save holds sb3-contrib's recurrent policy (its ``data`` names the policy's module)."""
    import json
    import zipfile

    try:
        with zipfile.ZipFile(path) as archive:
            data = json.loads(archive.read("data"))
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return False  # PPO.load reports what is wrong with the file
    module = data.get("policy_class", {}).get("__module__", "") if isinstance(data, dict) else ""
    return isinstance(module, str) and module.startswith("sb3_contrib.common.recurrent")


class PpoPolicy(BatchPolicy):
    """A stable-baselines3 PPO model (shared across agents) acting deterministically.

    The network runs on one agent's observation at a time (``model.predict`` on ``[1, obs_dim]``, the rule of
    :mod:`cv2x_marl.policies.base`): an agent's action is a function of its own observation alone, bit for bit,
    whatever the other agents of the step. A one-mover env (``cv2x/SingleMover-v3``, ``cv2x/Traffic-v1``) always
    ran it so.

    A recurrent model (``ppo.recurrent: true``: sb3-contrib's ``RecurrentPPO``) keeps one LSTM state per
    agent over the episode, from zeros at :meth:`reset` (and for an agent first seen later), as it was trained
    (``episode_start`` at an agent's first step); each agent's step is its own batch of one too.

    Args:
        path: the ``.zip`` written by ``cv2x-marl train`` (or any SB3 PPO / RecurrentPPO save).
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
            if _is_recurrent_save(path):
                algo = require("sb3_contrib", f"loading the recurrent PPO model {path}").RecurrentPPO
            else:
                algo = require("stable_baselines3", f"loading the PPO model {path}").PPO
            try:
                self.model = algo.load(str(path), device="cpu")
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

        self.recurrent = hasattr(self.model.policy, "lstm_actor")
        #: a recurrent model's LSTM state per agent (sb3-contrib's (h, c), each [layers, 1, units])
        self._lstm_states: dict[str, Any] = {}

    def reset(self, seed: int | None = None) -> None:
        """A new episode: a recurrent model's LSTM states start from zeros."""
        self._lstm_states = {}

    def act(self, observations: Observations) -> Actions:
        """Each agent's action from its own observation (and, recurrent, its own LSTM state), a batch of one."""
        with one_torch_thread():
            if not self.recurrent:
                return super().act(observations)
            out: Actions = {}
            for agent, ob in observations.items():
                state = self._lstm_states.get(agent)
                row = np.asarray(ob, dtype=np.float32).reshape(1, -1)
                act, self._lstm_states[agent] = self.model.predict(
                    row, state=state, episode_start=np.array([state is None]), deterministic=True
                )
                out[agent] = np.asarray(act, dtype=np.float32).reshape(2)
            return out

    def _predict(self, obs: np.ndarray) -> np.ndarray:
        """[1, obs_dim] -> [1, 2] (a stateless model)."""
        act, _ = self.model.predict(obs, deterministic=True)
        return np.asarray(act)
