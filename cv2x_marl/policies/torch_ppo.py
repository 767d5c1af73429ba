"""A PPO actor saved by ``cv2x-marl train`` with ``ppo.backend: torchrl`` as a policy (``--policy ppo:PATH/model.pt``).

``model.pt`` holds plain values and tensors (read with ``torch.load(weights_only=True)``: no pickled code): the
format tag :data:`MODEL_FORMAT`, the env id, the keyword arguments and the weights of
:class:`cv2x_marl.policies.ppo_nets.ActorCritic`. It acts deterministically: the Gaussian's mean, clipped to the
action Box (as SB3's ``predict(deterministic=True)``).

``ppo:PATH`` names a ``.pt`` file for MAPPO too; :func:`load_pt_policy` reads the file's format tag and builds the
policy it names.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cv2x_marl.extras import require
from cv2x_marl.policies.base import BatchPolicy
from cv2x_marl.policies.mappo import MODEL_FORMAT as MAPPO_FORMAT
from cv2x_marl.policies.mappo import MappoPolicy
from cv2x_marl.runs import check_file

if TYPE_CHECKING:
    from cv2x_marl.env.mobility_env import MobilityEnv

#: the format tag of a ``ppo.backend: torchrl`` ``model.pt`` (:mod:`cv2x_marl.rl.fast_ppo`)
MODEL_FORMAT = "cv2x_marl.torch_ppo"
#: the formats a ``ppo:PATH.pt`` may hold
PT_FORMATS = (MODEL_FORMAT, MAPPO_FORMAT)


def model_contents(env_id: str, net: Any) -> dict[str, Any]:
    """What a torchrl-format ``model.pt`` holds for ``net`` (a :class:`cv2x_marl.policies.ppo_nets.ActorCritic`)
    trained on ``env_id``: the format tag, the id, the network's keyword arguments and weights (plain values and
    tensors; ``torch.save`` it)."""
    return {"format": MODEL_FORMAT, "env_id": env_id, "net_kwargs": net.spec(), "net_state": net.state_dict()}


def read_model_file(path: Path, what: str) -> dict[str, Any]:
    """``torch.load(path, weights_only=True)`` of a ``.pt`` model, checked against its run's checksum.

    Raises:
        ValueError: a missing or unreadable file, or one that is not a mapping (each naming the file).
    """
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{what} model file {path} does not exist")
    check_file(path)  # against the checksum in the run folder's run.json, when it has one
    torch = require("torch", f"loading the {what} model {path}")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # any load failure is reported with the file name
        raise ValueError(f"cannot load {what} model {path}: {type(exc).__name__}: {exc}") from exc
    if not isinstance(data, dict):
        raise ValueError(f"{path} is not a model of cv2x-marl train (formats: {', '.join(PT_FORMATS)})")
    return data


def load_pt_policy(path: str | Path, env: MobilityEnv | None = None) -> BatchPolicy:
    """The policy of a ``.pt`` model file: a ``ppo.backend: torchrl`` actor or a MAPPO actor, by its format tag.

    Raises:
        ValueError: an unreadable file or an unknown format (naming the file and the formats allowed).
    """
    fmt = read_model_file(Path(path), "PyTorch").get("format")
    if fmt == MODEL_FORMAT:
        return TorchPpoPolicy(path, env)
    if fmt == MAPPO_FORMAT:
        return MappoPolicy(path, env)
    raise ValueError(f"{path} has format {fmt!r}; a ppo:PATH .pt file must hold one of {', '.join(PT_FORMATS)}")


class TorchPpoPolicy(BatchPolicy):
    """A ``ppo.backend: torchrl`` actor acting deterministically for every agent present.

    Args:
        path: the ``model.pt`` of the run folder.
        env: the env it will act in; its observation size must be the network's.

    Raises:
        ValueError: a missing or unreadable file, another format, or another observation size (each naming the file).
    """

    def __init__(self, path: str | Path, env: MobilityEnv | None = None) -> None:
        super().__init__(self._predict, "ppo")
        path = Path(path)
        data = read_model_file(path, "PPO")
        if data.get("format") != MODEL_FORMAT:
            raise ValueError(f"{path} is not a ppo.backend: torchrl model (no format {MODEL_FORMAT!r})")
        self.env_id = str(data["env_id"])
        torch = require("torch", f"loading the PPO model {path}")
        from cv2x_marl.policies.ppo_nets import ActorCritic

        try:
            self.net = ActorCritic(**data["net_kwargs"])
            self.net.load_state_dict(data["net_state"])
        except Exception as exc:
            raise ValueError(f"cannot rebuild the PPO network of {path}: {type(exc).__name__}: {exc}") from exc
        self.net.eval()
        self._torch = torch
        if env is not None:
            want = tuple(env.observation_space(env.possible_agents[0]).shape)
            got = (int(self.net.obs_size),)
            if want != got:
                raise ValueError(
                    f"PPO model {path} expects observations of shape {got}, the env gives {want} "
                    "(another vehicle count or n_neighbours?)"
                )

    def _predict(self, obs: np.ndarray) -> np.ndarray:
        """[n_agents, obs_size] -> [n_agents, 2] in [-1, 1]."""
        with self._torch.no_grad():
            return self.net.deterministic(self._torch.from_numpy(np.ascontiguousarray(obs))).numpy()
