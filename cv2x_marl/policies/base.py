"""One ``Policy`` protocol for every mover: observations in, actions out.

A policy maps the env's per-agent observations (dict of float32 vectors, see
:mod:`cv2x_marl.env.observation`) to per-agent actions in ``[-1, 1]^2`` (times the env's
``max_step_m``). ``reset(seed)`` is called at the start of every episode, so stochastic policies
are reproducible per episode.

Batch invariance (every learned policy: :class:`BatchPolicy` and the PPO and MAPPO policies built on it): an
agent's action is a function of its own observation (and its own recurrent state) alone, bit for bit, whatever
other agents or episodes are acting at the same time. The network is run on one agent's row at a time (a batch
of one, ``[1, obs_dim]``): CPU matrix kernels (MKL, oneDNN, OpenBLAS) may round a row differently depending on
the rows it is batched with (a matrix-vector kernel for one row, blocked matrix-matrix kernels for several), and
in a deterministic episode a last-bit difference in one action can send the episode elsewhere. The same row
then gives the same action whether it is acted on alone, with the rest of its episode's agents, or stacked
among any others (tested). What remains machine-dependent is the machine itself: another CPU or library
version may round the batch of one differently too.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

Observations = dict[str, NDArray[np.float32]]
Actions = dict[str, NDArray[np.float32]]


@runtime_checkable
class Policy(Protocol):
    """What every mover implements."""

    name: str

    def reset(self, seed: int | None = None) -> None:
        """Start an episode (seeds any randomness)."""

    def act(self, observations: Observations) -> Actions:
        """Actions for the agents present in ``observations``."""
        ...


class StaticPolicy:
    """Never moves: the baseline every gain is measured against."""

    name = "static"

    def reset(self, seed: int | None = None) -> None:
        return None

    def act(self, observations: Observations) -> Actions:
        return {a: np.zeros(2, dtype=np.float32) for a in observations}


class RandomPolicy:
    """Uniform actions in the box, from its own generator (seeded per episode)."""

    name = "random"

    def __init__(self, seed: int | None = None) -> None:
        self.rng = np.random.default_rng(seed)

    def reset(self, seed: int | None = None) -> None:
        if seed is not None:
            self.rng = np.random.default_rng(np.random.SeedSequence([seed, 0xA11CE]))

    def act(self, observations: Observations) -> Actions:
        acts = self.rng.uniform(-1.0, 1.0, size=(len(observations), 2)).astype(np.float32)
        return dict(zip(observations, acts, strict=True))


@contextlib.contextmanager
def one_torch_thread() -> Iterator[None]:
    """torch's intra-op threads set to one for the block, and restored after (torch is imported here: call it
    only where torch is loaded). A batch of one gains nothing from threads and, on a loaded machine, loses much
    time to their synchronisation; the actions of the shipped models were measured equal with one or two."""
    import torch

    threads = torch.get_num_threads()
    if threads == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def act_rows(act_fn: Callable[[NDArray[np.float32]], object], obs: NDArray[np.float32]) -> NDArray[np.float32]:
    """``act_fn`` on each row of ``obs`` alone (a batch of one), the module's batch-invariance rule.

    Args:
        act_fn: observations [1, obs_dim] (float32) -> actions [1, act_dim] (or [act_dim]).
        obs: [n_rows, obs_dim] float32.

    Returns:
        [n_rows, act_dim] float32: row i is ``act_fn(obs[i : i + 1])``, bit for bit, whatever the other rows.
    """
    # one call per row: the rule itself (a batched call is what may round a row differently)
    rows = [np.asarray(act_fn(obs[i : i + 1]), dtype=np.float32).reshape(1, -1) for i in range(obs.shape[0])]
    return np.concatenate(rows) if rows else np.zeros((0, 2), dtype=np.float32)


class BatchPolicy:
    """Any actor function as a policy, deterministic and stateless, one agent's row at a time.

    For movers trained outside the package (RLlib, TorchRL, your own torch module): evaluate them
    with :func:`cv2x_marl.experiments.evaluate.evaluate` on the same episodes as every baseline.

    ``act_fn`` is called once per agent present, on that agent's observation alone (``[1, obs_dim]``), so an
    agent's action never depends on which other agents are in the step (the module's batch-invariance rule).
    Pass ``row_by_row=False`` to call it once on all agents (``[n_agents, obs_dim]``) instead: faster, and
    exact only for a function whose rows are computed independently of each other bit for bit (not a torch or
    numpy matrix product on CPU: its kernels may round a row differently in a larger batch).

    Args:
        act_fn: observations [n, obs_dim] (float32, in the order of the observation dict; n = 1 by default)
            -> actions [n, 2] in [-1, 1].
        name: the name results are reported under.
        row_by_row: call ``act_fn`` on one agent's row at a time (default) or on all agents at once.
    """

    def __init__(
        self, act_fn: Callable[[NDArray[np.float32]], object], name: str = "batch", row_by_row: bool = True
    ) -> None:
        self.act_fn = act_fn
        self.name = name
        self.row_by_row = bool(row_by_row)

    def reset(self, seed: int | None = None) -> None:
        return None

    def act(self, observations: Observations) -> Actions:
        agents = list(observations)
        if not agents:
            return {}
        obs = np.stack([observations[a] for a in agents]).astype(np.float32, copy=False)
        if self.row_by_row:
            acts = act_rows(self.act_fn, obs).reshape(len(agents), 2)
        else:
            acts = np.asarray(self.act_fn(obs), dtype=np.float32).reshape(len(agents), 2)
        return dict(zip(agents, acts, strict=True))
