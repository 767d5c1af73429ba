"""PettingZoo environment for controlled mobility (``cv2x_mobility_v0``) and its factories.

    parallel_env(**kw)  the ParallelEnv (:class:`MobilityEnv`)
    raw_env(**kw)       its AEC version (``parallel_to_aec_wrapper``), unwrapped
    env(**kw)           the AEC version with PettingZoo's standard wrapper (order enforcing)

    parallel_env_v1 / env_v1   the same for ``cv2x/Mobility-v1`` (observation version 1, improvement rewards)
    parallel_env_v2 / env_v2   the same for ``cv2x/Mobility-v2`` (observation version 2: the sensing plan)

``import cv2x_marl`` registers ``cv2x/Mobility-v0``, ``-v1`` and ``-v2`` (``pettingzoo.make("parallel", ...)``
and ``pettingzoo.make("aec", ...)``) and the single-agent Gymnasium envs ``cv2x/SingleMover-v0``
``-v1`` and ``-v2``.
"""

from __future__ import annotations

from typing import Any

from pettingzoo.utils.conversions import parallel_to_aec, parallel_to_aec_wrapper

from cv2x_marl.env.mobility_env import MobilityEnv, mobility_v1, mobility_v2
from cv2x_marl.env.observation import ObservationLayout


def parallel_env(**kwargs: Any) -> MobilityEnv:
    """The ParallelEnv; keyword arguments as :class:`MobilityEnv`."""
    return MobilityEnv(**kwargs)


def parallel_env_v1(**kwargs: Any) -> MobilityEnv:
    """``cv2x/Mobility-v1``: the ParallelEnv with observation version 1 and improvement rewards."""
    return mobility_v1(**kwargs)


def env_v1(**kwargs: Any) -> Any:
    """AEC version of ``cv2x/Mobility-v1`` with the order-enforcing wrapper."""
    return parallel_to_aec(mobility_v1(**kwargs))


def parallel_env_v2(**kwargs: Any) -> MobilityEnv:
    """``cv2x/Mobility-v2``: the ParallelEnv with observation version 2 and improvement rewards."""
    return mobility_v2(**kwargs)


def env_v2(**kwargs: Any) -> Any:
    """AEC version of ``cv2x/Mobility-v2`` with the order-enforcing wrapper."""
    return parallel_to_aec(mobility_v2(**kwargs))


def raw_env(**kwargs: Any) -> Any:
    """AEC version without wrappers."""
    return parallel_to_aec_wrapper(MobilityEnv(**kwargs))


def env(**kwargs: Any) -> Any:
    """AEC version with the order-enforcing wrapper (what ``parallel_to_aec`` returns)."""
    return parallel_to_aec(MobilityEnv(**kwargs))


__all__ = [
    "MobilityEnv",
    "ObservationLayout",
    "env",
    "env_v1",
    "env_v2",
    "parallel_env",
    "parallel_env_v1",
    "parallel_env_v2",
    "raw_env",
]
