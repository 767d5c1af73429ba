"""Permutation-invariant neighbour encoders for SB3 policies (``ppo.encoder: deepsets | attention``).

An observation (:mod:`cv2x_marl.env.observation`) is a flat vector: per neighbour k (nearest first) a block of
features, spread over up to two places (the version-0 block ``[7k, 7k + 7)``, then version 3's measured block
``[7K + 5 + 10k, ... + 10)``, version 4's ``[7K + 5 + 8k, ... + 8)`` or versions 1-2's model / true success
``[7K + 5 + k]``, ``[8K + 5 + k]``), and the own entries (the version-0 own block, the version's own block, the
driving entries). :func:`split_indices` derives from an :class:`~cv2x_marl.env.observation.ObservationLayout`
(through its own accessors, applied to the index vector ``0 .. size - 1``) the index table ``[K, F]`` of each
neighbour's features and the indices ``[O]`` of every other entry (the own entries), so the encoder reads exactly
what the env writes.

:class:`NeighbourEncoder` (an SB3 ``BaseFeaturesExtractor``) gathers the rows ``x_k`` ([B, K, F]) and the own
entries ``o`` ([B, O]), encodes each neighbour with one shared MLP ``h_k = phi(x_k)`` and the own entries with
``g = rho(o)``, and pools over the neighbours (Zaheer et al., *Deep Sets*, NeurIPS 2017):

* ``deepsets``: ``[g, mean_k h_k, max_k h_k]``;
* ``attention``: one head with the own entries as the query (scaled dot product, Vaswani et al. 2017),
  ``a = sum_k softmax_k(q . key_k / sqrt(d)) value_k`` with ``q = W_q g``, ``key_k = W_k h_k``,
  ``value_k = W_v h_k``: ``[g, a, mean_k h_k]``.

Both are invariant to the order of the neighbour blocks (``tests/rl/test_encoders.py`` permutes them). The
policy's and value's ``net_arch`` MLPs then act on these ``3 d`` features (``d = ppo.encoder_units``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

try:
    import torch
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
    from torch import nn
except ImportError as _exc:  # the train extra is not installed
    from cv2x_marl.extras import missing_extra

    raise missing_extra(getattr(_exc, "name", None) or "torch", "the neighbour encoders (cv2x_marl.rl)", _exc) from _exc

from cv2x_marl.env.observation import ObservationLayout

#: the pooling of :class:`NeighbourEncoder` (``ppo.encoder`` besides ``mlp``, SB3's flat MLP)
POOLS = ("deepsets", "attention")
#: the keys of a layout spec (:func:`layout_spec`): what decides where the entries sit
SPEC_KEYS = ("n_neighbours", "version", "privileged", "drive")


def layout_spec(layout: ObservationLayout) -> dict[str, Any]:
    """The parts of ``layout`` that place the entries (plain values: saved with the model's policy kwargs)."""
    return {
        "n_neighbours": int(layout.n_neighbours),
        "version": int(layout.version),
        "privileged": bool(layout.privileged),
        "drive": bool(layout.drive),
    }


def _layout_of(spec: dict[str, Any]) -> ObservationLayout:
    if not isinstance(spec, dict) or sorted(spec) != sorted(SPEC_KEYS):
        raise ValueError(f"layout must be a mapping with the keys {', '.join(SPEC_KEYS)} (layout_spec), got {spec!r}")
    # the scales do not move any entry; 1.0 stands for them
    return ObservationLayout(
        int(spec["n_neighbours"]), 1.0, 1.0, 1.0,
        version=int(spec["version"]), privileged=bool(spec["privileged"]), drive=bool(spec["drive"]),
    )  # fmt: skip


def split_indices(layout: ObservationLayout | dict[str, Any]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Where each neighbour's features and the own entries sit in the flat observation.

    Args:
        layout: the env's :class:`ObservationLayout` (``env.layout``) or its :func:`layout_spec`.

    Returns:
        ``(rows, own)``: ``rows`` [K, F] the index of feature f of neighbour k (the version-0 block's 7
        features, then version 3's 10 (version 4's 8) measured ones, or versions 1-2's model (and true) success);
        ``own`` [O] every other index, in order (``K F + O`` = the observation's size).
    """
    lay = _layout_of(layout) if isinstance(layout, dict) else layout
    idx = np.arange(lay.size, dtype=np.float64)[None, :]  # [1, size]: each accessor returns the indices it reads
    parts = [lay.neighbours(idx)[0]]  # [K, 7]
    if lay.version in (3, 4):
        parts.append(lay.measured(idx)[0])  # [K, 10] (version 4: [K, 8])
    elif lay.version in (1, 2):
        parts.append(lay.model_success(idx)[0][:, None])
        if lay.privileged:
            parts.append(lay.true_success(idx)[0][:, None])
    rows = np.concatenate(parts, axis=1).astype(np.int64)
    own = np.setdiff1d(np.arange(lay.size, dtype=np.int64), rows.ravel())
    assert rows.size + own.size == lay.size and np.unique(rows).size == rows.size
    return rows, own


def _mlp(n_in: int, units: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, units), nn.ReLU(), nn.Linear(units, units), nn.ReLU())


class NeighbourEncoder(BaseFeaturesExtractor):
    """Deep-sets or attention features of a flat observation (module docstring).

    Args:
        observation_space: the env's Box of shape ``(layout.size,)``.
        layout: :func:`layout_spec` of the env's layout (``make_ppo`` passes it).
        pool: ``deepsets`` or ``attention``.
        units: d, the width of the neighbour and own encoders.

    Raises:
        ValueError: an observation size other than the layout's, an unknown pool, or ``units`` < 1.
    """

    def __init__(self, observation_space: Any, layout: dict[str, Any], pool: str = "deepsets", units: int = 64):
        if pool not in POOLS:
            raise ValueError(f"pool must be one of {', '.join(POOLS)}, got {pool!r}")
        if isinstance(units, bool) or not isinstance(units, int) or units < 1:
            raise ValueError(f"units must be an integer >= 1, got {units!r}")
        rows, own = split_indices(layout)
        shape = tuple(observation_space.shape)
        size = rows.size + own.size
        if shape != (size,):
            raise ValueError(
                f"observation_space has shape {shape}, but the layout {layout} has {size} entries "
                f"({rows.shape[0]} neighbours x {rows.shape[1]} features + {own.size} own); build the encoder "
                "from the env the policy acts in (env.layout)"
            )
        super().__init__(observation_space, features_dim=3 * units)
        self.pool = pool
        self.units = units
        self.n_neighbours, self.n_features = rows.shape
        self.rows: torch.Tensor
        self.own: torch.Tensor
        self.register_buffer("rows", torch.as_tensor(rows.ravel()), persistent=False)
        self.register_buffer("own", torch.as_tensor(own), persistent=False)
        self.phi = _mlp(self.n_features, units)
        self.rho = _mlp(own.size, units)
        if pool == "attention":
            self.query = nn.Linear(units, units, bias=False)
            self.key = nn.Linear(units, units, bias=False)
            self.value = nn.Linear(units, units, bias=False)

    def split(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``obs`` [B, size] -> (neighbour rows [B, K, F], own entries [B, O])."""
        nb = obs.index_select(-1, self.rows).reshape(obs.shape[0], self.n_neighbours, self.n_features)
        return nb, obs.index_select(-1, self.own)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        """[B, size] -> [B, 3 d] features."""
        nb, own = self.split(observations)
        h = self.phi(nb)  # [B, K, d]
        g = self.rho(own)  # [B, d]
        mean = h.mean(dim=1)
        if self.pool == "deepsets":
            return torch.cat((g, mean, h.amax(dim=1)), dim=1)
        q = self.query(g).unsqueeze(1)  # [B, 1, d]
        scores = (self.key(h) * q).sum(-1) / float(np.sqrt(self.units))  # [B, K]
        weights = torch.softmax(scores, dim=1).unsqueeze(-1)
        return torch.cat((g, (weights * self.value(h)).sum(dim=1), mean), dim=1)


def encoder_policy_kwargs(pool: str, units: int, layout: ObservationLayout | None) -> dict[str, Any]:
    """SB3 ``policy_kwargs`` entries that put :class:`NeighbourEncoder` in front of the policy and value MLPs
    (``make_ppo`` with ``ppo.encoder`` = ``pool``); plain values only, so the model's zip reloads them.

    Raises:
        ValueError: no layout (the encoder reads the neighbour blocks where the env's layout puts them).
    """
    if layout is None:
        raise ValueError(f"ppo.encoder={pool} needs the env's observation layout (make_ppo(..., layout=env.layout))")
    return {
        "features_extractor_class": NeighbourEncoder,
        "features_extractor_kwargs": {"layout": layout_spec(layout), "pool": pool, "units": units},
    }
