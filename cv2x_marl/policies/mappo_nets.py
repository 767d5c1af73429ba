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

import numpy as np

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


#: the actor kinds of a MAPPO ``model.pt`` (``actor_kind``; files without the key hold a ``gaussian`` one)
ACTOR_KINDS = ("gaussian", "categorical")
#: what :class:`MaskedActor` reads: the flat observation (``mlp``) or each candidate's entries (``candidates``)
MASKED_ENCODERS = ("mlp", "candidates", "candidates-attention")


def candidate_spec(layout: Any) -> dict[str, int]:
    """Where the candidate block and the ``decides`` flag sit in an observation of version 5 (plain ints: saved with
    the actor's keyword arguments, so the file rebuilds it without the env).

    Args:
        layout: the env's :class:`~cv2x_marl.env.observation.ObservationLayout` (``env.layout``), version 5.

    Returns:
        ``start`` (index of the first candidate's first entry), ``count`` (candidates K), ``features`` (entries F per
        candidate, the first ``valid``), ``decides`` (index of the own ``decides`` entry) and ``size``.

    Raises:
        ValueError: a layout without a candidate block.
    """
    from cv2x_marl.env.observation import (
        CANDIDATE_NAMES,
        FEATURES_CANDIDATE,
        N_CANDIDATES,
        OWN_V4,
        OWN_V5_EXTRA,
    )

    if int(layout.version) != 5:
        raise ValueError(
            f"a masked resource actor needs observation version 5 (the candidate block), got {layout.version}"
        )
    assert CANDIDATE_NAMES[0] == "valid" and OWN_V5_EXTRA[0] == "decides"
    decides = int(layout.own_v1_offset + OWN_V4)
    return {
        "start": decides + len(OWN_V5_EXTRA),
        "count": int(N_CANDIDATES),
        "features": int(FEATURES_CANDIDATE),
        "decides": decides,
        "size": int(layout.size),
    }


class MaskedActor(nn.Module):
    """A shared actor for a masked ``Discrete(n)`` action (``cv2x/Resource-v0``: an entry of the candidate list).

    It gives the logits [..., n] of a categorical distribution; the entries the mask rules out get ``-inf`` (TorchRL's
    ``MaskedCategorical`` in training, :meth:`deterministic` here). The mask of an observation is
    :meth:`mask_of`: the candidate's ``valid`` entry where the own ``decides`` entry is set, which equals the env's
    ``action_masks()`` row (tested).

    * ``encoder: mlp``: an MLP (tanh) on the flat observation -> n logits.
    * ``encoder: candidates``: one network shared over the candidates (a pointer-style scorer): the context
      ``g = rho(o)`` of every entry outside the candidate block (``o``: the neighbour blocks and the own entries),
      each candidate's embedding ``e_c = phi([x_c, c / n])`` from its F entries and its rank in the list, and the
      logit ``head([e_c, g, mean_{valid c'} e_c'])`` (tanh layers of ``net``). The same function scores every entry,
      so what it learns about one rank carries to the others.

    Args:
        obs_size: the observation's length.
        n_actions: n (the list's length).
        net: hidden layers of the MLP (``mlp``) or of the candidate head (``candidates``).
        encoder: ``mlp`` | ``candidates``.
        encoder_units: d of ``rho`` and ``phi`` (``candidates``).
        candidates: :func:`candidate_spec` of the env's layout.
        dither: the weight of the observation's own Gumbel noise in :meth:`deterministic` (0: the plain argmax). A
            plain argmax breaks near-ties the same way for every vehicle that senses alike, so vehicles pile onto
            the same resources (the herding the standard's random draw avoids: ``lowest-rssi``); 1 makes the
            choice a sample of the categorical drawn with the observation as its seed (docs/rl.md).
    """

    kind = "categorical"

    def __init__(
        self,
        obs_size: int,
        n_actions: int,
        net: tuple[int, ...] | list[int] = (128, 128),
        encoder: str = "candidates",
        encoder_units: int = 64,
        candidates: dict[str, int] | None = None,
        dither: float = 0.0,
    ) -> None:
        super().__init__()
        if encoder not in MASKED_ENCODERS:
            raise ValueError(f"encoder must be one of {', '.join(MASKED_ENCODERS)} for a masked actor, got {encoder!r}")
        if candidates is None:
            raise ValueError("a masked actor needs candidates=candidate_spec(env.layout) (where its mask is read)")
        spec = {k: int(v) for k, v in dict(candidates).items()}
        if spec.get("size") != int(obs_size) or spec.get("count") != int(n_actions):
            raise ValueError(f"candidates {spec} do not fit observations of {obs_size} entries and {n_actions} actions")
        self._spec = {
            "obs_size": int(obs_size),
            "n_actions": int(n_actions),
            "net": [int(u) for u in net],
            "encoder": str(encoder),
            "encoder_units": int(encoder_units),
            "candidates": spec,
            "dither": float(dither),
        }
        self.obs_size, self.n_actions, self.encoder = int(obs_size), int(n_actions), str(encoder)
        k, f, start = spec["count"], spec["features"], spec["start"]
        self.n_features = f
        block = torch.arange(start, start + k * f)
        self.block: torch.Tensor
        self.context: torch.Tensor
        self.valid: torch.Tensor
        self.rank: torch.Tensor
        self.register_buffer("block", block, persistent=False)
        keep = torch.ones(self.obs_size, dtype=torch.bool)
        keep[block] = False
        self.register_buffer("context", torch.nonzero(keep).flatten(), persistent=False)
        self.register_buffer("valid", block.reshape(k, f)[:, 0].clone(), persistent=False)
        self.register_buffer("rank", (torch.arange(k, dtype=torch.float32) / k).reshape(k, 1), persistent=False)
        self.decides = spec["decides"]
        if not (np.isfinite(dither) and dither >= 0):
            raise ValueError(f"dither must be a number >= 0, got {dither!r}")
        self.dither = float(dither)
        d = int(encoder_units)
        if encoder == "mlp":
            self.logits_net = mlp(self.obs_size, net, self.n_actions, out_gain=0.01)
        else:
            self.rho = mlp(int(self.context.numel()), (d,), d)
            self.phi = mlp(f + 1, (d,), d)
            self.head = mlp(3 * d, net, 1, out_gain=0.01)
        self.attention: nn.MultiheadAttention | None = None
        if encoder == "candidates-attention":  # the entries see each other (which share a subframe, ...)
            self.attention = nn.MultiheadAttention(d, num_heads=4 if d % 4 == 0 else 1, batch_first=True)

    def spec(self) -> dict[str, Any]:
        """The keyword arguments that rebuild this actor (plain values)."""
        spec: dict[str, Any] = dict(self._spec)
        spec["candidates"] = dict(spec["candidates"])
        return spec

    def mask_of(self, obs: torch.Tensor) -> torch.Tensor:
        """[..., n] bool: the valid entries of a deciding agent's list (none without a decision)."""
        valid = obs.index_select(-1, self.valid) > 0.5
        return valid & (obs[..., self.decides : self.decides + 1] > 0.5)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """``obs`` [..., obs_size] -> logits [..., n] (unmasked)."""
        lead = obs.shape[:-1]
        x = obs.reshape(-1, self.obs_size)
        if self.encoder == "mlp":
            return self.logits_net(x).reshape(*lead, self.n_actions)
        b, k = x.shape[0], self.n_actions
        cand = x.index_select(-1, self.block).reshape(b, k, self.n_features)
        e = self.phi(torch.cat((cand, self.rank.expand(b, k, 1)), dim=-1))  # [B, K, d]
        if self.attention is not None:
            invalid = cand[..., 0] <= 0.5
            invalid = invalid & ~invalid.all(-1, keepdim=True)  # no list: attend everywhere (its logits go unused)
            e = e + self.attention(e, e, e, key_padding_mask=invalid, need_weights=False)[0]
        g = self.rho(x.index_select(-1, self.context))  # [B, d]
        w = cand[..., :1]  # the valid entries
        pooled = (e * w).sum(1) / w.sum(1).clamp(min=1.0)
        both = torch.cat((g, pooled), dim=-1).unsqueeze(1).expand(b, k, -1)
        return self.head(torch.cat((e, both), dim=-1)).reshape(*lead, k)

    def deterministic(self, obs: torch.Tensor) -> torch.Tensor:
        """The deterministic choice [...] (int64; 0 where the mask is all zero: no decision): the argmax over the
        valid entries of the logits, plus ``dither`` times :func:`observation_gumbel` of each row when ``dither`` > 0
        (with ``dither = 1`` the Gumbel-max trick: the choice is distributed over observations as a sample of the
        trained categorical, yet a function of the row alone)."""
        mask = self.mask_of(obs)
        logits = self(obs)
        if self.dither > 0:
            flat = obs.reshape(-1, self.obs_size).detach().cpu().numpy()
            noise = np.stack([observation_gumbel(row, self.n_actions) for row in flat]) if flat.size else None
            if noise is not None:
                logits = logits + self.dither * torch.from_numpy(noise).to(logits.dtype).reshape(logits.shape)
        logits = logits.masked_fill(~mask, float("-inf"))
        best = logits.argmax(-1)
        return torch.where(torch.isfinite(logits.amax(-1)), best, torch.zeros_like(best))


#: the grid an observation is rounded to before :func:`observation_gumbel` hashes it (a last-bit difference of an
#: entry then changes the noise only where it crosses a grid line)
DITHER_GRID = 2.0**-8


def observation_gumbel(obs: np.ndarray, n: int) -> np.ndarray:
    """``n`` standard Gumbel values [n] (float64) drawn from a generator seeded with a hash of the observation ``obs``
    (rounded to :data:`DITHER_GRID`): pseudo-random, different for different observations, and the same for the same
    observation whatever else is acting (the batch-invariance rule of :mod:`cv2x_marl.policies.base`)."""
    import hashlib

    q = np.round(np.asarray(obs, dtype=np.float64) / DITHER_GRID).astype(np.int64)
    digest = hashlib.blake2b(q.tobytes(), digest_size=16).digest()
    u = np.random.default_rng(int.from_bytes(digest, "little")).random(n)
    return np.asarray(-np.log(-np.log(np.clip(u, 1e-300, 1.0 - 1e-16))), dtype=np.float64)


class ObservationCritic(nn.Module):
    """A per-agent critic: an MLP (tanh) on one agent's input [..., n_in] -> its value [..., 1]; the input is the
    agent's own observation (``critic: observation``: independent PPO) or ``state()`` followed by it (``critic: state``
    with individual rewards: the agent-specific global state of Yu et al. 2022)."""

    def __init__(self, n_in: int, net: tuple[int, ...] | list[int] = (256, 256)) -> None:
        super().__init__()
        self.n_in = int(n_in)
        self.v = mlp(self.n_in, net, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.v(x)
