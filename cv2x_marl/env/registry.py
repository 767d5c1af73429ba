"""The env ids in one table (:data:`SPECS`), and everything derived from it: the parallel env of an id
(:func:`make_parallel_env`, the one way every route builds it), the PettingZoo factories (:data:`FACTORIES`) and
the Gymnasium / PettingZoo registration. The defaults of each id are
:data:`~cv2x_marl.env.defaults.VERSION_DEFAULTS`:

    cv2x/Mobility-vN      PettingZoo, every mover an agent
    cv2x/SingleMover-vN   Gymnasium, vehicle 0 the only mover (:class:`~cv2x_marl.env.single.SingleMoverEnv`);
                          batched by :class:`~cv2x_marl.env.vector.SingleMoverVectorEnv`
                          (``gymnasium.make_vec(..., "vector_entry_point")``)
    cv2x/Cooperative-v0   PettingZoo, every vehicle moves for the team objective (v3 observations)
    cv2x/Cooperative-v1   Cooperative-v0 with the coordination channel: the AEC API in the order of the vehicles'
                          transmission subframes, each seeing the moves announced before it
                          (:mod:`~cv2x_marl.env.turns`)
    cv2x/Traffic-v0       Gymnasium and PettingZoo: vehicles drive (lane model), vehicle 0 commands its speed and
                          lane (``movers=None`` in PettingZoo: every vehicle drives its own)
    cv2x/Traffic-v1       Traffic-v0 observing what the mover measured on the road (observation version 4)

Every id is one :class:`~cv2x_marl.env.mobility_env.MobilityEnv` with the id's options and metadata name; the
Gymnasium ids are :class:`~cv2x_marl.env.single.SingleMoverEnv` with ``env_id`` (registered with
``kwargs={"env_id": ...}``), the PettingZoo ids :func:`make_parallel_env` / :func:`make_aec_env` with ``env_id``.
Adding an id is a row of :data:`SPECS` and its defaults in :data:`~cv2x_marl.env.defaults.VERSION_DEFAULTS`.

``import cv2x_marl`` calls :func:`register_envs`: the ids are registered at once in whichever of
Gymnasium / PettingZoo is already imported, else when it is imported (an import hook), so importing
``cv2x_marl`` (and starting the CLI) imports neither (about 0.2 s). Entry points are import strings,
so a fresh process (a Ray worker, a subprocess) resolves the Gymnasium ids with
``gymnasium.make("cv2x_marl:cv2x/SingleMover-v2")``, which imports the package first; PettingZoo has
no such syntax: frameworks take the factories (``parallel_env``, ``parallel_env_v1`` .. ``parallel_env_v3``,
``parallel_env_cooperative``, ``parallel_env_cooperative_v1``, ``parallel_env_traffic``, ``parallel_env_traffic_v1``
and their AEC ``env*``, also attributes of :mod:`cv2x_marl.env`) instead.

This module imports only the standard library (and the defaults table) at its top, so the CLI reads
:data:`ENV_IDS` for its
``--env`` choices without importing the env (about 0.9 s measured: PettingZoo, numba, the simulator);
the factories import :mod:`cv2x_marl.env.mobility_env` when called.
"""

from __future__ import annotations

import functools
import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import types
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from cv2x_marl.env.defaults import VERSION_DEFAULTS

if TYPE_CHECKING:
    from cv2x_marl.env.mobility_env import MobilityEnv


@dataclass(frozen=True)
class EnvSpec:
    """One registered env id: its registrations, :func:`make_parallel_env`, the factories and the tests derive
    from this row of :data:`SPECS`.

    Attributes:
        env_id: the id (``cv2x/<Family>-v<N>``).
        defaults: its key in :data:`~cv2x_marl.env.defaults.VERSION_DEFAULTS` (the options it fixes).
        frameworks: where it is registered: ``gymnasium`` (vehicle 0's view, :class:`~cv2x_marl.env.single.
            SingleMoverEnv`), ``pettingzoo`` (every vehicle an agent, parallel and AEC).
        movers: who moves: ``arguments`` (``movers``; default every vehicle), ``vehicle0`` (always vehicle 0;
            ``movers`` refused by the Gymnasium env, overridden by :func:`make_parallel_env`), ``vehicle0-default``
            (vehicle 0 unless ``movers`` says who; ``None``: every vehicle).
        factory: the suffix of its PettingZoo factories in :mod:`cv2x_marl.env` (``parallel_env{factory}``,
            ``env{factory}``); None: none (a Gymnasium-only id).
        vector: whether Gymnasium's ``vector_entry_point`` batches K copies (:mod:`cv2x_marl.env.vector`).
        summary: one line for listings.
    """

    env_id: str
    defaults: str
    frameworks: tuple[str, ...]
    movers: str
    factory: str | None
    vector: bool
    summary: str

    @property
    def name(self) -> str:
        """The metadata name (``cv2x_<family>_v<N>``)."""
        return "cv2x_" + self.env_id.split("/", 1)[1].lower().replace("-", "_")


def _versions(family: str, frameworks: tuple[str, ...], movers: str, vector: bool, summary: str) -> list[EnvSpec]:
    return [
        EnvSpec(
            f"cv2x/{family}-{v}",
            v,
            frameworks,
            movers,
            ("" if v == "v0" else f"_{v}") if "pettingzoo" in frameworks else None,
            vector,
            f"{summary}, {text}",
        )
        for v, text in (
            ("v0", "the paper's observation"),
            ("v1", "observation version 1, improvement rewards"),
            ("v2", "observation version 2 (the sensing plan), improvement rewards"),
            ("v3", "plan-free observation version 3, shadowing that follows the movers"),
        )
    ]


#: every registered id, oldest family and version first (the CLI lists them newest first)
SPECS: tuple[EnvSpec, ...] = (
    *(
        s
        for pair in zip(
            _versions("Mobility", ("pettingzoo",), "arguments", False, "PettingZoo, every mover an agent"),
            _versions("SingleMover", ("gymnasium",), "vehicle0", True, "Gymnasium, vehicle 0 the only mover"),
            strict=True,
        )
        for s in pair
    ),
    EnvSpec(
        "cv2x/Cooperative-v0",
        "cooperative-v0",
        ("pettingzoo",),
        "arguments",
        "_cooperative",
        False,
        "PettingZoo, every vehicle moves for the team objective (observation version 3)",
    ),
    EnvSpec(
        "cv2x/Cooperative-v1",
        "cooperative-v1",
        ("pettingzoo",),
        "arguments",
        "_cooperative_v1",
        False,
        "Cooperative-v0 with the coordination channel: the AEC API takes the vehicles in the order of their "
        "transmission subframes, each observing the moves announced earlier in the period",
    ),
    EnvSpec(
        "cv2x/Traffic-v0",
        "traffic-v0",
        ("gymnasium", "pettingzoo"),
        "vehicle0-default",
        "_traffic",
        False,
        "vehicles drive the lane model, vehicle 0 commands its speed and lane",
    ),
    EnvSpec(
        "cv2x/Traffic-v1",
        "traffic-v1",
        ("gymnasium", "pettingzoo"),
        "vehicle0-default",
        "_traffic_v1",
        False,
        "Traffic-v0 observing what the mover measured on the road (observation version 4)",
    ),
    EnvSpec(
        "cv2x/Resource-v0",
        "resource-v0",
        ("gymnasium", "pettingzoo"),
        "arguments",
        "_resource",
        False,
        "vehicles drive; each vehicle that reselects its SPS resource picks it from its sensed candidate list",
    ),
)
#: the rows of :data:`SPECS` by id
SPEC: Mapping[str, EnvSpec] = MappingProxyType({s.env_id: s for s in SPECS})
#: every id, oldest version first (the CLI lists them newest first: ``ENV_IDS[::-1]``)
ENV_IDS = tuple(SPEC)
#: the env versions of the Mobility / SingleMover families
VERSIONS = ("v0", "v1", "v2", "v3")
#: the PettingZoo ids of the Mobility family (every mover an agent)
MOBILITY_IDS = tuple(i for i in ENV_IDS if i.startswith("cv2x/Mobility-"))
#: the Gymnasium ids of the SingleMover family (vehicle 0 the only mover)
SINGLE_MOVER_IDS = tuple(i for i in ENV_IDS if i.startswith("cv2x/SingleMover-"))
#: the cooperative task (PettingZoo; every vehicle moves, team reward)
COOPERATIVE_IDS = tuple(i for i in ENV_IDS if i.startswith("cv2x/Cooperative-"))
#: the traffic task and its variant observing what the mover measured (Gymnasium and PettingZoo)
TRAFFIC_IDS = tuple(i for i in ENV_IDS if i.startswith("cv2x/Traffic-"))
#: the resource task (Gymnasium and PettingZoo; every vehicle chooses its SPS resource)
RESOURCE_IDS = tuple(i for i in ENV_IDS if i.startswith("cv2x/Resource-"))
#: the id commands run when none is given (the benchmark's single-mover task)
DEFAULT_ENV_ID = "cv2x/SingleMover-v3"


def spec_of(env_id: str) -> EnvSpec:
    """The row of a registered id; an unknown id is refused with the list."""
    if env_id not in SPEC:
        raise ValueError(f"unknown env id {env_id!r}; ids: {', '.join(ENV_IDS)}")
    return SPEC[env_id]


def env_version(env_id: str) -> str:
    """The key of a registered id's defaults in :data:`~cv2x_marl.env.defaults.VERSION_DEFAULTS` (``v0`` ..
    ``v3``; ``cooperative-v0`` / ``-v1``; ``traffic-v0`` / ``traffic-v1``); unknown ids are refused with the list."""
    return spec_of(env_id).defaults


def make_parallel_env(env_id: str, **kwargs: Any) -> MobilityEnv:
    """The parallel env of a registered id (what ``pettingzoo.make("parallel", env_id)`` builds, and what the
    Gymnasium id wraps): :class:`~cv2x_marl.env.mobility_env.MobilityEnv` with the id's defaults, its movers
    (:attr:`EnvSpec.movers`) and its metadata name; ``kwargs`` as ``MobilityEnv``, over the defaults. Where the id
    sets scenario ``overrides`` of its own (``cv2x/Resource-v0``'s SPS procedures), those given are applied after
    them (a later assignment of a key wins), not instead."""
    from cv2x_marl.env.mobility_env import MobilityEnv

    spec = spec_of(env_id)
    defaults = VERSION_DEFAULTS[spec.defaults]
    options = {**defaults}
    if spec.movers == "vehicle0-default":
        options["movers"] = [0]
    given = kwargs.get("overrides")
    own = defaults.get("overrides")
    if own is not None and (isinstance(given, str) or _strings(given)):  # the id's, then the caller's
        extra: tuple[str, ...] = (given,) if isinstance(given, str) else tuple(given or ())
        kwargs = {**kwargs, "overrides": (*own, *extra)}
    options.update(kwargs)
    if spec.movers == "vehicle0":
        options["movers"] = [0]
    env = MobilityEnv(**options)
    env.metadata = {**MobilityEnv.metadata, "name": spec.name}  # type: ignore[misc]  # per id, on the instance
    return env


def _strings(value: Any) -> bool:
    """Whether ``value`` is a list or tuple of strings (scenario overrides to append to an id's own)."""
    return isinstance(value, list | tuple) and all(isinstance(v, str) for v in value)


def make_aec_env(env_id: str, **kwargs: Any) -> Any:
    """The AEC version of :func:`make_parallel_env` with PettingZoo's order-enforcing wrapper: ``parallel_to_aec``,
    or with ``decision_order="subframe"`` (``cv2x/Cooperative-v1``) :class:`~cv2x_marl.env.turns.SubframeAECEnv`
    (the agents in the order of their transmission subframes, each seeing the moves announced before it)."""
    from pettingzoo.utils.conversions import parallel_to_aec

    par = make_parallel_env(env_id, **kwargs)
    if par.options.decision_order == "subframe":
        from cv2x_marl.env.turns import subframe_aec

        return subframe_aec(par)
    return parallel_to_aec(par)


def raw_env(**kwargs: Any) -> Any:
    """AEC version of ``cv2x/Mobility-v0`` without wrappers."""
    from pettingzoo.utils.conversions import parallel_to_aec_wrapper

    return parallel_to_aec_wrapper(make_parallel_env("cv2x/Mobility-v0", **kwargs))


#: the PettingZoo factories by name (``parallel_env{suffix}``, ``env{suffix}`` of :attr:`EnvSpec.factory`): what
#: frameworks without a registry take (RLlib, TorchRL); module attributes of this module and of :mod:`cv2x_marl.env`
FACTORIES: Mapping[str, Callable[..., Any]] = MappingProxyType(
    {
        f"{kind}{s.factory}": functools.partial(make, s.env_id)
        for s in SPECS
        if s.factory is not None
        for kind, make in (("parallel_env", make_parallel_env), ("env", make_aec_env))
    }
)


def __getattr__(name: str) -> Any:
    if name in FACTORIES:
        return FACTORIES[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# -- registration -----------------------------------------------------------------------------------


def _register_gymnasium() -> None:
    import gymnasium

    for spec in SPECS:
        if "gymnasium" in spec.frameworks and spec.env_id not in gymnasium.registry:
            gymnasium.register(
                id=spec.env_id,
                entry_point="cv2x_marl.env.single:SingleMoverEnv",
                vector_entry_point="cv2x_marl.env.vector:SingleMoverVectorEnv" if spec.vector else None,
                kwargs={"env_id": spec.env_id},
            )


def _register_pettingzoo() -> None:
    import pettingzoo

    for spec in SPECS:
        if "pettingzoo" not in spec.frameworks:
            continue
        for kind, entry in (("parallel", "make_parallel_env"), ("aec", "make_aec_env")):
            registry = pettingzoo.parallel_registry if kind == "parallel" else pettingzoo.aec_registry
            if spec.env_id not in registry:
                pettingzoo.register(
                    kind, spec.env_id, entry_point=f"cv2x_marl.env.registry:{entry}", kwargs={"env_id": spec.env_id}
                )


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
