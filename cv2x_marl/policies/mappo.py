"""A MAPPO actor saved by ``cv2x-marl train`` (``algo: mappo``) as a policy (``--policy ppo:PATH/model.pt``).

``model.pt`` holds plain values and tensors (read with ``torch.load(weights_only=True)``: no pickled code): the
format tag, the env id, the actor's kind, keyword arguments and weights (and the critic's, unused here). The actor
class is :class:`cv2x_marl.policies.mappo_nets.SharedActor` (``actor_kind`` absent or ``gaussian``: the offsets of
``cv2x/Cooperative-v0``) or :class:`~cv2x_marl.policies.mappo_nets.MaskedActor` (``categorical``: an entry of the
candidate list of ``cv2x/Resource-v0``), this layer's (the trainer, :mod:`cv2x_marl.rl.mappo`, builds its actor from
them too), imported when a file is loaded (torch is an extra). It acts deterministically on one agent's observation
at a time (the batch-invariance rule of :mod:`cv2x_marl.policies.base`: an agent's action is a function of its own
observation alone, bit for bit): ``tanh`` of the Gaussian's mean, or the most probable entry among the valid ones
(the mask read from the observation itself: the candidates' ``valid`` entries where ``decides`` is set).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cv2x_marl.extras import require
from cv2x_marl.policies.base import Actions, BatchPolicy, Observations, one_torch_thread
from cv2x_marl.runs import check_file

if TYPE_CHECKING:
    from cv2x_marl.env.mobility_env import MobilityEnv

#: the format tag of ``model.pt`` (:data:`cv2x_marl.rl.mappo.MODEL_FORMAT`)
MODEL_FORMAT = "cv2x_marl.mappo"
#: the suffix that makes ``ppo:PATH`` a MAPPO actor instead of an SB3 zip
SUFFIX = ".pt"


def is_mappo_file(path: str | Path) -> bool:
    """Whether ``ppo:PATH`` names a MAPPO actor (a ``.pt`` file) rather than an SB3 ``.zip``."""
    return Path(path).suffix == SUFFIX


class MappoPolicy(BatchPolicy):
    """A MAPPO shared actor acting deterministically for every agent present, each on its own observation alone.

    The actor runs once per agent on ``[1, obs_size]`` (:class:`~cv2x_marl.policies.base.BatchPolicy`'s rule): an
    agent's action does not depend, to the last bit, on how many agents act in the step or what they observe.

    Args:
        path: the ``model.pt`` of a MAPPO run folder.
        env: the env it will act in; its observation size must be the actor's.

    Raises:
        ValueError: a missing or unreadable file, another format, or another observation size (each naming the file).
    """

    def __init__(self, path: str | Path, env: MobilityEnv | None = None) -> None:
        # _predict runs the actor one row at a time itself (one no_grad and one tensor for the step)
        super().__init__(self._predict, "mappo", row_by_row=False)
        path = Path(path)
        if not path.exists():
            raise ValueError(f"MAPPO model file {path} does not exist")
        check_file(path)  # against the checksum in the run folder's run.json, when it has one
        torch = require("torch", f"loading the MAPPO model {path}")
        try:
            data = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # any load failure is reported with the file name
            raise ValueError(f"cannot load MAPPO model {path}: {type(exc).__name__}: {exc}") from exc
        if not isinstance(data, dict) or data.get("format") != MODEL_FORMAT:
            raise ValueError(f"{path} is not a MAPPO model of cv2x-marl train (no format {MODEL_FORMAT!r})")
        self.env_id = str(data["env_id"])
        from cv2x_marl.policies.mappo_nets import ACTOR_KINDS, MaskedActor, SharedActor

        self.kind = str(data.get("actor_kind", "gaussian"))
        if self.kind not in ACTOR_KINDS:
            raise ValueError(f"{path} holds a MAPPO actor of kind {self.kind!r}; kinds: {', '.join(ACTOR_KINDS)}")
        try:
            self.actor = (MaskedActor if self.kind == "categorical" else SharedActor)(**data["actor_kwargs"])
            self.actor.load_state_dict(data["actor_state"])
        except Exception as exc:
            raise ValueError(f"cannot rebuild the MAPPO actor of {path}: {type(exc).__name__}: {exc}") from exc
        self.actor.eval()
        self._torch = torch
        if env is not None:
            check_action_space(self.actor, env, path)
            want = tuple(env.observation_space(env.possible_agents[0]).shape)
            got = (int(self.actor.obs_size),)
            if want != got:
                raise ValueError(
                    f"MAPPO model {path} expects observations of shape {got}, the env gives {want} "
                    "(another vehicle count or n_neighbours?)"
                )

    def act(self, observations: Observations) -> Actions:
        if self.kind == "categorical":
            return masked_choices(self.actor, observations)
        return super().act(observations)

    def _predict(self, obs: np.ndarray) -> np.ndarray:
        """[n, obs_size] -> [n, 2] in [-1, 1]: the actor on each row alone (a batch of one, ``[1, obs_size]``)."""
        with self._torch.no_grad(), one_torch_thread():
            rows = self._torch.from_numpy(np.ascontiguousarray(obs, dtype=np.float32))
            acts = [self.actor.deterministic(rows[i : i + 1]) for i in range(rows.shape[0])]
            return self._torch.cat(acts).numpy() if acts else np.zeros((0, 2), dtype=np.float32)


def check_action_space(actor: Any, env: MobilityEnv, path: str | Path) -> None:
    """Refuse an env whose action space is not the actor's: ``Discrete(n)`` with the masked actor's n entries, a
    ``Box`` of the Gaussian actor's size otherwise (each naming the file and both spaces)."""
    from gymnasium import spaces

    space = env.action_space(env.possible_agents[0])
    if getattr(actor, "kind", "gaussian") == "categorical":
        if not isinstance(space, spaces.Discrete) or int(space.n) != int(actor.n_actions):
            raise ValueError(
                f"MAPPO model {path} picks one of {actor.n_actions} list entries (Discrete({actor.n_actions}), "
                f"cv2x/Resource-v0); this env's action space is {space}"
            )
        return
    size = int(actor.spec()["act_size"])
    if not isinstance(space, spaces.Box) or tuple(space.shape) != (size,):
        raise ValueError(f"MAPPO model {path} gives Box actions of shape ({size},); this env's action space is {space}")


def masked_choices(actor: Any, observations: Observations) -> Actions:
    """Each agent's most probable valid entry (int64; 0 without a decision) from a masked actor
    (:class:`~cv2x_marl.policies.mappo_nets.MaskedActor`), on its own observation alone (a batch of one)."""
    import torch

    agents = list(observations)
    with torch.no_grad(), one_torch_thread():
        out = {}
        for a in agents:
            row = torch.from_numpy(np.ascontiguousarray(observations[a], dtype=np.float32)).reshape(1, -1)
            out[a] = np.int64(actor.deterministic(row)[0])
    return out  # type: ignore[return-value]


class MaskedChoicePolicy:
    """A masked actor in memory (the trainer's evaluations) as a deterministic policy: :func:`masked_choices`."""

    def __init__(self, actor: Any, name: str = "mappo") -> None:
        self.actor = actor
        self.name = name

    def reset(self, seed: int | None = None) -> None:
        return None

    def act(self, observations: Observations) -> Actions:
        return masked_choices(self.actor, observations)
