"""The env ids, their versions, the factories behind them and their registration, in one place.

Two families of four versions each, and the cooperative task (the defaults of each are
:data:`cv2x_marl.env.options.VERSION_DEFAULTS`):

    cv2x/Mobility-vN      PettingZoo, every mover an agent (:class:`~cv2x_marl.env.mobility_env.MobilityEnv`)
    cv2x/SingleMover-vN   Gymnasium, vehicle 0 the only mover (:mod:`cv2x_marl.env.single`); vectorised
                          by :mod:`cv2x_marl.env.vector` (``gymnasium.make_vec(..., "vector_entry_point")``)
    cv2x/Cooperative-v0   PettingZoo, every vehicle moves for the team objective (v3 observations)
    cv2x/Traffic-v0       Gymnasium, vehicles drive (lane model), vehicle 0 commands its speed and lane
                          (:class:`~cv2x_marl.env.single.TrafficEnv`); also PettingZoo
                          (:class:`~cv2x_marl.env.traffic_parallel.TrafficParallelEnv`: every vehicle an agent,
                          vehicle 0 drives, ``movers=None``: every vehicle drives)
    cv2x/Traffic-v1       Traffic-v0 observing what the mover measured on the road (observation version 4:
                          RSRP, SCI resources, own SPS state; :class:`~cv2x_marl.env.single.TrafficEnvV1`);
                          also PettingZoo (:class:`~cv2x_marl.env.traffic_parallel.TrafficParallelEnvV1`)

``import cv2x_marl`` calls :func:`register_envs`: the ids are registered at once in whichever of
Gymnasium / PettingZoo is already imported, else when it is imported (an import hook), so importing
``cv2x_marl`` (and starting the CLI) imports neither (about 0.2 s). Entry points are import strings,
so a fresh process (a Ray worker, a subprocess) resolves the Gymnasium ids with
``gymnasium.make("cv2x_marl:cv2x/SingleMover-v2")``, which imports the package first; PettingZoo has
no such syntax: frameworks take the factories (:func:`parallel_env`, :func:`parallel_env_v1` ..
:func:`parallel_env_v3`, :func:`parallel_env_cooperative`, :func:`parallel_env_traffic`, re-exported by
:mod:`cv2x_marl.env`) instead.

This module imports only the standard library at its top, so the CLI reads :data:`ENV_IDS` for its
``--env`` choices without importing the env (about 0.9 s measured: PettingZoo, numba, the simulator);
the factories import :mod:`cv2x_marl.env.mobility_env` when called.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import types
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from cv2x_marl.env.mobility_env import MobilityEnv

#: the env versions (observation version, reward form: :data:`~cv2x_marl.env.mobility_env.VERSION_DEFAULTS`)
VERSIONS = ("v0", "v1", "v2", "v3")
#: the PettingZoo ids (every mover an agent)
MOBILITY_IDS = tuple(f"cv2x/Mobility-{v}" for v in VERSIONS)
#: the Gymnasium ids (vehicle 0 the only mover)
SINGLE_MOVER_IDS = tuple(f"cv2x/SingleMover-{v}" for v in VERSIONS)
#: the cooperative task (PettingZoo; every vehicle moves, team reward)
COOPERATIVE_IDS = ("cv2x/Cooperative-v0",)
#: the traffic task (Gymnasium and PettingZoo; vehicle 0 drives with speed and lane commands), and its
#: variant observing what the mover measured
TRAFFIC_IDS = ("cv2x/Traffic-v0", "cv2x/Traffic-v1")
#: every id, oldest version first (the CLI lists them newest first: ``ENV_IDS[::-1]``)
ENV_IDS = (
    *(i for pair in zip(MOBILITY_IDS, SINGLE_MOVER_IDS, strict=True) for i in pair),
    *COOPERATIVE_IDS,
    *TRAFFIC_IDS,
)
#: the id commands run when none is given
DEFAULT_ENV_ID = "cv2x/SingleMover-v2"
#: Gymnasium classes per version: (entry point in :mod:`cv2x_marl.env.single`, vector entry point
#: in :mod:`cv2x_marl.env.vector`)
_GYM_CLASSES = {
    "v0": ("SingleMoverEnv", "SingleMoverVectorEnv"),
    "v1": ("SingleMoverEnvV1", "SingleMoverVectorEnvV1"),
    "v2": ("SingleMoverEnvV2", "SingleMoverVectorEnvV2"),
    "v3": ("SingleMoverEnvV3", "SingleMoverVectorEnvV3"),
}
#: the Gymnasium classes of the traffic ids (in :mod:`cv2x_marl.env.single`)
_TRAFFIC_CLASSES = {"cv2x/Traffic-v0": "TrafficEnv", "cv2x/Traffic-v1": "TrafficEnvV1"}
#: PettingZoo ids -> the suffix of their factories in :mod:`cv2x_marl.env` (``parallel_env{suffix}``, ``env{suffix}``)
_PETTINGZOO_SUFFIX = {
    **{i: ("" if v == "v0" else f"_{v}") for v, i in zip(VERSIONS, MOBILITY_IDS, strict=True)},
    "cv2x/Cooperative-v0": "_cooperative",
    "cv2x/Traffic-v0": "_traffic",
    "cv2x/Traffic-v1": "_traffic_v1",
}


def env_version(env_id: str) -> str:
    """The key of a registered id's defaults in :data:`~cv2x_marl.env.options.VERSION_DEFAULTS` (``v0`` ..
    ``v3``; ``cooperative-v0`` for ``cv2x/Cooperative-v0``, ``traffic-v0`` / ``traffic-v1`` for ``cv2x/Traffic-v0`` /
    ``-v1``); unknown
    ids are refused with the list."""
    if env_id not in ENV_IDS:
        raise ValueError(f"unknown env id {env_id!r}; ids: {', '.join(ENV_IDS)}")
    if env_id in COOPERATIVE_IDS:
        return "cooperative-" + env_id.rsplit("-", 1)[1]
    if env_id in TRAFFIC_IDS:
        return "traffic-" + env_id.rsplit("-", 1)[1]
    return env_id.rsplit("-", 1)[1]


def make_parallel_env(env_id: str, **kwargs: Any) -> MobilityEnv:
    """The parallel env behind a registered id with its version's defaults (SingleMover: only
    vehicle 0 moves; Traffic: vehicle 0 drives unless ``movers`` says who does, ``None``: every vehicle);
    ``kwargs`` as :class:`~cv2x_marl.env.mobility_env.MobilityEnv`, over the defaults. A PettingZoo id gives
    the object ``pettingzoo.make("parallel", env_id)`` gives (its class and metadata name; tested)."""
    from cv2x_marl.env.mobility_env import MobilityEnv
    from cv2x_marl.env.options import VERSION_DEFAULTS

    version = env_version(env_id)
    if env_id in SINGLE_MOVER_IDS:
        return MobilityEnv(**{**VERSION_DEFAULTS[version], **kwargs, "movers": [0]})
    factory: Callable[..., MobilityEnv] = globals()[f"parallel_env{_PETTINGZOO_SUFFIX[env_id]}"]
    return factory(**kwargs)


# -- PettingZoo factories (the entry points of cv2x/Mobility-vN) ------------------------------------


def parallel_env(**kwargs: Any) -> MobilityEnv:
    """``cv2x/Mobility-v0``: the ParallelEnv; keyword arguments as :class:`MobilityEnv`."""
    from cv2x_marl.env.mobility_env import MobilityEnv

    return MobilityEnv(**kwargs)


def parallel_env_v1(**kwargs: Any) -> MobilityEnv:
    """``cv2x/Mobility-v1``: the ParallelEnv with observation version 1 and improvement rewards."""
    from cv2x_marl.env.mobility_env import mobility_v1

    return mobility_v1(**kwargs)


def parallel_env_v2(**kwargs: Any) -> MobilityEnv:
    """``cv2x/Mobility-v2``: the ParallelEnv with observation version 2 and improvement rewards."""
    from cv2x_marl.env.mobility_env import mobility_v2

    return mobility_v2(**kwargs)


def parallel_env_v3(**kwargs: Any) -> MobilityEnv:
    """``cv2x/Mobility-v3``: the ParallelEnv with the plan-free observation version 3 and the shadowing field."""
    from cv2x_marl.env.mobility_env import MobilityEnvV3

    return MobilityEnvV3(**kwargs)


def parallel_env_cooperative(**kwargs: Any) -> MobilityEnv:
    """``cv2x/Cooperative-v0``: every vehicle moves, reward the team objective, observation version 3."""
    from cv2x_marl.env.mobility_env import CooperativeEnv

    return CooperativeEnv(**kwargs)


def parallel_env_traffic(**kwargs: Any) -> MobilityEnv:
    """``cv2x/Traffic-v0`` as a ParallelEnv: vehicles drive the lane model, vehicle 0 commands its speed and lane
    (``movers=None``: every vehicle drives its own, each rewarded with its own period utility)."""
    from cv2x_marl.env.traffic_parallel import TrafficParallelEnv

    return TrafficParallelEnv(**kwargs)


def parallel_env_traffic_v1(**kwargs: Any) -> MobilityEnv:
    """``cv2x/Traffic-v1`` as a ParallelEnv: ``cv2x/Traffic-v0`` with observation version 4 (what each agent
    measured on the road); ``movers`` as :func:`parallel_env_traffic`."""
    from cv2x_marl.env.traffic_parallel import TrafficParallelEnvV1

    return TrafficParallelEnvV1(**kwargs)


def raw_env(**kwargs: Any) -> Any:
    """AEC version of ``cv2x/Mobility-v0`` without wrappers."""
    from pettingzoo.utils.conversions import parallel_to_aec_wrapper

    return parallel_to_aec_wrapper(parallel_env(**kwargs))


def env(**kwargs: Any) -> Any:
    """AEC version of ``cv2x/Mobility-v0`` with the order-enforcing wrapper (what ``parallel_to_aec`` returns)."""
    from pettingzoo.utils.conversions import parallel_to_aec

    return parallel_to_aec(parallel_env(**kwargs))


def env_v1(**kwargs: Any) -> Any:
    """AEC version of ``cv2x/Mobility-v1`` with the order-enforcing wrapper."""
    from pettingzoo.utils.conversions import parallel_to_aec

    return parallel_to_aec(parallel_env_v1(**kwargs))


def env_v2(**kwargs: Any) -> Any:
    """AEC version of ``cv2x/Mobility-v2`` with the order-enforcing wrapper."""
    from pettingzoo.utils.conversions import parallel_to_aec

    return parallel_to_aec(parallel_env_v2(**kwargs))


def env_v3(**kwargs: Any) -> Any:
    """AEC version of ``cv2x/Mobility-v3`` with the order-enforcing wrapper."""
    from pettingzoo.utils.conversions import parallel_to_aec

    return parallel_to_aec(parallel_env_v3(**kwargs))


def env_cooperative(**kwargs: Any) -> Any:
    """AEC version of ``cv2x/Cooperative-v0`` with the order-enforcing wrapper."""
    from pettingzoo.utils.conversions import parallel_to_aec

    return parallel_to_aec(parallel_env_cooperative(**kwargs))


def env_traffic(**kwargs: Any) -> Any:
    """AEC version of ``cv2x/Traffic-v0`` with the order-enforcing wrapper."""
    from pettingzoo.utils.conversions import parallel_to_aec

    return parallel_to_aec(parallel_env_traffic(**kwargs))


def env_traffic_v1(**kwargs: Any) -> Any:
    """AEC version of ``cv2x/Traffic-v1`` with the order-enforcing wrapper."""
    from pettingzoo.utils.conversions import parallel_to_aec

    return parallel_to_aec(parallel_env_traffic_v1(**kwargs))


# -- registration -----------------------------------------------------------------------------------


def _register_gymnasium() -> None:
    import gymnasium

    for version, env_id in zip(VERSIONS, SINGLE_MOVER_IDS, strict=True):
        cls, vector_cls = _GYM_CLASSES[version]
        if env_id not in gymnasium.registry:
            gymnasium.register(
                id=env_id,
                entry_point=f"cv2x_marl.env.single:{cls}",
                vector_entry_point=f"cv2x_marl.env.vector:{vector_cls}",
            )
    for env_id in TRAFFIC_IDS:
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point=f"cv2x_marl.env.single:{_TRAFFIC_CLASSES[env_id]}")


def _register_pettingzoo() -> None:
    import pettingzoo

    for env_id, suffix in _PETTINGZOO_SUFFIX.items():
        for kind, entry in (("parallel", f"cv2x_marl.env:parallel_env{suffix}"), ("aec", f"cv2x_marl.env:env{suffix}")):
            registry = pettingzoo.parallel_registry if kind == "parallel" else pettingzoo.aec_registry
            if env_id not in registry:
                pettingzoo.register(kind, env_id, entry_point=entry)


class _RegisterAfter(importlib.abc.Loader):
    """Loader wrapper: executes the module with its own loader, then registers our ids in it."""

    def __init__(self, loader: importlib.abc.Loader, register: Callable[[], None]) -> None:
        self._loader, self._register = loader, register

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType | None:
        return self._loader.create_module(spec)

    def exec_module(self, module: types.ModuleType) -> None:
        self._loader.exec_module(module)
        self._register()


class _RegisterOnImport(importlib.abc.MetaPathFinder):
    """Registers our ids when Gymnasium / PettingZoo is imported, so that ``import cv2x_marl`` (and the
    CLI's start) does not import them (about 0.2 s) while ``gymnasium.make("cv2x/...")`` still works
    whichever of the two packages is imported first."""

    def __init__(self, hooks: dict[str, Callable[[], None]]) -> None:
        self._hooks = hooks
        self._busy: set[str] = set()

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: types.ModuleType | None = None
    ) -> importlib.machinery.ModuleSpec | None:
        if fullname not in self._hooks or fullname in self._busy:
            return None
        self._busy.add(fullname)
        try:
            spec = importlib.util.find_spec(fullname)  # the real spec, from the finders after us
        finally:
            self._busy.discard(fullname)
        if spec is None or spec.loader is None:
            return None
        register = self._hooks.pop(fullname)
        if not self._hooks and self in sys.meta_path:
            sys.meta_path.remove(self)
        spec.loader = _RegisterAfter(spec.loader, register)
        return spec


def register_envs() -> None:
    """Register our ids now in whichever of Gymnasium / PettingZoo is imported, later in the other."""
    later: dict[str, Callable[[], None]] = {}
    for name, register in (("gymnasium", _register_gymnasium), ("pettingzoo", _register_pettingzoo)):
        if name in sys.modules:
            register()
        elif importlib.util.find_spec(name) is not None:  # base dependencies; a broken install registers nothing
            later[name] = register
    if later:
        sys.meta_path.insert(0, _RegisterOnImport(later))
