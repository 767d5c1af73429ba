"""The networks of MAPPO (:mod:`cv2x_marl.rl.mappo`): a shared actor on each agent's observation, a centralised
critic on the env's ``state()``.

* :class:`SharedActor`: one set of weights for every vehicle (parameter sharing; decentralised execution: it
  reads only a vehicle's observation [..., obs_size]). Its features are the flat observation (``encoder:
  mlp``) or the permutation-invariant neighbour features of :class:`cv2x_marl.policies.encoders.NeighbourEncoder`
  (``deepsets`` / ``attention``, 3 d values); an MLP (tanh) maps them to the mean ``mu`` [..., 2] of a Gaussian
  whose standard deviation ``exp(log_std)`` [2] is a free parameter; actions are ``tanh`` of its samples
  (TorchRL's ``TanhNormal``), the deterministic action is ``tanh(mu)``.
* :class:`StateCritic`: an MLP (tanh) on ``state()`` [..., S] -> one value [..., 1] per env step (the reward is the
  team's, the same for every agent).

Both are plain ``torch.nn`` modules built from plain keyword arguments (:meth:`SharedActor.spec`), so a saved
actor (``model.pt``) is rebuilt by :class:`cv2x_marl.policies.mappo.MappoPolicy` without pickled code.
"""

from __future__ import annotations

from typing import Any

try:
    import torch
    from torch import nn
except ImportError as _exc:  # the torchrl (or train) extra is not installed
    from cv2x_marl.extras import missing_extra

    raise missing_extra("torch", "the MAPPO networks (cv2x_marl.policies.mappo_nets)", _exc) from _exc


def mlp(n_in: int, hidden: tuple[int, ...] | list[int], n_out: int, out_gain: float = 1.0) -> nn.Sequential:
    """``n_in`` -> hidden layers (tanh) -> ``n_out`` (linear; its weights scaled by ``out_gain``)."""
    layers: list[nn.Module] = []
    width = n_in
    for units in hidden:
        layers += [nn.Linear(width, int(units)), nn.Tanh()]
        width = int(units)
    head = nn.Linear(width, n_out)
    with torch.no_grad():
        head.weight.mul_(out_gain)
        head.bias.zero_()
    return nn.Sequential(*layers, head)


class SharedActor(nn.Module):
    """The shared actor (module docstring).

    Args:
        obs_size: the observation's length.
        act_size: the action's length (2: the offset in x and y, times ``max_step_m``).
        net: hidden layers of the MLP.
        encoder: ``mlp`` | ``deepsets`` | ``attention``.
        encoder_units: d of the neighbour encoder.
        layout: :func:`cv2x_marl.policies.encoders.layout_spec` of the env's layout (needed by the neighbour encoders).
        log_std_init: the initial ``log_std``.
    """

    def __init__(
        self,
        obs_size: int,
        act_size: int = 2,
        net: tuple[int, ...] | list[int] = (128, 128),
        encoder: str = "mlp",
        encoder_units: int = 64,
        layout: dict[str, Any] | None = None,
        log_std_init: float = -0.5,
    ) -> None:
        super().__init__()
        self._spec = {
            "obs_size": int(obs_size),
            "act_size": int(act_size),
            "net": [int(u) for u in net],
            "encoder": str(encoder),
            "encoder_units": int(encoder_units),
            "layout": layout,
            "log_std_init": float(log_std_init),
        }
        self.obs_size = int(obs_size)
        self.encoder: nn.Module | None = None
        width = self.obs_size
        if encoder != "mlp":
            from gymnasium import spaces

            from cv2x_marl.policies.encoders import NeighbourEncoder

            if layout is None:
                raise ValueError(f"encoder={encoder} needs the env's layout (cv2x_marl.policies.encoders.layout_spec)")
            box = spaces.Box(-1.0, 1.0, (self.obs_size,))
            self.encoder = NeighbourEncoder(box, layout, pool=encoder, units=int(encoder_units))
            width = 3 * int(encoder_units)
        self.mu = mlp(width, net, int(act_size), out_gain=0.01)
        self.log_std = nn.Parameter(torch.full((int(act_size),), float(log_std_init)))

    def spec(self) -> dict[str, Any]:
        """The keyword arguments that rebuild this actor (plain values)."""
        return dict(self._spec)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``obs`` [..., obs_size] -> (``mu`` [..., act_size], ``scale`` [..., act_size])."""
        lead = obs.shape[:-1]
        x = obs.reshape(-1, self.obs_size)
        if self.encoder is not None:
            x = self.encoder(x)
        loc = self.mu(x).reshape(*lead, -1)
        return loc, self.log_std.exp().expand_as(loc)

    def deterministic(self, obs: torch.Tensor) -> torch.Tensor:
        """The deterministic action ``tanh(mu)`` [..., act_size] in [-1, 1]."""
        return torch.tanh(self(obs)[0])


class StateCritic(nn.Module):
    """The centralised critic: ``state()`` [..., S] -> the value [..., 1] of the env step."""

    def __init__(self, state_size: int, net: tuple[int, ...] | list[int] = (256, 256)) -> None:
        super().__init__()
        self.state_size = int(state_size)
        self.v = mlp(self.state_size, net, 1)

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return self.v(state)
