"""cv2x_marl: controlled mobility in C-V2X sidelink Mode 4 networks.

Importing the package registers ``cv2x/Mobility-v0``, ``-v1``, ``-v2`` with PettingZoo and
``cv2x/SingleMover-v0``, ``-v1``, ``-v2`` with Gymnasium (both are base dependencies; the simulator
itself, ``cv2x_marl.sim``, never imports them): at once in a package already imported, else when it
is imported (an import hook), so importing ``cv2x_marl`` alone does not import either. Entry points
are import strings, so a fresh process (a Ray worker, a subprocess) resolves the Gymnasium ids with
``gymnasium.make("cv2x_marl:cv2x/SingleMover-v2")``, which imports the package first;
``gymnasium.make_vec(id, num_envs=K, vectorization_mode="vector_entry_point")`` gives K copies
stepped by one compiled call (:mod:`cv2x_marl.env.vector`); PettingZoo has no such syntax:
frameworks take the factories ``cv2x_marl.env.parallel_env`` / ``parallel_env_v1`` / ``parallel_env_v2`` instead.
"""

__version__ = "0.1.0"

import importlib.abc
import importlib.machinery
import importlib.util
import sys
import types
from collections.abc import Callable, Sequence


def _register_gymnasium() -> None:
    import gymnasium

    for version, cls in (("v0", "SingleMoverEnv"), ("v1", "SingleMoverEnvV1"), ("v2", "SingleMoverEnvV2")):
        if f"cv2x/SingleMover-{version}" not in gymnasium.registry:
            gymnasium.register(
                id=f"cv2x/SingleMover-{version}",
                entry_point=f"cv2x_marl.env.single:{cls}",
                vector_entry_point=f"cv2x_marl.env.vector:{cls.replace('Env', 'VectorEnv')}",
            )


def _register_pettingzoo() -> None:
    import pettingzoo

    for version in ("v0", "v1", "v2"):
        env_id = f"cv2x/Mobility-{version}"
        suffix = "" if version == "v0" else f"_{version}"
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


def _register_envs() -> None:
    """Register our ids now in whichever of Gymnasium / PettingZoo is imported, later in the other."""
    later: dict[str, Callable[[], None]] = {}
    for name, register in (("gymnasium", _register_gymnasium), ("pettingzoo", _register_pettingzoo)):
        if name in sys.modules:
            register()
        elif importlib.util.find_spec(name) is not None:  # base dependencies; a broken install registers nothing
            later[name] = register
    if later:
        sys.meta_path.insert(0, _RegisterOnImport(later))


_register_envs()
