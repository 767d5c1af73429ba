"""The environments of every env id (one :class:`MobilityEnv` per id's options) and their factories.

    make_parallel_env(env_id, **kw) / make_aec_env(env_id, **kw)   any registered id
    parallel_env(**kw)  the ParallelEnv of ``cv2x/Mobility-v0`` (:class:`MobilityEnv`)
    raw_env(**kw)       its AEC version (``parallel_to_aec_wrapper``), unwrapped
    env(**kw)           the AEC version with PettingZoo's standard wrapper (order enforcing)

    parallel_env_v1 / env_v1   the same for ``cv2x/Mobility-v1`` (observation version 1, improvement rewards)
    parallel_env_v2 / env_v2   the same for ``cv2x/Mobility-v2`` (observation version 2: the sensing plan)
    parallel_env_v3 / env_v3   the same for ``cv2x/Mobility-v3`` (plan-free observation version 3, shadowing field)
    parallel_env_cooperative / env_cooperative   ``cv2x/Cooperative-v0`` (every vehicle moves, team reward)
    parallel_env_cooperative_v1 / env_cooperative_v1   ``cv2x/Cooperative-v1`` (the same; the AEC API in the
                                                 order of the transmission subframes, the moves announced before)
    parallel_env_traffic / env_traffic           ``cv2x/Traffic-v0`` (vehicles drive; vehicle 0, or with
                                                 ``movers=None`` every vehicle, commands its speed and lane)
    parallel_env_traffic_v1 / env_traffic_v1     ``cv2x/Traffic-v1`` (the same, observation version 4: measured)

The ids (one table, :data:`cv2x_marl.env.registry.SPECS`), the factories (``functools.partial`` of
:func:`make_parallel_env` / :func:`make_aec_env` on the id, :data:`~cv2x_marl.env.registry.FACTORIES`) and their
registration are :mod:`cv2x_marl.env.registry`'s: ``import
cv2x_marl`` registers ``cv2x/Mobility-v0`` .. ``-v3``, ``cv2x/Cooperative-v0`` / ``-v1``, ``cv2x/Traffic-v0`` / ``-v1``
(``pettingzoo.make("parallel", ...)`` and ``pettingzoo.make("aec", ...)``) and the single-agent Gymnasium
envs ``cv2x/SingleMover-v0`` .. ``-v3`` and ``cv2x/Traffic-v0``. :class:`MobilityEnv` and
:class:`ObservationLayout` are imported on first use, so that importing the package (the registry, for
the CLI's ``--env`` choices) does not import the env itself (about 0.9 s measured).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from cv2x_marl.env.registry import FACTORIES, make_aec_env, make_parallel_env, raw_env

if TYPE_CHECKING:
    from cv2x_marl.env.mobility_env import MobilityEnv
    from cv2x_marl.env.observation import ObservationLayout

#: names imported on first use, and their modules
_LAZY = {"MobilityEnv": "cv2x_marl.env.mobility_env", "ObservationLayout": "cv2x_marl.env.observation"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    if name in FACTORIES:  # parallel_env, env_v3, parallel_env_cooperative, ... (registry.FACTORIES)
        return FACTORIES[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["MobilityEnv", "ObservationLayout", "make_aec_env", "make_parallel_env", "raw_env", *sorted(FACTORIES)]
