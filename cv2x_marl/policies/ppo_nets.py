"""The actor-critic of ``ppo.backend: torchrl`` (:mod:`cv2x_marl.rl.fast_ppo`), laid out as SB3's ``MlpPolicy``.

:class:`ActorCritic` has the parts and the sizes of the network stable-baselines3 builds for the same
``ppo`` settings (``net_arch``, ``encoder``, ``encoder_units``, ``log_std_init``):

* features [..., F]: the flat observation (``encoder: mlp``, F = obs_size) or the neighbour features of
  :class:`cv2x_marl.policies.encoders.NeighbourEncoder` (``deepsets`` / ``attention``, F = 3 d), one
  extractor shared by the actor and the critic (SB3's ``share_features_extractor=True``);
* the actor: an MLP of ``net_arch`` (tanh) and a linear head to the mean ``mu`` [..., 2] of a diagonal
  Gaussian whose log standard deviation [2] is a free parameter (``log_std_init``); the sampled action is
  clipped to the action Box [-1, 1]^2 by the trainer before the env steps (SB3's ``clip_actions``), the
  deterministic action is ``clip(mu, -1, 1)``;
* the critic: its own MLP of ``net_arch`` (tanh) and a linear head to the value [..., 1].

Initial weights as SB3's ``ortho_init``: every linear layer orthogonal, biases zero, gains sqrt(2) for the
features and the MLPs, 0.01 for the action head and 1 for the value head; drawn from a caller's
``torch.Generator`` (:meth:`ActorCritic.init_weights`), never from the global torch state. The module is built
from plain keyword arguments (:meth:`ActorCritic.spec`), so a saved model (``model.pt``) is rebuilt by
:class:`cv2x_marl.policies.torch_ppo.TorchPpoPolicy` without pickled code.
"""

from __future__ import annotations

import math
from typing import Any

try:
    import torch
    from torch import nn
except ImportError as _exc:  # the train extra is not installed
    from cv2x_marl.extras import missing_extra

    raise missing_extra("torch", "the PPO networks (cv2x_marl.policies.ppo_nets)", _exc) from _exc


def tanh_mlp(n_in: int, hidden: tuple[int, ...] | list[int]) -> tuple[nn.Sequential, int]:
    """``n_in`` -> hidden layers (each linear, then tanh); returns the module and its output width."""
    layers: list[nn.Module] = []
    width = int(n_in)
    for units in hidden:
        layers += [nn.Linear(width, int(units)), nn.Tanh()]
        width = int(units)
    return nn.Sequential(*layers), width


class ActorCritic(nn.Module):
    """SB3's ``MlpPolicy`` network for one ``ppo`` setting (module docstring).

    Args:
        obs_size: the observation's length.
        act_size: the action's length (2: the offset in x and y, times ``max_step_m``).
        net_arch: hidden layers of the actor's and of the critic's MLP.
        encoder: ``mlp`` | ``deepsets`` | ``attention``.
        encoder_units: d of the neighbour encoder.
        layout: :func:`cv2x_marl.policies.encoders.layout_spec` of the env's layout (the neighbour encoders).
        log_std_init: the initial log standard deviation of the Gaussian.
    """

    def __init__(
        self,
        obs_size: int,
        act_size: int = 2,
        net_arch: tuple[int, ...] | list[int] = (128, 128),
        encoder: str = "mlp",
        encoder_units: int = 64,
        layout: dict[str, Any] | None = None,
        log_std_init: float = 0.0,
    ) -> None:
        super().__init__()
        self._spec = {
            "obs_size": int(obs_size),
            "act_size": int(act_size),
            "net_arch": [int(u) for u in net_arch],
            "encoder": str(encoder),
            "encoder_units": int(encoder_units),
            "layout": layout,
            "log_std_init": float(log_std_init),
        }
        self.obs_size = int(obs_size)
        self.encoder: nn.Module | None = None
        width = self.obs_size
        # torch's default initialisation draws from the global generator: it runs on a forked copy of it, so
        # building the network leaves the global state as it was (init_weights sets the weights)
        with torch.random.fork_rng(devices=[]):
            if encoder != "mlp":
                from gymnasium import spaces

                from cv2x_marl.policies.encoders import NeighbourEncoder

                if layout is None:
                    raise ValueError(
                        f"encoder={encoder} needs the env's layout (cv2x_marl.policies.encoders.layout_spec)"
                    )
                box = spaces.Box(-1.0, 1.0, (self.obs_size,))
                self.encoder = NeighbourEncoder(box, layout, pool=encoder, units=int(encoder_units))
                width = 3 * int(encoder_units)
            self.policy_net, pi_width = tanh_mlp(width, net_arch)
            self.value_net, vf_width = tanh_mlp(width, net_arch)
            self.action_net = nn.Linear(pi_width, int(act_size))
            self.value_head = nn.Linear(vf_width, 1)
        self.log_std = nn.Parameter(torch.full((int(act_size),), float(log_std_init)))

    def spec(self) -> dict[str, Any]:
        """The keyword arguments that rebuild this network (plain values)."""
        return dict(self._spec)

    def init_weights(self, generator: torch.Generator) -> None:
        """SB3's orthogonal initialisation (module docstring), every draw from ``generator``."""
        gains: list[tuple[nn.Module | None, float]] = [
            (self.encoder, math.sqrt(2)),
            (self.policy_net, math.sqrt(2)),
            (self.value_net, math.sqrt(2)),
            (self.action_net, 0.01),
            (self.value_head, 1.0),
        ]
        with torch.no_grad():
            for part, gain in gains:
                if part is None:
                    continue
                for module in part.modules():
                    if isinstance(module, nn.Linear):
                        nn.init.orthogonal_(module.weight, gain=gain, generator=generator)
                        if module.bias is not None:
                            module.bias.zero_()

    def features(self, obs: torch.Tensor) -> torch.Tensor:
        """``obs`` [B, obs_size] -> the shared features [B, F]."""
        return obs if self.encoder is None else self.encoder(obs)

    def actor_head(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Features [B, F] -> (``mu`` [B, act_size], standard deviation [B, act_size])."""
        loc = self.action_net(self.policy_net(features))
        return loc, self.log_std.exp().expand_as(loc)

    def critic_head(self, features: torch.Tensor) -> torch.Tensor:
        """Features [B, F] -> the value [B, 1]."""
        return self.value_head(self.value_net(features))

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``obs`` [..., obs_size] -> (``mu``, standard deviation), each [..., act_size]."""
        lead = obs.shape[:-1]
        loc, scale = self.actor_head(self.features(obs.reshape(-1, self.obs_size)))
        return loc.reshape(*lead, -1), scale.reshape(*lead, -1)

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        """``obs`` [..., obs_size] -> the value [..., 1]."""
        lead = obs.shape[:-1]
        return self.critic_head(self.features(obs.reshape(-1, self.obs_size))).reshape(*lead, 1)

    def deterministic(self, obs: torch.Tensor) -> torch.Tensor:
        """The deterministic action ``clip(mu, -1, 1)`` [..., act_size] (SB3's ``predict(deterministic=True)``)."""
        return self(obs)[0].clamp(-1.0, 1.0)
